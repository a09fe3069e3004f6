"""What ran, as one record (``Model.describe()``, ``Result.method``; profile.json holds its
``as_json()``): an engine fills in its fields, the network or least squares the method and the
model file, each layer around them (speed rung, fine detail, tta, detail fusion) its own, by
``dataclasses.replace`` on the inner one's record."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any


@dataclass(frozen=True, kw_only=True)
class RunMethod:
    """In profile.json's order. None is "not said", left out of :meth:`as_json`, but for
    ``threads`` (the engine's default), ``model`` and ``choice`` wherever ``method`` is said
    (least squares; no reason given) and ``chunk`` wherever ``graph`` is (all lights at once)."""

    method: str | None = None  # "msf" (the network) or "l2" (least squares); None: an engine's
    model: str | None = None
    engine: str | None = None  # onnxruntime, openvino, torch or numpy
    precision: str | None = None
    provider: str | None = None  # ONNX Runtime's execution provider
    device: str | None = None  # OpenVINO's device
    threads: int | None = None
    openvino: str | None = None  # OpenVINO's version
    graph: str | None = None  # monolithic or staged
    chunk: int | None = None  # lights per call through a staged graph
    choice: str | None = None  # why this engine and precision (engines.dispatch)
    edge_context: bool | None = None
    speed: str | None = None  # the speed rung's name, and what it runs
    speed_rung: str | None = None
    fine_detail: str | None = None
    tta: int | None = None  # dihedral copies averaged
    detail_fusion: str | None = None

    @classmethod
    def of_engine(cls, e: Any, **said: Any) -> RunMethod:
        """An engine's (base.Engine) name, precision, threads, graph and chunk, and ``said``."""
        g = "staged" if e.info.staged else "monolithic"
        return cls(
            engine=e.name, precision=e.precision, threads=e.threads, graph=g, chunk=e.chunk, **said
        )

    def as_json(self) -> dict[str, object]:
        said = {"threads", "model", "choice"} if self.method else {"threads"}
        said |= {"chunk"} if self.graph else set()
        return {k: v for k, v in asdict(self).items() if v is not None or k in said}


__all__ = ["RunMethod"]
