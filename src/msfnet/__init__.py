"""msfnet: edge deployment toolkit for the MSF-Net photometric-stereo network.

The sub-packages follow the data flow:
``calib`` (lights, capture) -> ``runtime`` (stack, normalise, infer, outputs; torch-free)
with ``model`` (the exact torch network, checkpoints, training), ``export`` (checkpoint -> ONNX),
``synth`` (synthetic stacks) and ``bench`` (CPU latency benchmarks) beside it.
"""

__version__ = "0.1.0"
