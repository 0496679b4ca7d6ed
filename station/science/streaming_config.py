"""Every constant of the martinez2022 section 3.3 method, in one configurable dataclass.

Why a module of its own: the same constants are read by the streaming segment detector
(streaming), the end-of-test computation of TDB/TDSF (drift_coefficients) and the offline analyses
that replay the detector's gate (offline_fit, residual, thermal_calibration). The detector's
`result()` uses the end-of-test computation, so the constants can live in neither of those two
without an import circle; here every user imports them from below.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class StreamingConfig:
    """Every constant of martinez2022 section 3.3, configurable."""

    alpha_acc: float = 0.05  # exponential filter on all measurements (3 axes and temperature)
    alpha_gradient: float = 0.01  # exponential filter on the thermal gradient
    gradient_limit_c_per_min: float = 1.0  # logging allowed while |gradient| < this
    discard_samples: int = 500  # stable samples discarded before averaging
    average_samples: int = 1000  # samples averaged into one segment
    segment_delta_c: float = 20.0  # temperature change from the last saved segment = new segment
    orientation_delta_g: float = 0.8  # every axis moving more than this = new orientation
    gradient_reset_c_per_min: float = 10.0  # "high value" the gradient is reset to (and starts at)
    gradient_reset_signed: bool = True  # reset toward the change's direction (see module docstring)
    t_ref_c: float = 25.0  # reference temperature of eq. 1
    clamp_positive_tdsf: bool = True  # TDSF is physically negative: positive -> 0 (flagged)
    detect_orientation_while_logging: bool = True  # see module docstring
    min_pair_delta_c: float | None = None  # TD_i pairs need this temperature gap (None: delta / 2)

    def pair_delta_c(self) -> float:
        return self.segment_delta_c / 2.0 if self.min_pair_delta_c is None else self.min_pair_delta_c


__all__ = [
    "StreamingConfig",
]
