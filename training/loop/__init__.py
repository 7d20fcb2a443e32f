"""neumip.training.loop: training a material (`train`, its `config`, `losses`, `blur` schedule,
`checkpoint`), validating it and writing its outputs, and the whole `fit` from maps to model."""
