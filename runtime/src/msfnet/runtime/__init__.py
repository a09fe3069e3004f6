"""The torch-free edge runtime: stack -> normalise -> infer (tiled) -> engines -> results.

Subpackages in data-flow order: ``stack`` (the Stack type, loaders, readers, selection,
real-camera transforms, writers), ``infer`` (the network's normalisation, memory-bounded tiling,
estimators: network, least squares, fine detail), ``engines`` (ONNX Runtime and OpenVINO behind
one interface, and the choice between them), ``results`` (result files, latency profile,
inspection maps), ``evaluate`` (metrics, detail ratio, benchmark datasets), ``batch`` (many
stacks, locally or on Ray) and ``cli`` (msf-run, msf-eval). ``api`` is the Python API (``Model``,
``Result``); ``contract`` holds what exporter and runtime agree on. The code map is
docs/design.md; what every part shares (files, CLI plumbing, errors) is in ``msfnet.common``.
"""
