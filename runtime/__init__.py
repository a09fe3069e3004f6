"""The torch-free edge runtime: stack I/O, normalisation, ONNX Runtime inference, outputs."""

from .errors import InputError
from .stack import Stack, load_stack, save_stack

__all__ = ["InputError", "Stack", "load_stack", "save_stack"]
