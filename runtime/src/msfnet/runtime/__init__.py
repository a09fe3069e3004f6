"""The torch-free edge runtime: stack -> normalise -> infer (tiled) -> metrics -> outputs.

Modules in data-flow order: ``stack`` (type, loaders, selection), ``preprocess`` (the network's
normalisation), ``tiling`` + ``infer`` (memory-bounded windows), ``session`` / ``chunked`` (ONNX
Runtime, plain and staged graphs), ``estimators`` (network and least squares behind one
protocol), ``metrics``, ``pipeline`` (``Model`` and ``Result``), ``outputs`` (files);
``contract`` holds what exporter and runtime agree on, ``files`` and ``cliutil`` what every
command shares.
"""
