"""Bias wander of a sensor class: the structure function the slope and curvature budgets use.

Why a module of its own: offline_fit, residual, verify and part_noise all read it; part_noise
measures a part's own level against the class's shape (station/science/part_noise.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class BiasWander:
    """Bias wander of a sensor class beyond white noise, as its structure function
    D(lag) = var(b(t + lag) - b(t)) = rw^2 lag + sum_c 2 (flicker^2 / m) (1 - exp(-lag / tau_c)):
    a random walk plus a flicker floor modelled by m decade-spaced Gauss-Markov processes. The
    variance of any zero-sum combination sum_i w_i b(t_i) is -1/2 sum_ij w_i w_j D(|t_i - t_j|),
    which is what a slope between segments tens of minutes apart suffers and what sigma/sqrt(n) of
    a segment mean leaves out. Numbers come from a long static log (`characterise_bias_wander`).
    white_ug_per_sqrt_hz tells the classes apart when a record does not name its sensor."""

    name: str
    white_ug_per_sqrt_hz: float
    rw_g_per_sqrt_s: float
    flicker_g: float
    flicker_tau_s: tuple[float, ...] = (60.0, 600.0, 6000.0)

    def structure_g2(self, lag_s) -> np.ndarray:
        lag = np.abs(np.asarray(lag_s, dtype=np.float64))
        d = self.rw_g_per_sqrt_s ** 2 * lag
        m = max(1, len(self.flicker_tau_s))
        for tau in self.flicker_tau_s:
            d = d + 2.0 * self.flicker_g ** 2 / m * (1.0 - np.exp(-lag / tau))
        return d

    def combination_var_g2(self, weights, time_s) -> float:
        """Variance (g^2) of sum_i w_i b(t_i) for zero-sum weights (a slope, a curvature)."""
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
        t = np.asarray(time_s, dtype=np.float64).reshape(-1)
        if w.size < 2:
            return 0.0
        d = self.structure_g2(t[:, None] - t[None, :])
        return max(0.0, float(-0.5 * w @ d @ w))


# Measured with `python benchmarks/coverage.py --characterise` (characterise_bias_wander on 8 h
# static simulated logs, 6 boards per sensor class, realistic noise, fixed decade taus 60/600/6000
# s; the simulator's truth is rw 3.54e-6 / flicker 40e-6 and 0.5e-6 / 5e-6). A real line measures
# its part family the same way (one board, static, hours) and replaces these. They are the SHAPE
# and the wander-to-white ratio of a class: each part's level is its own (part_noise).
WANDER_BY_SENSOR: dict[str, BiasWander] = {
    "LIS3DSH": BiasWander("LIS3DSH", 393.0, 3.60e-6, 39.5e-6),  # 6 boards x 8 h, mean of rw^2 and flicker^2
    "ADXL355": BiasWander("ADXL355", 24.6, 0.51e-6, 4.8e-6),
}
NO_WANDER = BiasWander("white", 0.0, 0.0, 0.0)
LAG_SIGMA_S = 5.0  # MEMS behind its on-die temperature sensor: same die, a few seconds at most


def wander_for(sensor: str | None = None, white_ug_per_sqrt_hz: float | None = None) -> BiasWander:
    """The bias-wander class of a DUT: by sensor name, else the class whose white noise density is
    nearest (log ratio) to the measured one, else the largest (LIS3DSH, conservative)."""
    if sensor:
        for k, w in WANDER_BY_SENSOR.items():
            if k.lower() == str(sensor).lower():
                return w
    if white_ug_per_sqrt_hz is not None and math.isfinite(white_ug_per_sqrt_hz) and white_ug_per_sqrt_hz > 0:
        return min(WANDER_BY_SENSOR.values(), key=lambda w: abs(math.log(white_ug_per_sqrt_hz / w.white_ug_per_sqrt_hz)))
    return WANDER_BY_SENSOR["LIS3DSH"]


def _block_pair_basis(lag_s: float, block_s: float, flicker_tau_s: tuple[float, ...], n_sub: int = 16) -> tuple[float, float]:
    """E[(mean of a block at lag_s) - (mean of the block at 0)]^2 for a unit random walk (rw = 1
    g/sqrt(s)) and for a unit flicker (flicker_g = 1): block means, not points, so the averaging
    inside a block (which hides most of a short flicker time constant) is part of the model."""
    t0 = (np.arange(n_sub) + 0.5) * (block_s / n_sub)
    t = np.concatenate([t0, t0 + lag_s])
    w = np.concatenate([-np.ones(n_sub), np.ones(n_sub)]) / n_sub
    rw = BiasWander("unit rw", 0.0, 1.0, 0.0, flicker_tau_s).combination_var_g2(w, t)
    fl = BiasWander("unit flicker", 0.0, 0.0, 1.0, flicker_tau_s).combination_var_g2(w, t)
    return rw, fl


def characterise_bias_wander(time_s, acc_g, name: str = "measured", block_s: float = 60.0,
                             flicker_tau_s: tuple[float, ...] = (60.0, 600.0, 6000.0)) -> BiasWander:
    """BiasWander of a long STATIC log (constant temperature and position): the empirical structure
    function of block means at lags of 1..(duration/3) blocks, minus the white part (2 var_w /
    n_block), fitted (non-negative least squares, pooled over axes, relative weights) with what a
    unit random walk and a unit flicker give the same pair of BLOCK MEANS (`_block_pair_basis`; a
    fit to the point structure function instead reads a flicker about 40 % low)."""
    from scipy.optimize import nnls

    t = np.asarray(time_s, dtype=np.float64).reshape(-1)
    a = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    odr = 1.0 / float(np.median(np.diff(t)))
    nb = max(2, int(round(block_s * odr)))
    m = a.shape[0] // nb
    bm = a[: m * nb].reshape(m, nb, 3).mean(axis=1)
    d1 = np.diff(a, axis=0)
    var_w = 0.5 * float(np.mean(np.var(d1, axis=0)))
    lags = np.unique(np.round(np.geomspace(1, max(2, m // 3), 25)).astype(int))
    rows, rhs = [], []
    for k in lags:
        dk = float(np.mean((bm[k:] - bm[:-k]) ** 2)) - 2.0 * var_w / nb
        rw_b, fl_b = _block_pair_basis(k * nb / odr, nb / odr, tuple(flicker_tau_s))
        wgt = 1.0 / max(dk, 1e-14)  # relative (log-like) weighting over the decades
        rows.append([rw_b * wgt, fl_b * wgt])
        rhs.append(dk * wgt)
    coef, _ = nnls(np.array(rows), np.array(rhs))
    white = math.sqrt(var_w) / math.sqrt(odr / 2.0) * 1e6
    return BiasWander(name, white, math.sqrt(coef[0]), math.sqrt(coef[1]), tuple(flicker_tau_s))


__all__ = ["BiasWander", "WANDER_BY_SENSOR", "NO_WANDER", "LAG_SIGMA_S", "wander_for", "characterise_bias_wander"]
