"""neumip.server: the FastAPI + ONNX Runtime batch-inference service."""
