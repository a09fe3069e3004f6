"""The estimator a model's settings ask for, built as layers around the base estimator.

The order is data (:data:`LAYERS`): each layer wraps what the ones before it built, so the
outermost runs first and sees the result of everything inside it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from msfnet.runtime.infer.detail_fusion import DetailFusionEstimator
from msfnet.runtime.infer.estimators import Estimator, NetworkEstimator
from msfnet.runtime.infer.fine_detail import FineDetailEstimator
from msfnet.runtime.infer.ladder import reduced_network
from msfnet.runtime.infer.tta import TTAEstimator


@dataclass(frozen=True)
class Layers:
    """The settings that wrap the base estimator (ModelOptions' fields of the same names)."""

    edge_context: bool = True
    speed: str = "full"
    fine_detail: bool = False
    tta: int = 1
    detail_fusion: bool = True


def _speed(est: Estimator, layers: Layers) -> Estimator:
    if not isinstance(est, NetworkEstimator):
        return est
    est.edge_context = layers.edge_context
    # the network on fewer pixels / lights; the detail fusion gives the detail back
    return reduced_network(est, layers.speed)


def _fine_detail(est: Estimator, layers: Layers) -> Estimator:
    if layers.fine_detail and isinstance(est, NetworkEstimator):
        return FineDetailEstimator(est)
    return est


def _tta(est: Estimator, layers: Layers) -> Estimator:
    return TTAEstimator(est, layers.tta) if layers.tta > 1 and est.method == "msf" else est


def _detail_fusion(est: Estimator, layers: Layers) -> Estimator:
    return DetailFusionEstimator(est) if layers.detail_fusion and est.method == "msf" else est


# innermost first: the turned copies (tta) average the network's part only, inside the fusion
LAYERS: tuple[Callable[[Estimator, Layers], Estimator], ...] = (
    _speed,
    _fine_detail,
    _tta,
    _detail_fusion,
)


def build_estimator(base: Estimator, layers: Layers) -> Estimator:
    """``base`` (the network or least squares) with every layer ``layers`` asks for."""
    est = base
    for layer in LAYERS:
        est = layer(est, layers)
    return est


__all__ = ["LAYERS", "Layers", "build_estimator"]
