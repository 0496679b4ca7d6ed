"""Verified drift error of a programmed DUT (design 4, program and verify; martinez2022 eqs. 10-12).

Pure science: arrays in, a VerificationResult out. The verification step heats the plate again
while the board outputs COMPENSATED counts (eq. 13 runs on the board with its own temperature).
This module turns those samples into:

  e_after_mg   eq. 10 on the compensated output: thermal sections are `section_c`-wide bins of the
               board temperature along the heating (time order = temperature order while heating);
               each step's |dAcc| is scaled to `full_range_c` by its own dT, as in the paper.
  e_before_mg  eq. 10 on the UNcompensated first-pass segments at the same orientation (the drift
               the part would show without its coefficients), scaled the same way.
  curvature    a quadratic fit of the compensated output against the board temperature. Linear
               TDB/TDSF compensation leaves a flat line on a part that follows eq. 1; a part with
               curved bias drift (bias_t2) leaves a parabola whose chord passes near the two
               calibration temperatures, so heating between them again can look "fine" at its ends.
               The bow of that parabola over the full range (|c2| (full_range/2)^2) is the residual
               drift the linear model cannot remove; it is named in the result.

Pass rule per axis (VerifyCriteria): e_after <= max(e_ratio_max * e_before, e_floor_mg) AND no
significant curvature (bow <= curvature_limit_mg or |c2| < curvature_sigma x its standard error).
The floor exists because an axis that hardly drifts (|TD| ~ 0.02 mg/C -> E_before ~ 1.4 mg) cannot
show a 4x reduction above the section noise; the default 2 mg over 70 C is 0.1 % of the +-1 g span.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from station.science.thermal_model import drift_error_fs_pct, drift_error_mg
from station.types import AXES


@dataclass(frozen=True)
class VerifyCriteria:
    e_ratio_max: float = 0.25  # verified E at most this fraction of the uncompensated E ...
    e_floor_mg: float = 2.0  # ... or at most this (axes that hardly drift)
    full_range_c: float = 70.0  # eq. 10 scaling (martinez2022: -10..60 C)
    section_c: float = 4.0  # width of a thermal section of the verification ramp
    min_section_samples: int = 20
    curvature_limit_mg: float = 4.0  # residual bow over the full range that flags a part (bias_t2 >= 0.005 mg/C^2 gives >= 6 mg)
    curvature_sigma: float = 4.0  # ... when also this many standard errors from zero
    min_rise_c: float = 10.0  # a verification that heated less cannot judge (flagged, not passed)

    def to_json(self) -> dict:
        return dict(self.__dict__)


@dataclass
class AxisVerification:
    axis: str
    e_before_mg: float | None
    e_after_mg: float
    ratio: float | None
    residual_range_mg: float  # max - min of the compensated section means over the verified ramp
    curvature_mg_per_c2: float
    curvature_sigma_mg_per_c2: float
    curvature_bow_mg: float  # |c2| (full_range/2)^2: residual drift a linear model leaves over the range
    curved: bool
    passed: bool
    reason: str = ""

    def to_json(self) -> dict:
        return dict(self.__dict__)


@dataclass
class VerificationResult:
    passed: bool
    axes: dict[str, AxisVerification]
    rise_c: float
    temp_from_c: float
    temp_to_c: float
    n_samples: int
    n_sections: int
    criteria: VerifyCriteria
    flags: list[str] = field(default_factory=list)

    @property
    def e_before_mg(self) -> dict[str, float | None]:
        return {a: v.e_before_mg for a, v in self.axes.items()}

    @property
    def e_after_mg(self) -> dict[str, float]:
        return {a: v.e_after_mg for a, v in self.axes.items()}

    def to_json(self) -> dict:
        return {
            "passed": self.passed,
            "flags": list(self.flags),
            "rise_c": self.rise_c,
            "temp_from_c": self.temp_from_c,
            "temp_to_c": self.temp_to_c,
            "n_samples": self.n_samples,
            "n_sections": self.n_sections,
            "e_before_mg": self.e_before_mg,
            "e_after_mg": self.e_after_mg,
            "e_after_fs_pct": {a: float(drift_error_fs_pct(v.e_after_mg)) for a, v in self.axes.items()},
            "axes": {a: v.to_json() for a, v in self.axes.items()},
            "criteria": self.criteria.to_json(),
        }


def temperature_sections(acc_g: np.ndarray, temp_c: np.ndarray, section_c: float, min_samples: int = 20):
    """Thermal sections of a heating ramp: samples binned by temperature, section_c wide, each
    section's mean acceleration (m, 3), mean temperature (m,) and sample count (m,), in temperature
    order. Bins with fewer than min_samples are left out."""
    acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    temp = np.asarray(temp_c, dtype=np.float64).reshape(-1)
    if len(temp) == 0:
        return np.empty((0, 3)), np.empty(0), np.empty(0, dtype=int)
    k = np.floor((temp - temp.min()) / section_c).astype(int)
    means, temps, counts = [], [], []
    for b in np.unique(k):
        m = k == b
        if m.sum() >= min_samples:
            means.append(acc[m].mean(axis=0))
            temps.append(temp[m].mean())
            counts.append(int(m.sum()))
    return np.array(means).reshape(-1, 3), np.array(temps), np.array(counts, dtype=int)


def drift_before_mg(segment_acc_g, segment_temp_c, full_range_c: float = 70.0) -> np.ndarray | None:
    """Eq. 10 on uncompensated first-pass segments of one orientation (time order). None if the
    segments do not span two temperatures."""
    acc = np.asarray(segment_acc_g, dtype=np.float64).reshape(-1, 3)
    temp = np.asarray(segment_temp_c, dtype=np.float64).reshape(-1)
    if len(temp) < 2:
        return None
    keep = np.concatenate([[True], np.abs(np.diff(temp)) > 1.0])  # consecutive sections must differ
    if keep.sum() < 2:
        return None
    return drift_error_mg(acc[keep], temp[keep], full_range_c)


def _quadratic(temp: np.ndarray, acc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """c2 (g/C^2) per axis and its standard error from an ordinary least-squares quadratic fit."""
    x = temp - temp.mean()
    X = np.stack([np.ones_like(x), x, x * x], axis=1)
    coef, *_ = np.linalg.lstsq(X, acc, rcond=None)
    resid = acc - X @ coef
    dof = max(len(x) - 3, 1)
    s2 = (resid**2).sum(axis=0) / dof
    cov = np.linalg.pinv(X.T @ X)
    return coef[2], np.sqrt(np.maximum(cov[2, 2] * s2, 0.0))


def verify_compensated(
    acc_g: np.ndarray,
    temp_c: np.ndarray,
    e_before_mg,
    criteria: VerifyCriteria | None = None,
) -> VerificationResult:
    """Judge the compensated output of one DUT over a verification heating ramp (see module doc).

    acc_g (n, 3) compensated samples in g, temp_c (n,) the board's temperature; e_before_mg (3,)
    or None: the uncompensated E of the same orientation from the first pass.
    """
    c = criteria or VerifyCriteria()
    acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    temp = np.asarray(temp_c, dtype=np.float64).reshape(-1)
    flags: list[str] = []
    n = len(temp)
    if n < 3 * c.min_section_samples:
        raise ValueError(f"verification needs at least {3 * c.min_section_samples} samples, got {n}")
    # the rise seen by the board: robust ends (medians of the first and last 5 %)
    k = max(5, n // 20)
    t_from, t_to = float(np.median(temp[:k])), float(np.median(temp[-k:]))
    rise = t_to - t_from
    sec_acc, sec_temp, _ = temperature_sections(acc, temp, c.section_c, c.min_section_samples)
    if len(sec_temp) >= 2:
        e_after = drift_error_mg(sec_acc, sec_temp, c.full_range_c)
        residual_range = (sec_acc.max(axis=0) - sec_acc.min(axis=0)) * 1e3
    else:
        e_after = np.full(3, np.nan)
        residual_range = np.full(3, np.nan)
        flags.append("fewer than two thermal sections in the verification")
    if rise < c.min_rise_c:
        flags.append(f"the verification heated only {rise:.1f} C (< {c.min_rise_c:g} C): drift not judged")
    c2, c2_se = _quadratic(temp, acc)
    half = c.full_range_c / 2.0
    eb = None if e_before_mg is None else np.asarray(e_before_mg, dtype=np.float64).reshape(3)
    axes: dict[str, AxisVerification] = {}
    for i, name in enumerate(AXES):
        before = None if eb is None or not np.isfinite(eb[i]) else float(eb[i])
        after = float(e_after[i])
        bow = abs(float(c2[i])) * half * half * 1e3
        sig = float(c2_se[i])
        curved = bow > c.curvature_limit_mg and abs(float(c2[i])) > c.curvature_sigma * sig
        limit = max(c.e_ratio_max * before, c.e_floor_mg) if before is not None else c.e_floor_mg
        reasons = []
        if not np.isfinite(after):
            reasons.append("no verified E")
        elif after > limit:
            reasons.append(f"verified E {after:.2f} mg > limit {limit:.2f} mg"
                           + (f" ({c.e_ratio_max:.0%} of {before:.2f} mg uncompensated)" if before is not None else ""))
        if curved:
            reasons.append(f"curved residual drift: {bow:.1f} mg over {c.full_range_c:g} C "
                           f"(quadratic {float(c2[i]) * 1e3:+.4f} mg/C^2): linear TDB/TDSF compensation does not hold")
        ok = not reasons and rise >= c.min_rise_c
        axes[name] = AxisVerification(
            axis=name,
            e_before_mg=before,
            e_after_mg=after,
            ratio=(after / before) if before else None,
            residual_range_mg=float(residual_range[i]),
            curvature_mg_per_c2=float(c2[i]) * 1e3,
            curvature_sigma_mg_per_c2=sig * 1e3,
            curvature_bow_mg=bow,
            curved=curved,
            passed=ok,
            reason="; ".join(reasons),
        )
        if reasons:
            flags.append(f"{name}: " + "; ".join(reasons))
    passed = all(a.passed for a in axes.values()) and rise >= c.min_rise_c
    return VerificationResult(passed, axes, rise, t_from, t_to, n, len(sec_temp), c, flags)


__all__ = ["VerifyCriteria", "AxisVerification", "VerificationResult", "verify_compensated",
           "drift_before_mg", "temperature_sections"]
