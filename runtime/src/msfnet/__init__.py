"""msfnet: edge deployment toolkit for the MSF-Net photometric-stereo network.

The parts follow the data flow, one top-level folder each (``<part>/src/msfnet/<part>``):
``calib`` (lights, capture) -> ``runtime`` (stack, normalise, infer, outputs; torch-free)
<- ``export`` (checkpoint -> ONNX) <- ``model`` (the exact torch network, training), with
``synth`` (synthetic stacks) for training, tests and the demo, and ``bench`` on top.
"""

from pkgutil import extend_path

# In a checkout's editable install each part is its own source root on sys.path: gather the
# ``msfnet`` folders of all of them (an installed wheel has just one).
__path__ = extend_path(__path__, __name__)

__version__ = "0.2.0"
