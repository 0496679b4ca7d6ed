"""What is left after compensation, predicted from the DUT's own data (martinez2022 eqs. 10-13).

The fit gives TDB/TDSF with 1-sigma uncertainties; the verdict needs to know how well eq. 13 will
compensate THIS part over the product's operating range R. From the DUT's own stable (gate open,
still) samples, compensated with its own TDB/TDSF, per axis:

- curvature c2 (mg/C^2): a parabola in (T - 25) fitted per orientation to block means of the
  compensated data (batch means, so autocorrelated noise does not look significant); per axis the
  orientations that put the same gravity on it are combined (inverse variance), and of those groups
  the largest |c2| is kept, with its 1-sigma. A linear TDB/TDSF cannot compensate it.
- bow (mg) = |c2| R^2 / 8: how far that parabola departs from the best straight line over R; the
  verdict names a bow over its limit as "the DUT's data reject the linear model".
- drift error E (mg), eq. 10 evaluated on the residual model over R: the linear compensation
  matched each orientation's chord slope over its own data (25..50 C on a fast-thermal run), so the
  parabola it leaves has its vertex at half that chord's x^2-on-x slope (about the data's middle),
  and E = |c2| ((R/2 + v)^2 + (R/2 - v)^2) (R^2 / 2 for a vertex at 25 C; `parabola_variation`).
  Its 1-sigma combines the curvature's sigma (times the same factor) with what the coefficient uncertainty alone leaves over
  R at +-1 g (eq. 1 with each coefficient's error, TDB and TDSF correlated by rho, the worse sign):
  R sqrt(sigma_TDB^2 + (sigma_TDSF * 1 g)^2 + 2 |rho sigma_TDB sigma_TDSF * 1 g|).
  sigma_c2 is the batch-means scatter PLUS the terms batch means cannot see (offline_fit module
  doc): bias wander between the blocks (the part's structure function), the temperature
  quantiser's periodic error and the MEMS lag, each propagated with the quadratic's own weights.
  E_FS = E / 2000 mg * 100 % (eq. 12, the +-1 g span; Table 7: fast method 0.61 % mean, 1.16 % max).
  Extrapolating the parabola seen on the ramp (~25..50 C) to R is the model's assumption.
- ramp residual (mg): RMS of the compensated block means about their orientation's mean, i.e. how
  far the DUT's own ramp data sit from the compensated model where it was measured.
- noise density (ug/sqrt(Hz)): the robust sigma of (raw - filtered) over the stable samples,
  corrected for the filter, divided by sqrt(ODR / 2) (ODR from the sample times).

Pure: arrays in, numbers out.
"""

from __future__ import annotations

import math

import numpy as np

from station.science.chunked import median_step_s, split_bounds
from station.science.offline_fit import (LAG_SIGMA_S, BiasWander, block_features, budget_inputs,
                                         combination_budget, robust_sigma_g, runs_by_orientation, usable_mask)
from station.science.gate_trace import GateTrace, trace_gate
from station.science.streaming_config import StreamingConfig
from station.science.thermal_model import FULL_SCALE_MG, compensate
from contracts.types import AXES, T_REF_C

DEFAULT_OPERATING_RANGE_C = 70.0  # martinez2022 4.5: -10..60 C


def _sigmas(v) -> np.ndarray:
    """Per-axis 1-sigma; None (a method without uncertainty) -> NaN, so E gets no sigma either."""
    if v is None:
        return np.full(3, np.nan)
    return np.array([np.nan if x is None else float(x) for x in v], dtype=np.float64)


def _combine_curvatures(per_gravity: dict[tuple[int, float], list[tuple[float, float, float]]], range_c: float
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per axis: the curvature (c2, sigma, mg/C^2) and the drift error it leaves (E, its sigma, mg).

    The orientations in which the axis feels the same gravity measure the same curvature (a bias
    curvature; a scale curvature flips with the sign of g), so they are combined by inverse
    variance. Of the gravity groups the curvature kept is the largest |c2|, and E the largest
    |c2| `parabola_variation` (each group's own vertex: its data's chord, which differs between a
    heating and a cooling orientation by several C): the worse position. A max over every single
    orientation instead would favour noise."""
    c2, c2_sig = np.full(3, np.nan), np.full(3, np.nan)
    e, e_sig = np.full(3, np.nan), np.full(3, np.nan)
    for (k, _g), vals in per_gravity.items():
        v = np.array([x[0] for x in vals])
        sg = np.array([x[1] for x in vals])
        f = float(np.max(parabola_variation(np.array([x[2] for x in vals]), range_c)))
        if not np.all(np.isfinite(sg)) or np.any(sg <= 0):
            i = int(np.argmax(np.abs(v)))
            cur, cs = float(v[i]), float(sg[i])
        else:
            w = 1.0 / sg ** 2
            cur, cs = float(np.sum(w * v) / np.sum(w)), float(1.0 / math.sqrt(np.sum(w)))
        if not np.isfinite(c2[k]) or abs(cur) > abs(c2[k]):
            c2[k], c2_sig[k] = cur, cs
        if not np.isfinite(e[k]) or abs(cur) * f > e[k]:
            e[k], e_sig[k] = abs(cur) * f, cs * f
    return c2, c2_sig, e, e_sig


def parabola_variation(vertex_c: np.ndarray, range_c: float) -> np.ndarray:
    """Eq. 10's total variation of (x - vertex)^2 over the range x in [-R/2, R/2] (x = T - 25):
    times |c2| it is the drift error E a curvature leaves after a linear compensation that matched
    the chord of the calibration's data (R^2 / 2 when the vertex sits at 25 C)."""
    h = range_c / 2.0
    v = np.asarray(vertex_c, dtype=np.float64)
    inside = np.abs(v) <= h
    return np.where(inside, (h + v) ** 2 + (h - v) ** 2, np.abs((h - v) ** 2 - (h + v) ** 2))


def residual_report(
    time_s,
    acc_g,
    temp_c,
    tdb_mg_per_c,
    tdsf_ppm_per_c,
    tdb_sigma_mg_per_c=None,
    tdsf_sigma_ppm_per_c=None,
    *,
    operating_range_c: float = DEFAULT_OPERATING_RANGE_C,
    min_span_c: float = 8.0,
    block_samples: int = 200,
    config: StreamingConfig | None = None,
    trace: GateTrace | None = None,
    tdb_tdsf_corr=None,
    sensor: str | None = None,
    wander: BiasWander | str | None = None,
    lag_sigma_s: float = LAG_SIGMA_S,
) -> dict:
    """Per-axis residual drift E/E_FS, curvature and noise density of one DUT (see module doc).

    Returns {"operating_range_c", "odr_hz", "n_used", "axes": {x: {"drift_error_mg",
    "drift_error_sigma_mg", "drift_error_fs_pct", "drift_error_fs_sigma_pct",
    "drift_error_curvature_sigma_mg" (the curvature's part of that sigma), "curvature_mg_per_c2",
    "curvature_sigma_mg_per_c2", "bow_mg", "bow_sigma_mg", "noise_ug_per_sqrt_hz",
    "ramp_residual_rms_mg"}}}; values are None where the data do not allow them (an orientation
    needs >= 5 blocks spanning min_span_c for a curvature). tdb_tdsf_corr (3,): correlation of
    each axis's TDB and TDSF errors (offline_fit's `.uncertainty`; None = 0). wander: as offline_fit
    (None: white only; "auto": the sensor class).
    """
    cfg = config or StreamingConfig()
    t = np.asarray(time_s, dtype=np.float64).reshape(-1)
    acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    temp = np.asarray(temp_c, dtype=np.float64).reshape(-1)
    if trace is None:
        trace, _ = trace_gate(t, acc, temp, cfg)
    use = usable_mask(acc, trace)
    tdb = np.asarray(tdb_mg_per_c, dtype=np.float64)
    tdsf = np.asarray(tdsf_ppm_per_c, dtype=np.float64)
    rng = float(operating_range_c)
    quantum, _, amps, wander = budget_inputs(t, acc, temp, trace, use, cfg.alpha_acc, sensor, wander)

    per_gravity: dict[tuple[int, float], list[tuple[float, float]]] = {}
    ramp_ss = np.zeros(3)
    ramp_n = 0
    by_orientation = runs_by_orientation(use, trace.orientation)
    for o in np.unique(trace.orientation):
        runs = [(s, e) for s, e in by_orientation.get(int(o), []) if e - s >= 2]
        if not runs:
            continue
        bx, by, bn, blocks = [], [], [], []
        for s, e in runs:
            nb = max(1, int(round((e - s) / block_samples)))
            for a, b in split_bounds(s, e, nb):
                bx.append(temp[a:b].mean() - T_REF_C)
                by.append(compensate(acc[a:b], temp[a:b], tdb, tdsf).mean(axis=0))  # the block's samples only
                bn.append(float(b - a))
                blocks.append((a, b))
        bx, by, bn = np.array(bx), np.array(by), np.array(bn)
        if bx.size >= 2:
            ramp_ss += np.sum((by - by.mean(axis=0)) ** 2, axis=0)
            ramp_n += bx.size
        if bx.size >= 5 and np.ptp(bx) >= min_span_c:
            # weighted by block size: a gate that flickers on a noisy temperature reading leaves
            # short blocks on the ramp, whose means are noisier and sit where a curvature has its
            # leverage; an unweighted fit and scatter under-state that sigma 2x (part_noise tests)
            xm = float(np.average(bx, weights=bn))
            X = np.column_stack([np.ones_like(bx), bx - xm, (bx - xm) ** 2])
            XtW = X.T * bn
            cov_unit = np.linalg.pinv(XtW @ X)
            coef = cov_unit @ XtW @ by
            resid = by - X @ coef
            s2 = np.sum(bn[:, None] * resid * resid, axis=0) / max(bx.size - 3, 1)  # per-sample variance
            var_c2 = s2 * cov_unit[2, 2]
            w_c2 = (cov_unit @ XtW)[2]
            # wander / quantiser / lag through the curvature's own weights on the block means; a
            # temperature error moves the compensated output by the slope compensation removed
            bt, bg, ph = block_features(t, trace.temp_filt_between, quantum, blocks)
            sens = tdb * 1e-3 + tdsf * 1e-6 * by.mean(axis=0)
            terms = combination_budget(w_c2, bt, bg, ph, sens, wander, amps, lag_sigma_s)
            sig = np.sqrt(var_c2 + sum(terms.values()))
            g_axis = np.round(by.mean(axis=0) * 2.0) / 2.0  # the axis's gravity, to 0.5 g
            # the compensation matched this orientation's chord slope (its TD_i) over these data, so
            # the parabola it leaves has its vertex where a line fitted to x^2 touches: chord / 2
            bxc = bx - np.average(bx, weights=bn)
            vertex = 0.5 * float(np.sum(bn * bxc * bx * bx) / np.sum(bn * bxc * bxc))
            for k in range(3):
                per_gravity.setdefault((k, float(g_axis[k])), []).append((coef[2, k] * 1e3, sig[k] * 1e3, vertex))
    c2, c2_sig, e_curv_mg, e_curv_sig_mg = _combine_curvatures(per_gravity, rng)
    ramp_rms = np.sqrt(ramp_ss / ramp_n) * 1e3 if ramp_n else np.full(3, np.nan)
    # noise density
    dt_med = median_step_s(t) if t.size > 1 else float("nan")
    odr = float(1.0 / dt_med) if dt_med > 0 else float("nan")
    noise = np.full(3, np.nan)
    if np.count_nonzero(use) >= 50 and math.isfinite(odr):
        sigma_g = robust_sigma_g(acc, trace, use)
        # raw - filtered with alpha: var = var_w * (1 - alpha/(2 - alpha))^... ~ var_w * 2/(2 - alpha)
        # for white noise: e = x - y, y_n = a x_n + (1-a) y_{n-1}; var(e) = var_w * 2 (1-a)/(2-a)
        a = cfg.alpha_acc
        sigma_g = sigma_g / math.sqrt(2.0 * (1.0 - a) / (2.0 - a))
        noise = sigma_g / math.sqrt(odr / 2.0) * 1e6
    sb = _sigmas(tdb_sigma_mg_per_c)
    sf = _sigmas(tdsf_sigma_ppm_per_c)
    rho = np.zeros(3) if tdb_tdsf_corr is None else np.nan_to_num(
        np.asarray([np.nan if v is None else float(v) for v in tdb_tdsf_corr], dtype=np.float64))
    sf_mg = sf * 1e-3  # ppm/C at 1 g = 1e-3 mg/C
    coef_sig = rng * np.sqrt(sb ** 2 + sf_mg ** 2 + 2.0 * np.abs(rho * sb * sf_mg))  # the worse of +-1 g
    e_mg = e_curv_mg
    e_sig = np.sqrt(e_curv_sig_mg ** 2 + coef_sig ** 2)
    bow = np.abs(c2) * rng ** 2 / 8.0
    bow_sig = c2_sig * rng ** 2 / 8.0

    def f(v: float) -> float | None:
        return float(v) if math.isfinite(v) else None

    axes = {}
    for k, ax in enumerate(AXES):
        axes[ax] = {
            "drift_error_mg": f(e_mg[k]),
            "drift_error_sigma_mg": f(e_sig[k]),
            "drift_error_fs_pct": f(e_mg[k] / FULL_SCALE_MG * 100.0),
            "drift_error_fs_sigma_pct": f(e_sig[k] / FULL_SCALE_MG * 100.0),
            "drift_error_curvature_sigma_mg": f(e_curv_sig_mg[k]),
            "curvature_mg_per_c2": f(c2[k]),
            "curvature_sigma_mg_per_c2": f(c2_sig[k]),
            "bow_mg": f(bow[k]),
            "bow_sigma_mg": f(bow_sig[k]),
            "noise_ug_per_sqrt_hz": f(noise[k]),
            "ramp_residual_rms_mg": f(ramp_rms[k]),
        }
    return {"operating_range_c": rng, "odr_hz": f(odr), "n_used": int(use.sum()), "axes": axes}


__all__ = ["residual_report", "DEFAULT_OPERATING_RANGE_C"]
