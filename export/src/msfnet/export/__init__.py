"""Checkpoint -> ONNX export with self-verification (needs torch and onnx)."""
