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

__version__ = "0.2.0"

if TYPE_CHECKING:
    from msfnet.runtime.api import Model, Result
    from msfnet.runtime.stack import LoadOptions, Stack, load_stack

__all__ = ["LoadOptions", "Model", "Result", "Stack", "__version__", "load_stack"]


def __getattr__(name: str) -> object:
    # Lazy, so that `import msfnet.model` (training workers) does not load onnxruntime.
    if name in ("Model", "Result"):
        from msfnet.runtime import api as pipeline

        return getattr(pipeline, name)
    if name in ("LoadOptions", "Stack", "load_stack"):
        from msfnet.runtime import stack

        return getattr(stack, name)
    raise AttributeError(f"module 'msfnet' has no attribute {name!r}")
