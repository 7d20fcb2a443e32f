"""neumip.core: the ground floor every other area imports, and that imports none of them.

- `contract`: the query contract (layout of queries, answers and groups; the model file's metadata keys);
- `errors`: the root of neumip's user-facing errors;
- `config`: `MaterialConfig`, the architecture of one neural material;
- `head`: the decoder's output heads (their constants);
- `weights`: the weights' names and shapes, as the model holds them and as the exported graph stores them;
- `modelfile`: the one reader of a model file and its `ModelError` (`onnx_proto`: the ONNX bytes it reads);
- `files`: writing a file atomically.

Only numpy: importing `neumip.core` never imports torch, onnx, drjit or mitsuba.
"""
