"""neumip.server: the FastAPI batch-inference service (ONNX Runtime, or drjit kernels: `engine`)."""
