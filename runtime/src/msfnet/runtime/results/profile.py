"""Per-stage latency over repeated runs, peak RSS and achieved GFLOP/s, as JSON and a table."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from msfnet.runtime.instrument import STAGES, StageTimer, peak_rss_mb


@dataclass
class Profile:
    runs: list[dict[str, float]] = field(default_factory=list)
    flops: float = 0.0  # per run, executed by the inference stage (0 for --method l2)
    info: dict[str, object] = field(default_factory=dict)

    def add(self, timer: StageTimer) -> None:
        self.runs.append(dict(timer.seconds))

    def median_s(self, stage: str) -> float:
        return float(np.median([r.get(stage, 0.0) for r in self.runs])) if self.runs else 0.0

    def summary(self) -> dict[str, object]:
        stages: dict[str, dict[str, float]] = {}
        for stage in STAGES:
            vals = np.array([r.get(stage, 0.0) for r in self.runs], np.float64)
            stages[stage] = {
                "median_s": float(np.median(vals)),
                "p90_s": float(np.percentile(vals, 90)),
                "min_s": float(vals.min()),
            }
        infer = stages["inference"]["median_s"]
        gflops = self.flops / infer / 1e9 if self.flops and infer > 0 else None
        return {
            "repeat": len(self.runs),
            "stages": stages,
            "peak_rss_mb": peak_rss_mb(),
            "inference_gflop": self.flops / 1e9,
            "inference_gflops_per_s": gflops,
            "runs": self.runs,
            **self.info,
        }

    def table(self) -> str:
        s = self.summary()
        stages = s["stages"]
        assert isinstance(stages, dict)
        lines = [f"{'stage':<12} {'median s':>10} {'p90 s':>10}   (repeat {s['repeat']})"]
        for stage, t in ((stage, stages[stage]) for stage in STAGES):
            lines.append(f"{stage:<12} {t['median_s']:>10.3f} {t['p90_s']:>10.3f}")
        lines.append(f"peak RSS     {s['peak_rss_mb']:>10.0f} MB")
        if s["inference_gflops_per_s"] is not None:
            lines.append(
                f"inference    {s['inference_gflops_per_s']:>10.1f} GFLOP/s "
                f"({s['inference_gflop']:.0f} GFLOP per run)"
            )
        return "\n".join(lines)


@dataclass(frozen=True)
class BatchStats:
    """How a stack of a batch was fed to the model (profile.json's "batch")."""

    decode_s: float  # reading and decoding the stack
    wait_s: float | None = None  # how long the model waited for it (prefetching hides decode)
    prefetched: bool | None = None  # decoded while the previous stack ran
    worker: str | None = None  # host:pid of the Ray worker that ran it

    def as_dict(self) -> dict[str, object]:
        return {k: v for k, v in asdict(self).items() if v is not None}


__all__ = ["BatchStats", "Profile"]
