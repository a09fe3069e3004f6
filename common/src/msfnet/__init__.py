"""msfnet: edge deployment toolkit for the MSF-Net photometric-stereo network.

    from msfnet import Model, load_stack
    result = Model()(load_stack("ballPNG"))     # bundled model; result.normals, result.metrics

The parts follow the data flow, one top-level folder each (``<part>/src/msfnet/<part>``):
``calib`` (lights, capture) -> ``runtime`` (stack, normalise, infer, outputs; torch-free)
<- ``export`` (checkpoint -> ONNX) <- ``model`` (the exact torch network, training), with
``synth`` (synthetic stacks; -> ``runtime``) for training, tests and the demo sample, and
``bench`` on top. One more arrow, ``calib -> synth`` (simulated rig only): ``msf-capture
--camera sim`` renders its scene with ``msfnet.synth.spheres``, imported lazily only when
the simulated rig is used (never by a capture with real hardware, nor by importing calib).
"""

from __future__ import annotations

from pkgutil import extend_path
from typing import TYPE_CHECKING

# In a checkout's editable install each part is its own source root on sys.path: gather the
# ``msfnet`` folders of all of them (an installed wheel has just one).
__path__ = extend_path(__path__, __name__)

# An msf-* command's first import: from here on, Ctrl-C while it is still loading (numpy,
# OpenCV, ONNX Runtime take a second or more) is one line, not a traceback. Standard library
# only, and a no-op in any other program.
from msfnet.common.signals import guard_startup as _guard_startup

_guard_startup()

if TYPE_CHECKING:
    __version__: str
    from msfnet.runtime.api import Model, Result, load_stack
    from msfnet.runtime.inspection.defects import DefectOptions
    from msfnet.runtime.inspection.station import Station
    from msfnet.runtime.results.maps import MapOptions
    from msfnet.runtime.stack import LoadOptions, Stack

__all__ = [
    "DefectOptions",
    "LoadOptions",
    "MapOptions",
    "Model",
    "Result",
    "Stack",
    "Station",
    "__version__",
    "load_stack",
]


def __getattr__(name: str) -> object:
    # Lazy, so that `import msfnet.model` (training workers) does not load onnxruntime, and
    # `from msfnet import Model` does not read package metadata (importlib.metadata: ~0.05 s).
    if name == "__version__":
        # written once, in pyproject.toml; read from the install's metadata ("0+unknown"
        # without one)
        from msfnet.common.version import installed_version

        return installed_version()
    if name in ("Model", "Result", "load_stack"):  # load_stack: errors in the API's words
        from msfnet.runtime import api as pipeline

        return getattr(pipeline, name)
    if name in ("LoadOptions", "Stack"):
        from msfnet.runtime import stack

        return getattr(stack, name)
    if name in ("Station", "DefectOptions"):  # Station(DefectOptions(depth=...)).inspect(part)
        from msfnet.runtime.inspection import defects, station

        return getattr(station if name == "Station" else defects, name)
    if name == "MapOptions":  # Model(maps=MapOptions(...)): which inspection maps, and how
        from msfnet.runtime.results.maps import MapOptions

        return MapOptions
    raise AttributeError(f"module 'msfnet' has no attribute {name!r}")
