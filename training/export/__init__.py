"""neumip.training.export: the material written as one ONNX graph (`graph`, with its stages `lod`,
`lookup`, `base`), read back (`read`, `upgrade`) and cut (`trim`). Needs numpy and onnx; torch only
to take weights from a trained material."""
