"""neumip.training: the NeuMIP model (pure torch), ground-truth generation, training and ONNX export."""
