"""The residual's noise model and the GLS comparison of two model structures: how strong the
evidence for an effect is when the residual is not white.

Why a module of its own: a real MEMS bias wanders (random walk, flicker), so neighbouring 10 s
blocks share their error and an ordinary likelihood ratio would count the same wander many times
over. Every p-value, delta BIC and parameter sigma the ranking reports comes from here: a local
level + AR(p) noise model fitted on the residual of the larger model of a comparison, both models
refitted on the prewhitened data (GLS). The admission gate (gate.py) and the staircase decide on
these numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter
from scipy.stats import chi2

from station.diagnostics.design import _Design
from station.diagnostics.effects import get_effect
from station.diagnostics.fit import DutFit, _tau_int
from station.diagnostics.report_values import _r
from station.diagnostics.segmentation import DutData
from contracts.types import AXES


tau_int = _tau_int


def block_resid(d: DutData, r: np.ndarray) -> np.ndarray:
    """Block means of a per-sample residual (n_blocks, 3)."""
    return d.block_mean(np.nan_to_num(r))


def n_eff_axes(d: DutData, r: np.ndarray) -> np.ndarray:
    """Effective number of independent block means per axis (autocorrelation within runs)."""
    rb = block_resid(d, r)
    run_b = d.block_run
    out = np.zeros(3)
    for i in range(3):
        taus, counts = [], []
        for run_id in np.unique(run_b):
            x = rb[run_b == run_id, i]
            if x.size >= 8:
                taus.append(tau_int(x))
                counts.append(x.size)
        tau = float(np.average(taus, weights=counts)) if taus else 1.0
        out[i] = rb.shape[0] / tau
    return out


def _ssr_block(d: DutData, r: np.ndarray) -> np.ndarray:
    rb = block_resid(d, r)
    return np.sum(d.block_count[:, None] * rb**2, axis=0)


AR_MAX = 6
THETA_GRID = np.concatenate([[0.0], 1.0 - 10.0 ** np.linspace(-0.3, -3.5, 28)])


GAP_RESTART_S = 600.0  # a gap in the log longer than this restarts the noise filter


def _runs_of_blocks(d: DutData) -> list[np.ndarray]:
    """Block indices of each contiguous piece of the log: the noise filter runs over the whole log
    and restarts only at a gap longer than GAP_RESTART_S (a log cut in two, a lost link).

    The plate's moves are not restarts. A filter restarted at every constant-orientation run drops
    that run's first value and differences its level away, so each run's level was free in the
    evidence: an effect whose signature is a level shift between runs (orientation-dependent,
    rate-dependent, a slow drift in time, a step) lost most of its in-sample evidence while its
    held-out error fell (issue 38: cross_axis 2x the floor, delta BIC -5). Across a move the
    orientation's Acc0 columns step with the data, so the filtered regressors carry the jump and the
    noise model sees only what the model does not explain."""
    t = d.block_time_s
    cut = np.flatnonzero(np.diff(t) > GAP_RESTART_S) + 1
    return np.split(np.arange(t.size), cut)


@dataclass
class NoiseFilter:
    """Residual noise model of block means: a local level (random walk + white: IMA(1,1), theta) and
    AR(p) for what is left (flicker, short-range correlation). apply() is its prediction-error
    (whitening) filter, run over each contiguous piece of the log (_runs_of_blocks), started at the
    piece's first value."""

    theta: float
    phi: np.ndarray
    sigma: float

    def _ima(self, v: np.ndarray) -> np.ndarray:
        # (1 - L) y_t = (1 - theta L) e_t  ->  e = lfilter([1, -1], [1, -theta], y), level removed
        zi = -v[:1]  # the filter's state for a constant input equal to the first value: output 0
        y, _ = lfilter([1.0, -1.0], [1.0, -self.theta], v, axis=0, zi=zi)
        return y[1:]

    def _ar(self, v: np.ndarray) -> np.ndarray:
        p_ = self.phi.size
        if v.shape[0] <= p_:
            return v[:0]
        w = v[p_:].copy()
        for j in range(1, p_ + 1):
            w -= self.phi[j - 1] * v[p_ - j:v.shape[0] - j]
        return w

    def apply(self, x: np.ndarray, runs: list[np.ndarray]) -> np.ndarray:
        out = [self._ar(self._ima(x[idx])) for idx in runs if idx.size > self.phi.size + 2]
        return np.concatenate(out) if out else x[:0]

    def to_json(self) -> dict:
        s = float(np.sum(self.phi))
        return {"model": "local level (random walk + white, IMA(1,1)) + AR(p)", "theta": _r(self.theta, 5),
                "ar_order": int(self.phi.size), "phi": [round(float(x), 4) for x in self.phi],
                "innovation_mg": _r(self.sigma, 5),
                "random_walk": bool(self.theta < 0.999),
                "long_run_factor": _r(1.0 / max(abs(1.0 - s), 1e-3), 2)}


def _robust_ms(w: np.ndarray) -> float:
    """Mean square of a series that may hold a few sustained offsets: (1.4826 MAD)^2, the mean
    square of a Gaussian series, which an offset over a minority of it does not move."""
    if not w.size:
        return math.inf
    return float((1.4826 * np.median(np.abs(w - np.median(w)))) ** 2)


def ar_fit(e: np.ndarray, runs: list[np.ndarray], pmax: int = AR_MAX, robust: bool = False) -> NoiseFilter:
    """Fit the residual noise model: theta of the local level by conditional sum of squares on a
    grid (theta -> 1: no random walk), then AR(p) (p <= pmax by BIC) of the IMA-filtered residual.

    robust=True (leftover.py): theta by the median absolute innovation instead of the mean square,
    and the AR fitted without the innovations beyond 3.5 robust sigmas. A structure the model misses
    leaves sustained offsets in its residual (a step, a half-cycle of a draught); the mean square
    adapts the local level to them by calling them a random walk, which then predicts a held-out
    error as large as the structure's and hides it. The evidence (compare) keeps the Gaussian fit:
    it is the likelihood the test needs."""
    e = np.asarray(e, float)
    loss = _robust_ms if robust else (lambda w: float(np.mean(w**2)) if w.size else math.inf)
    best = None
    for th in THETA_GRID:
        f = NoiseFilter(float(th), np.zeros(0), 0.0)
        ss = loss(f.apply(e, runs))
        if best is None or ss < best[0]:
            best = (ss, float(th))
    theta = best[1]
    pieces = [NoiseFilter(theta, np.zeros(0), 0.0)._ima(e[idx]) for idx in runs if idx.size > pmax + 3]
    rows_y, rows_x = [], []
    for x in pieces:
        if x.size <= pmax + 1:
            continue
        rows_y.append(x[pmax:])
        rows_x.append(np.stack([x[pmax - j:x.size - j] for j in range(1, pmax + 1)], axis=1))
    if not rows_y:
        return NoiseFilter(theta, np.zeros(0), float(np.std(e)) if e.size else 0.0)
    Y = np.concatenate(rows_y)
    X = np.concatenate(rows_x)
    if robust:
        keep = np.abs(Y - np.median(Y)) <= 3.5 * math.sqrt(_robust_ms(Y))
        if keep.sum() > 4 * pmax:
            Y, X = Y[keep], X[keep]
    n = Y.size
    bbest = (math.inf, np.zeros(0), float(np.sqrt(np.mean(Y**2))))
    for p_ in range(pmax + 1):
        if p_:
            phi, *_ = np.linalg.lstsq(X[:, :p_], Y, rcond=None)
            r = Y - X[:, :p_] @ phi
        else:
            phi, r = np.zeros(0), Y
        s2 = max(float(np.mean(r**2)), 1e-300)
        bic = n * math.log(s2) + p_ * math.log(n)
        if bic < bbest[0]:
            bbest = (bic, phi, math.sqrt(s2))
    return NoiseFilter(theta, bbest[1], bbest[2])


def whiten(x: np.ndarray, runs: list[np.ndarray], nf: NoiseFilter) -> np.ndarray:
    return nf.apply(x, runs)


def _design_blocks(d: DutData, effects: list[str], nl: dict, acc0_g: np.ndarray) -> list[np.ndarray]:
    mats, _ = _Design(d, [get_effect(n) for n in effects]).block_matrices(nl, acc0_g)
    return mats


def _n_nl(effects: list[str], nl: dict) -> int:
    """Nonlinear parameters the fit chose (a family's shape counts as one: see Effect.n_nonlinear)."""
    return sum(get_effect(n).n_nonlinear(nl.get(n, {})) for n in effects)


def _gls_ssr(Xw: np.ndarray, yw: np.ndarray) -> tuple[float, int]:
    live = np.any(np.abs(Xw) > 0, axis=0)
    A = Xw[:, live]
    if A.shape[1] == 0:
        return float(yw @ yw), 0
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    sol, _, rank, _ = np.linalg.lstsq(A / scale, yw, rcond=None)
    r = yw - (A / scale) @ sol
    return float(r @ r), int(rank)


def _ols_ssr(X: np.ndarray, y: np.ndarray) -> float:
    live = np.any(np.abs(X) > 0, axis=0)
    coef, *_ = np.linalg.lstsq(X[:, live], y, rcond=None)
    r = y - X[:, live] @ coef
    return float(r @ r)


@dataclass
class Comparison:
    """Small model vs big model under the big model's AR noise (prewhitened GLS)."""

    lr: float
    df: int
    p: float
    delta_bic: float
    n: int
    noise: dict


def compare(data: list[DutData], small: list[tuple], big: list[tuple]) -> Comparison:
    """Likelihood-ratio test and delta BIC of `big` against `small` (per DUT: (effects, nl, acc0_g)).

    The noise model (AR(p) per DUT and axis) is fitted on the OLS residual of the big model and both
    models are refitted by GLS under it, so the comparison is fair and the random-walk part of the
    residual is not counted as independent evidence."""
    lr = 0.0
    df = 0
    n_tot = 0
    noise: dict = {}
    for d, (es, nls, a0s), (eb, nlb, a0b) in zip(data, small, big):
        Xs = _design_blocks(d, es, nls, a0s)
        Xb = _design_blocks(d, eb, nlb, a0b)
        runs = _runs_of_blocks(d)
        noise[d.serial] = {}
        for i in range(3):
            y = d.y_block[:, i]
            live = np.any(np.abs(Xb[i]) > 0, axis=0)
            coef, *_ = np.linalg.lstsq(Xb[i][:, live], y, rcond=None)
            e = y - Xb[i][:, live] @ coef
            if float(e @ e) > _ols_ssr(Xs[i], y) * (1 + 1e-9):
                # the big model fits this axis worse in sample (a nonlinear value stuck at its
                # bound): no evidence, whatever its misfit does to the noise model it is judged under
                n_tot += y.size
                df += max(int(np.count_nonzero(live)) - int(np.count_nonzero(np.any(np.abs(Xs[i]) > 0, axis=0))), 0)
                noise[d.serial][AXES[i]] = None
                continue
            nf = ar_fit(e, runs)
            yw = nf.apply(y, runs)
            ss, ks = _gls_ssr(nf.apply(Xs[i], runs), yw)
            sb, kb = _gls_ssr(nf.apply(Xb[i], runs), yw)
            n = yw.size
            lr += n * math.log(max(ss, 1e-300) / max(sb, 1e-300))
            df += max(kb - ks, 0)
            n_tot += n
            noise[d.serial][AXES[i]] = nf.to_json()
        df += max(_n_nl(eb, nlb) - _n_nl(es, nls), 0)
    df = max(df, 1)
    lr = max(lr, 0.0)
    p = float(chi2.sf(lr, df))
    dbic = -lr + df * math.log(max(n_tot, 2))
    return Comparison(lr=lr, df=df, p=p, delta_bic=dbic, n=n_tot, noise=noise)


def gls_sigma(d: DutData, fit: DutFit) -> list[np.ndarray]:
    """1-sigma of every linear parameter from the GLS fit under the residual's AR noise model."""
    X = _design_blocks(d, fit.effects, fit.nl, fit.acc0_g)
    runs = _runs_of_blocks(d)
    out = []
    for i in range(3):
        y = d.y_block[:, i]
        sig = np.full(X[i].shape[1], np.nan)
        live = np.any(np.abs(X[i]) > 0, axis=0)
        A = X[i][:, live]
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        nf = ar_fit(y - A @ coef, runs)
        Aw = nf.apply(A, runs)
        yw = nf.apply(y, runs)
        scale = np.linalg.norm(Aw, axis=0)
        scale[scale == 0] = 1.0
        sol, *_ = np.linalg.lstsq(Aw / scale, yw, rcond=None)
        r = yw - (Aw / scale) @ sol
        s2 = float(r @ r) / max(1, yw.size - A.shape[1])
        cov = np.linalg.pinv((Aw / scale).T @ (Aw / scale)) / np.outer(scale, scale)
        sig[live] = np.sqrt(np.maximum(np.diag(cov), 0.0) * s2)
        out.append(sig)
    return out


__all__ = ["NoiseFilter", "ar_fit", "whiten", "Comparison", "compare", "gls_sigma", "tau_int", "block_resid",
           "n_eff_axes"]
