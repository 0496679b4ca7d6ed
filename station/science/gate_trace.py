"""The streaming calibrator's decisions sample by sample, over a whole record, for offline analyses.

Why a module of its own: the live station needs only the calibrator's saved segments. The offline
fit (offline_fit) and the residual analysis (residual) need, for every sample, what the gradient
gate and the orientation counter decided, so that they pick their samples by the calibrator's own
rule. That view is recorded by replaying the record through the calibrator's batch path with a
recorder attached; it lives here so that streaming.py stays the algorithm an MCU would run.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from station.science.streaming import StreamingCalibrator, _Recorder
from station.science.streaming_config import StreamingConfig
from contracts.types import Segment


@dataclass
class GateTrace:
    """Per-sample view of the calibrator's decisions, for the offline fit and for plots."""

    gradient_c_per_min: np.ndarray  # (n,) filtered gradient after resets
    orientation: np.ndarray  # (n,) orientation counter after this sample
    acc_filt_g: np.ndarray  # (n, 3)
    temp_filt_c: np.ndarray  # (n,)
    limit_c_per_min: float

    @property
    def stable(self) -> np.ndarray:
        return np.abs(self.gradient_c_per_min) < self.limit_c_per_min


def trace_gate(time_s, acc_g, temp_c, config: StreamingConfig | None = None) -> tuple[GateTrace, list[Segment]]:
    """Run the calibrator over a whole record and return its per-sample gate view and segments."""
    cal = StreamingCalibrator(config)
    rec = _Recorder()
    cal._run(time_s, acc_g, temp_c, rec)
    if not rec.grad:
        empty = np.empty(0)
        return GateTrace(empty, np.empty(0, dtype=np.int64), np.empty((0, 3)), empty,
                         cal.config.gradient_limit_c_per_min), []
    trace = GateTrace(
        np.concatenate(rec.grad),
        np.concatenate(rec.orient),
        np.concatenate(rec.acc),
        np.concatenate(rec.temp),
        cal.config.gradient_limit_c_per_min,
    )
    return trace, cal.segments


__all__ = [
    "GateTrace",
    "trace_gate",
]
