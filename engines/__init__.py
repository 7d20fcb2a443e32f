"""neumip.engines: the engines that answer queries from a model file, and the model folder.

- `folder`: a model folder, listed and loaded one way (`ModelFolder`; the server's registry builds on it);
- `local`: ONNX Runtime in process (`LocalMaterials`, one file's `Material`);
- `kernel`: the exported graph interpreted as drjit arithmetic (`onnx_kernel`, `onnx_ops`), in the
  render's own kernels or on numpy buffers; `llvm` finds the libLLVM drjit needs.

Engines import `neumip.core` only; the server and the client build on them. Importing this package
never imports torch or mitsuba.
"""
