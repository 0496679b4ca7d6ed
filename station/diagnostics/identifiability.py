"""What the data can and cannot tell apart, decided before any candidate is ranked or admitted.

Why a module of its own: a candidate whose regressors lie in the baseline's span (cross_axis from
two orientations), candidates with identical regressors on this data (bias_t2 and scale_t2 with one
orientation), or a pair that only a missing data feature separates (thermal_lag and hysteresis
without two ramp rates) would otherwise be ranked, admitted or reported with parameters the data
cannot support. This module finds them, so the report can say which test would identify them:
unidentifiable candidates, alias groups (ranked as one term), confusable contributions, the data
features, and per axis whether TDSF is identifiable.
"""

from __future__ import annotations

import math

import numpy as np

from station.science.chunked import median_step_s, pieces
from station.diagnostics.design import _Design, tdsf_identifiable
from station.diagnostics.effects import get_effect
from station.diagnostics.evaluation import ModelEval
from station.diagnostics.fit import DutFit
from station.diagnostics.segmentation import DutData
from contracts.types import AXES

UNIDENTIFIABLE_REL = 1e-3
CONFUSABLE_COS = 0.9


def _baseline_design(d: DutData, fit: DutFit):
    """Baseline columns per axis (block means) at the fitted Acc0."""
    return _Design(d, []).block_matrices({}, fit.acc0_g)[0]


def _residualize(Xb: np.ndarray, Z: np.ndarray, w: np.ndarray) -> np.ndarray:
    sw = np.sqrt(w)[:, None]
    A = Xb * sw
    live = np.any(A != 0, axis=0)
    A = A[:, live]
    Zw = Z * sw
    coef, *_ = np.linalg.lstsq(A, Zw, rcond=None)
    return (Zw - A @ coef) / sw


def candidate_regressors(d: DutData, base_fit: DutFit, cand_fit: DutFit) -> list[np.ndarray]:
    """Per axis (n_blocks, m): the candidate's regressors at its fitted nonlinear values.

    For a temperature-changing effect (thermal_lag) the regressor is the change of the baseline
    prediction when the lagged temperature replaces the measured one (the derivative direction).
    """
    eff = [get_effect(n) for n in cand_fit.effects if n not in base_fit.effects]
    design = _Design(d, eff)
    mats, names = design.block_matrices(cand_fit.nl, base_fit.acc0_g)
    P = len(d.pos_labels)
    out = []
    for i in range(3):
        cols = [mats[i][:, P + 2:]]
        if design.lag:
            base_mats, _ = _Design(d, []).block_matrices({}, base_fit.acc0_g)
            base_pred = base_mats[i] @ base_fit.beta[i][: P + 2]
            lag_pred = mats[i][:, : P + 2] @ base_fit.beta[i][: P + 2]
            cols.append((lag_pred - base_pred)[:, None])
        out.append(np.hstack(cols))
    return out


def identifiability(data: list[DutData], base: ModelEval, name: str) -> float:
    """Smallest-over-DUTs max-over-columns relative norm of the candidate regressors left after
    projecting out the baseline's. ~0: the data cannot identify the candidate."""
    eff = get_effect(name)
    worst = 1.0
    best_any = 0.0
    for d, bf in zip(data, base.fits):
        nl0 = {eff.name: {p.name: p.init for p in eff.nonlinear}}
        design = _Design(d, [eff])
        mats, _ = design.block_matrices(nl0, bf.acc0_g)
        P = len(d.pos_labels)
        Xs = _baseline_design(d, bf)
        rel_cols = []
        for i in range(3):
            Z = mats[i][:, P + 2:]
            if design.lag:
                dl = (mats[i][:, P] - Xs[i][:, P])[:, None]  # lagged minus measured dT
                Z = np.hstack([Z, dl])
            for c in range(Z.shape[1]):
                z = Z[:, c]
                nz = float(np.sqrt(np.sum(d.block_count * z * z)))
                if nz == 0:
                    continue
                zt = _residualize(Xs[i], z[:, None], d.block_count)[:, 0]
                rel_cols.append(float(np.sqrt(np.sum(d.block_count * zt * zt))) / nz)
        rel = max(rel_cols) if rel_cols else 0.0
        best_any = max(best_any, rel)
        worst = min(worst, rel)
    return best_any


def _contribution(data, base: ModelEval, cand: ModelEval) -> np.ndarray:
    """The candidate's fitted change of prediction (block means, all DUTs and axes), baseline
    projected out."""
    parts = []
    for d, bf, rb_, rc in zip(data, base.fits, base.resid_block, cand.resid_block):
        delta = np.nan_to_num(rb_ - rc)  # = pred_cand - pred_base
        Xs = _baseline_design(d, bf)
        for i in range(3):
            parts.append(_residualize(Xs[i], delta[:, i:i + 1], d.block_count)[:, 0] * np.sqrt(d.block_count))
    return np.concatenate(parts)


def _cos(a: np.ndarray, b: np.ndarray) -> float:
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    return float(a @ b / (na * nb)) if na > 0 and nb > 0 else 0.0


def drift_identifiability(data: list[DutData], base: ModelEval) -> dict:
    """Per DUT and axis: is TDSF identifiable from the orientations in the log (see _params_json)?"""
    out = {}
    for d, f in zip(data, base.fits):
        ok = tdsf_identifiable(f.acc0_g)
        out[d.serial] = {ax: bool(ok[i]) for i, ax in enumerate(AXES)}
    return out


FEATURE_TEXT = {"ramp_rates": "two or more distinct temperature ramp rates"}


def ramp_rates(d: DutData) -> list[float]:
    """Distinct ramp rates (C/min) of a DUT's log: |dT/dt| over 5 min of the smoothed die
    temperature, histogram in half-octave bins; the bins holding >= 12 % of the ramping time."""
    t, T = d.time_s, d.temp_smooth_c
    if t.size < 10:
        return []
    dt = median_step_s(t)
    h = max(1, int(round(150.0 / dt)))
    if T.size <= 2 * h:
        return []
    edges = np.arange(-2.0, 5.01, 0.5)
    hist = np.zeros(edges.size - 1, dtype=np.int64)
    n_rate, n_ramp = T.size - 2 * h, 0
    for a, b in pieces([(0, n_rate)]):  # the rates a piece at a time: the counts add up
        rate = np.abs(T[a + 2 * h:b + 2 * h] - T[a:b]) / (t[a + 2 * h:b + 2 * h] - t[a:b]) * 60.0
        ramp = rate[rate > 0.25]
        n_ramp += ramp.size
        hist += np.histogram(np.log2(ramp), bins=edges)[0]
    if n_ramp < 0.02 * n_rate or n_ramp == 0:
        return []
    frac = hist / n_ramp
    centers = 2.0 ** (0.5 * (edges[:-1] + edges[1:]))
    return [round(float(c), 3) for c, f in zip(centers, frac) if f >= 0.12]


def data_features(data: list[DutData]) -> dict:
    """What the data contain that some identifications need (pooled over DUTs)."""
    rates = sorted({r for d in data for r in ramp_rates(d)})
    spread = math.log2(max(rates) / min(rates)) if rates else 0.0
    return {"ramp_rates": bool(spread >= 0.9), "ramp_rates_c_per_min": rates,
            "orientations": max(len(d.pos_labels) for d in data)}



TERMS = {"bias_t2": "curvature", "scale_t2": "curvature", "bias_t3": "cubic drift", "thermal_lag": "lag",
         "hysteresis": "hysteresis", "self_heating": "warm-up", "cross_axis": "cross-axis drift",
         "scale_nonlinearity": "nonlinearity drift"}
ALIAS_REL = 1e-4


def _span_residual(A: np.ndarray, B: np.ndarray) -> float:
    """Largest relative norm of a column of B left after projecting it on the span of A."""
    if A.shape[1] == 0 or B.shape[1] == 0:
        return 1.0
    coef, *_ = np.linalg.lstsq(A, B, rcond=None)
    r = B - A @ coef
    nb = np.linalg.norm(B, axis=0)
    ok = nb > 0
    return float(np.max(np.linalg.norm(r, axis=0)[ok] / nb[ok])) if ok.any() else 0.0


def alias_groups(data: list[DutData], base: ModelEval, names: list[str]) -> list[list[str]]:
    """Groups of candidates whose regressors span the same space on this data once the baseline is
    projected out (effects with nonlinear parameters are compared at their initial values only if
    they have none: a lag or width makes the regressor data-dependent, so those are never aliases)."""
    lin = [n for n in names if not get_effect(n).nonlinear and type(get_effect(n)).temperature is type(get_effect(n)).__mro__[-2].temperature]
    cols: dict[str, list[np.ndarray]] = {}
    for n in lin:
        parts = []
        for d, bf in zip(data, base.fits):
            mats, _ = _Design(d, [get_effect(n)]).block_matrices({}, bf.acc0_g)
            Xs = _baseline_design(d, bf)
            P = len(d.pos_labels)
            for i in range(3):
                Z = mats[i][:, P + 2:]
                parts.append(_residualize(Xs[i], Z, d.block_count) if Z.shape[1] else Z)
        cols[n] = parts
    groups: list[list[str]] = []
    used: set[str] = set()
    for k, a in enumerate(lin):
        if a in used:
            continue
        g = [a]
        for b in lin[k + 1:]:
            if b in used:
                continue
            same = all(_span_residual(A, B) < ALIAS_REL and _span_residual(B, A) < ALIAS_REL
                       for A, B in zip(cols[a], cols[b]) if A.shape[1] and B.shape[1])
            if same:
                g.append(b)
                used.add(b)
        if len(g) > 1:
            groups.append(g)
            used.add(a)
    return groups


__all__ = ["identifiability", "alias_groups", "data_features", "ramp_rates", "drift_identifiability",
           "candidate_regressors", "TERMS", "FEATURE_TEXT"]
