"""Verified drift error of a programmed DUT (design 4, program and verify; martinez2022 eqs. 10-12).

Pure science: arrays in, a VerificationResult out. The verification step heats the plate again
while the board outputs COMPENSATED counts (eq. 13 runs on the board with its own temperature).
The heat spans only 15-20 C of the 70 C operating range, so eq. 10 on its own sections, scaled by
Full Range / dT, extrapolates each section's slope linearly: a part with curved drift whose chord
the linear compensation follows reads far too little (17-19 mg for a 31 mg part), and pure noise
reads more than zero (|dAcc| of noise is positive). This module instead:

  fit          the compensated output against the board temperature with a quadratic, on batch
               means (consecutive `block_s` blocks, so autocorrelated noise does not pass for
               signal); its covariance is the block scatter PLUS the bias wander between blocks
               (the part's structure function, offline_fit.BiasWander) through the fit's weights.
  e_after_mg   eq. 10 evaluated on that quadratic with infinitely fine sections over the product's
               operating range [range_centre_c -+ full_range_c/2] (-10..60 C): the total variation
               of the residual, integral |b1 + 2 b2 (T - Tm)| dT. Extrapolating the quadratic from
               the verified span to the range is the model's assumption; its uncertainty is carried.
  e_after_sigma_mg   the standard deviation of that E under the fit's covariance (Monte Carlo with
               a fixed seed: E is not differentiable where the residual slope changes sign).
               The estimate is bias-corrected (2 E(b) - mean E(b + d), floored at 0), so a pure
               noise input reads ~0 within its sigma instead of a positive "drift".
  e_before_mg  eq. 10 on the UNcompensated first-pass segments at the same orientation (the drift
               the part would show without its coefficients), scaled the same way.
  curvature    c2 of the same quadratic with its full sigma; bow |c2| (full_range/2)^2 is the
               residual drift the linear model cannot remove; it is named in the result.

Pass rule per axis (VerifyCriteria): E - e_sigma_k sigma_E <= max(e_ratio_max * e_before, e_floor_mg)
(an E significantly over the limit fails; the verdict judges E with its guard band on top) AND no
significant curvature (bow <= curvature_limit_mg or |c2| < curvature_sigma x its standard error)
AND the heat rose at least min_rise_c. The floor exists because an axis that hardly drifts
(|TD| ~ 0.02 mg/C -> E_before ~ 1.4 mg) cannot show a 4x reduction above the noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import math

import numpy as np

from station.science.offline_fit import NO_WANDER, BiasWander, wander_for
from station.science.part_noise import measure_part_noise
from station.science.thermal_model import drift_error_fs_pct, drift_error_mg
from contracts.types import AXES, T_REF_C


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
    range_centre_c: float = T_REF_C  # E is judged over range_centre_c +- full_range_c / 2 (-10..60 C)
    block_s: float = 10.0  # batch-means block of the verification fit
    e_sigma_k: float = 2.0  # the E rule fails an axis when E - k sigma is still over its limit
    odr_hz: float = 3.125  # sample rate assumed when the caller gives no sample times

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
    e_after_sigma_mg: float = float("nan")  # 1-sigma of e_after_mg (fit + wander, extrapolated)

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
            "e_after_sigma_mg": {a: v.e_after_sigma_mg for a, v in self.axes.items()},
            "e_after_fs_pct": {a: float(drift_error_fs_pct(v.e_after_mg)) for a, v in self.axes.items()},
            "e_after_fs_sigma_pct": {a: float(drift_error_fs_pct(v.e_after_sigma_mg)) for a, v in self.axes.items()},
            "range_c": [self.criteria.range_centre_c - self.criteria.full_range_c / 2.0,
                        self.criteria.range_centre_c + self.criteria.full_range_c / 2.0],
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


def total_variation_mg(b1_g_per_c, b2_g_per_c2, t_mean_c: float, low_c: float, high_c: float) -> np.ndarray:
    """Eq. 10 with infinitely fine sections over [low_c, high_c] of r(T) = b1 u + b2 u^2, u = T - t_mean_c:
    the mean |dr/dT| times the range = integral |b1 + 2 b2 u| dT (mg; broadcasts over b1, b2)."""
    b1 = np.asarray(b1_g_per_c, dtype=np.float64)
    b2 = np.asarray(b2_g_per_c2, dtype=np.float64)
    b1, b2 = np.broadcast_arrays(b1, b2)
    lo, hi = low_c - t_mean_c, high_c - t_mean_c

    def prim(u):
        return b1 * u + b2 * u * u

    with np.errstate(divide="ignore", invalid="ignore"):
        root = np.where(b2 != 0.0, -b1 / (2.0 * b2), np.inf)
    inside = (root > lo) & (root < hi)
    r = np.where(inside, root, lo)
    tv = np.where(inside, np.abs(prim(r) - prim(lo)) + np.abs(prim(hi) - prim(r)), np.abs(prim(hi) - prim(lo)))
    return tv * 1e3


def _white_ug_per_sqrt_hz(acc: np.ndarray, odr_hz: float) -> float:
    """White noise density from first differences (robust): the wander class of the verified part."""
    if acc.shape[0] < 10:
        return float("nan")
    d = np.diff(acc, axis=0)
    sd = 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0) / math.sqrt(2.0)
    return float(np.mean(sd)) / math.sqrt(odr_hz / 2.0) * 1e6


def verified_drift_error(acc_g, temp_c, time_s, criteria: VerifyCriteria, wander: BiasWander = NO_WANDER,
                         n_draws: int = 4000) -> dict:
    """E over the operating range from the quadratic of the compensated output (module doc).

    Returns per axis (3,) arrays: "e_mg" (bias-corrected), "e_raw_mg" (plug-in), "sigma_mg", "c2"
    and "c2_sigma" (g/C^2), plus "n_blocks". NaN where fewer than 5 blocks span the heat."""
    c = criteria
    acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    temp = np.asarray(temp_c, dtype=np.float64).reshape(-1)
    t = np.asarray(time_s, dtype=np.float64).reshape(-1)
    n = temp.shape[0]
    dt = float(np.median(np.diff(t))) if n > 1 else 1.0 / c.odr_hz
    nb = max(3, min(int(round(c.block_s / max(dt, 1e-9))), n // 12 if n >= 36 else 3))
    m = n // nb
    nan3 = np.full(3, np.nan)
    out = {"e_mg": nan3, "e_raw_mg": nan3, "sigma_mg": nan3, "c2": nan3, "c2_sigma": nan3, "n_blocks": m}
    if m < 5:
        return out
    sl = slice(n - m * nb, n)  # whole blocks, the latest samples (the start is the settle edge)
    bx = temp[sl].reshape(m, nb).mean(axis=1)
    by = acc[sl].reshape(m, nb, 3).mean(axis=1)
    bt = t[sl].reshape(m, nb).mean(axis=1)
    xm = float(bx.mean())
    u = bx - xm
    if np.ptp(u) <= 0:
        return out
    X = np.column_stack([np.ones(m), u, u * u])
    P = np.linalg.pinv(X)  # rows: the weights of b0, b1, b2 on the block means
    beta = P @ by  # (3, 3 axes)
    resid = by - X @ beta
    s2 = np.sum(resid * resid, axis=0) / max(m - 3, 1)
    lo = c.range_centre_c - c.full_range_c / 2.0
    hi = c.range_centre_c + c.full_range_c / 2.0
    # covariance of (b1, b2): block scatter (white + short-lag wander) + wander between blocks
    g = P[1:] @ P[1:].T
    d = wander.structure_g2(bt[:, None] - bt[None, :])
    w_cov = -0.5 * P[1:] @ d @ P[1:].T
    rng = np.random.default_rng(20220584)  # fixed: the same data give the same sigma
    z = rng.standard_normal((n_draws, 2))
    e_raw, e_hat, sig, c2s = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    for k in range(3):
        cov = s2[k] * g + w_cov
        cov = 0.5 * (cov + cov.T)
        lch = np.linalg.cholesky(cov + np.eye(2) * 1e-30 * max(1.0, float(np.trace(cov))))
        draws = beta[1:, k][None, :] + z @ lch.T
        e_d = total_variation_mg(draws[:, 0], draws[:, 1], xm, lo, hi)
        e_raw[k] = float(total_variation_mg(beta[1, k], beta[2, k], xm, lo, hi))
        e_hat[k] = max(2.0 * e_raw[k] - float(e_d.mean()), 0.0)
        sig[k] = float(e_d.std())
        c2s[k] = math.sqrt(max(cov[1, 1], 0.0))
    out.update(e_mg=e_hat, e_raw_mg=e_raw, sigma_mg=sig, c2=beta[2].copy(), c2_sigma=c2s)
    return out


def verify_compensated(
    acc_g: np.ndarray,
    temp_c: np.ndarray,
    e_before_mg,
    criteria: VerifyCriteria | None = None,
    *,
    time_s: np.ndarray | None = None,
    wander: BiasWander | str | None = "auto",
) -> VerificationResult:
    """Judge the compensated output of one DUT over a verification heating ramp (see module doc).

    acc_g (n, 3) compensated samples in g, temp_c (n,) the board's temperature; e_before_mg (3,)
    or None: the uncompensated E of the same orientation from the first pass. time_s (n,): sample
    times (default: index / criteria.odr_hz); wander: the part's bias wander ("auto": the class of
    its white noise at the part's own level, station/science/part_noise.py; None: white only).
    """
    c = criteria or VerifyCriteria()
    acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    temp = np.asarray(temp_c, dtype=np.float64).reshape(-1)
    flags: list[str] = []
    n = len(temp)
    if n < 3 * c.min_section_samples:
        raise ValueError(f"verification needs at least {3 * c.min_section_samples} samples, got {n}")
    t = np.arange(n) / c.odr_hz if time_s is None else np.asarray(time_s, dtype=np.float64).reshape(-1)
    if wander is None:
        wander = NO_WANDER
    elif isinstance(wander, str):  # the class of its white noise, at the level measured on the part
        odr = 1.0 / float(np.median(np.diff(t))) if n > 1 and np.median(np.diff(t)) > 0 else c.odr_hz
        wander = measure_part_noise(t, acc, [(0, n)], wander_for(None, _white_ug_per_sqrt_hz(acc, odr))).wander
    # the rise seen by the board: robust ends (medians of the first and last 5 %)
    k = max(5, n // 20)
    t_from, t_to = float(np.median(temp[:k])), float(np.median(temp[-k:]))
    rise = t_to - t_from
    sec_acc, sec_temp, _ = temperature_sections(acc, temp, c.section_c, c.min_section_samples)
    if len(sec_temp) >= 2:
        residual_range = (sec_acc.max(axis=0) - sec_acc.min(axis=0)) * 1e3
    else:
        residual_range = np.full(3, np.nan)
    fit = verified_drift_error(acc, temp, t, c, wander)
    e_after, e_sig = fit["e_mg"], fit["sigma_mg"]
    if not np.all(np.isfinite(e_after)):
        flags.append("too few blocks spanning a temperature change in the verification: no verified E")
    if rise < c.min_rise_c:
        flags.append(f"the verification heated only {rise:.1f} C (< {c.min_rise_c:g} C): drift not judged")
    c2, c2_se = fit["c2"], fit["c2_sigma"]
    half = c.full_range_c / 2.0
    eb = None if e_before_mg is None else np.asarray(e_before_mg, dtype=np.float64).reshape(3)
    axes: dict[str, AxisVerification] = {}
    for i, name in enumerate(AXES):
        before = None if eb is None or not np.isfinite(eb[i]) else float(eb[i])
        after = float(e_after[i])
        bow = abs(float(c2[i])) * half * half * 1e3
        sig = float(c2_se[i])
        curved = bool(bow > c.curvature_limit_mg and abs(float(c2[i])) > c.curvature_sigma * sig)
        limit = max(c.e_ratio_max * before, c.e_floor_mg) if before is not None else c.e_floor_mg
        reasons = []
        if not np.isfinite(after):
            reasons.append("no verified E")
        elif after - c.e_sigma_k * float(e_sig[i]) > limit:
            reasons.append(f"verified E {after:.2f} +- {float(e_sig[i]):.2f} mg > limit {limit:.2f} mg"
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
            e_after_sigma_mg=float(e_sig[i]),
        )
        if reasons:
            flags.append(f"{name}: " + "; ".join(reasons))
    passed = all(a.passed for a in axes.values()) and rise >= c.min_rise_c
    return VerificationResult(passed, axes, rise, t_from, t_to, n, len(sec_temp), c, flags)


__all__ = ["VerifyCriteria", "AxisVerification", "VerificationResult", "verify_compensated",
           "drift_before_mg", "temperature_sections", "verified_drift_error", "total_variation_mg"]
