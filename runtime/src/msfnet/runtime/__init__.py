"""The torch-free edge runtime: stack I/O, normalisation, ONNX Runtime inference, outputs."""

from .errors import InputError
from .stack import Stack, load_stack, save_stack

__all__ = ["InputError", "Stack", "load_stack", "run_stack", "save_stack"]


def __getattr__(name: str):
    # lazy: `run_stack` pulls in onnxruntime, which plain stack I/O users do not need
    if name == "run_stack":
        from .run import run_stack

        return run_stack
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
