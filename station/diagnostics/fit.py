"""Fit the baseline thermal model (martinez2022 eq. 1), optionally plus effects, to one DUT's log,
and predict from the fit, in sample and held out.

Why a module of its own: every figure the ranking weighs (in-sample and held-out residuals, the
fitted Acc0 and nonlinear values the GLS comparison starts from) and every saved model come from
this one fit, so a candidate effect is always fitted by the same solver as the baseline it must beat.

Per axis i and orientation p: Acc_i = Acc0_{p,i} + dT (TDB_i + TDSF_i Acc0_{p,i}) + effect terms.
Linear parameters (Acc0 per orientation, TDB, TDSF, effect amplitudes) are solved by weighted
least squares; the bilinear TDSF*Acc0 products use the current Acc0 estimate and are iterated to
the fixed point (the product is ~1e-3 of Acc0, so 3 passes converge to machine precision). Shared
nonlinear parameters (lag and warm-up time constants, hysteresis width) are fitted by variable
projection: scipy.optimize.least_squares over them, with the linear solve inside.

Fitting runs on 10 s block means of the regressors (exact for a linear model: regressors are
computed per sample, then averaged), which keeps every fit fast; predictions are per sample.
Residual = measured - model, in mg, always.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from station.diagnostics.design import _Design
from station.diagnostics.effects import Effect, get_effect
from station.diagnostics.segmentation import DutData, train_mask


@dataclass
class DutFit:
    """A fitted model for one DUT (on the training blocks given)."""

    effects: list[str]
    nl: dict[str, dict[str, float]]  # effect -> nonlinear parameter -> value
    nl_sigma: dict[str, dict[str, float]]
    beta: list[np.ndarray]  # per axis, over columns (NaN-free; dropped columns are 0)
    beta_sigma: list[np.ndarray]
    col_names: list[list[str]]  # per axis
    acc0_g: np.ndarray  # (P, 3), NaN for orientations not in training
    ssr_block: np.ndarray  # (3,) weighted training SSR on block means (mg^2 * samples)
    n_train_blocks: int


def _solve(Xb: np.ndarray, yb: np.ndarray, w: np.ndarray, want_cov: bool = True):
    """Weighted least squares dropping columns that are zero on the training blocks."""
    sw = np.sqrt(w)
    A = Xb * sw[:, None]
    # a column with no support in the training data (e.g. a warm-up transient whose start is held
    # out, with a tiny tau) carries no information: do not let column scaling blow it up
    live = np.max(np.abs(A), axis=0) > 1e-9 * max(1.0, float(np.max(np.abs(A))))
    beta = np.zeros(Xb.shape[1])
    cov = np.full((Xb.shape[1], Xb.shape[1]), np.nan)
    if live.any():
        As = A[:, live]
        scale = np.linalg.norm(As, axis=0)
        scale[scale == 0] = 1.0
        sol, *_ = np.linalg.lstsq(As / scale, yb * sw, rcond=None)
        beta[live] = sol / scale
        if not want_cov:
            return beta, cov, live
        try:
            inv = np.linalg.pinv((As / scale).T @ (As / scale))
            cov[np.ix_(live, live)] = inv / np.outer(scale, scale)
        except np.linalg.LinAlgError:
            pass
    return beta, cov, live


def _inner(design: _Design, nl, train_blocks: np.ndarray, acc0_init: np.ndarray, passes: int = 3,
           want_cov: bool = True):
    """Linear solve with the Acc0 fixed-point iteration; returns betas, covs, acc0, residuals."""
    d = design.d
    P = len(d.pos_labels)
    acc0 = acc0_init.copy()
    w = d.block_count[train_blocks]
    for _ in range(passes):
        mats, names = design.block_matrices(nl, acc0)
        betas, covs, res = [], [], []
        new_acc0 = np.full((P, 3), np.nan)
        for i in range(3):
            Xb = mats[i][train_blocks]
            # a column with < 1 % of its full-log size in the training blocks (a warm-up transient
            # whose start is held out) would be extrapolated by 100x: not fitted in this fold
            full_max = np.max(np.abs(mats[i]), axis=0)
            weak = np.max(np.abs(Xb), axis=0) < 1e-2 * full_max if Xb.shape[0] else np.zeros(Xb.shape[1], bool)
            if weak.any():
                Xb = Xb.copy()
                Xb[:, weak] = 0.0
            yb = d.y_block[train_blocks, i]
            beta, cov, live = _solve(Xb, yb, w, want_cov=want_cov)
            betas.append(beta)
            covs.append(cov)
            res.append((yb - Xb @ beta) * np.sqrt(w))
            present = live[:P]
            new_acc0[present, i] = beta[:P][present]
        acc0 = new_acc0
    return betas, covs, acc0, np.concatenate(res), mats, names


def _nl_specs(effects: list[Effect]):
    return [(e.name, p) for e in effects for p in e.nonlinear]


def _initial_acc0(d: DutData, train_blocks: np.ndarray) -> np.ndarray:
    P = len(d.pos_labels)
    acc0 = np.full((P, 3), np.nan)
    for p in range(P):
        m = train_blocks & (d.block_pos == p)
        if m.any():
            acc0[p] = np.average(d.y_block[m], axis=0, weights=d.block_count[m]) / 1000.0
    return acc0


def fit_dut(d: DutData, effect_names: list[str], train_blocks: np.ndarray | None = None,
            nl_start: dict[str, dict[str, float]] | None = None, max_nfev: int = 40) -> DutFit:
    """Fit baseline + effects on the training blocks (all blocks by default)."""
    effects = [get_effect(n) for n in effect_names]
    if train_blocks is None:
        train_blocks = np.ones(d.block_starts.shape[0], bool)
    design = _Design(d, effects)
    acc0 = _initial_acc0(d, train_blocks)
    specs = _nl_specs(effects)
    nl: dict[str, dict[str, float]] = {e.name: {} for e in effects}
    nl_sigma: dict[str, dict[str, float]] = {e.name: {} for e in effects}
    if specs:
        def unpack(u):
            out = {e.name: {} for e in effects}
            for (name, p), v in zip(specs, u):
                out[name][p.name] = float(math.exp(v) if p.log else v)
            return out

        def pack(vals):
            return np.array([math.log(vals[name][p.name]) if p.log else vals[name][p.name]
                             for name, p in specs])

        lo = np.array([math.log(p.lower) if p.log else p.lower for _, p in specs])
        hi = np.array([math.log(p.upper) if p.log else p.upper for _, p in specs])
        # The Acc0 fixed point is solved once per stage (baseline, then at the start values) and held
        # during the search: one linear pass per evaluation, a deterministic objective for the
        # finite-difference Jacobian. The final solve below iterates Acc0 to convergence again.
        base_acc0 = _inner(_Design(d, []), {}, train_blocks, acc0, passes=2, want_cov=False)[2]
        state = {"acc0": base_acc0}

        def resid(u):
            _, _, a0, r, _, _ = _inner(design, unpack(u), train_blocks, state["acc0"], passes=1, want_cov=False)
            return r

        if nl_start and all(p.name in nl_start.get(name, {}) for name, p in specs):
            u0 = np.clip(pack(nl_start), lo + 1e-9, hi - 1e-9)
        else:
            # coarse grid per parameter (others at their init), best start for the polish
            u0 = np.array([math.log(p.init) if p.log else p.init for _, p in specs])
            for k in range(len(specs)):
                grid = np.linspace(lo[k], hi[k], 9)[1:-1]
                costs = []
                for g in grid:
                    u = u0.copy()
                    u[k] = g
                    costs.append(float(np.sum(resid(u) ** 2)))
                u0[k] = grid[int(np.argmin(costs))]
        state["acc0"] = _inner(design, unpack(u0), train_blocks, base_acc0, passes=2, want_cov=False)[2]
        sol = least_squares(resid, u0, bounds=(lo, hi), diff_step=1e-3, x_scale=1.0, max_nfev=max_nfev)
        nl = unpack(sol.x)
        # nonlinear uncertainty from the projected Jacobian (white-noise scaling; see noise_gls.gls_sigma)
        J = sol.jac
        dof = max(1, sol.fun.size - J.shape[1])
        s2 = float(np.sum(sol.fun**2)) / dof
        try:
            cov_u = np.linalg.pinv(J.T @ J) * s2
            for k, (name, p) in enumerate(specs):
                su = math.sqrt(max(cov_u[k, k], 0.0))
                val = nl[name][p.name]
                nl_sigma[name][p.name] = val * su if p.log else su
        except np.linalg.LinAlgError:
            pass
    betas, covs, acc0, r, mats, names = _inner(design, nl, train_blocks, acc0, passes=3)
    nb = int(train_blocks.sum())
    rk = [r[k * nb:(k + 1) * nb] for k in range(3)]
    ssr = np.array([float(np.sum(x**2)) for x in rk])
    # autocorrelated residuals: inflate the white-noise covariance by the integrated
    # autocorrelation time of the (weighted) block residual
    tau = np.array([_tau_int(x) for x in rk])
    sig = []
    for i in range(3):
        ncol = mats[i].shape[1]
        s2 = ssr[i] / max(1.0, nb - ncol) * tau[i]
        sig.append(np.sqrt(np.maximum(np.diag(covs[i]), 0.0) * s2))
    for name in nl_sigma:
        for k in nl_sigma[name]:
            nl_sigma[name][k] *= math.sqrt(float(np.mean(tau)))
    return DutFit(effects=list(effect_names), nl=nl, nl_sigma=nl_sigma, beta=betas, beta_sigma=sig,
                  col_names=names, acc0_g=acc0, ssr_block=ssr, n_train_blocks=nb)


def _tau_int(x: np.ndarray) -> float:
    """Integrated autocorrelation time (in samples) with Sokal's automatic window (c = 5)."""
    x = np.asarray(x, float)
    n = x.size
    if n < 8:
        return 1.0
    x = x - x.mean()
    f = np.fft.rfft(x, 2 * n)
    acf = np.fft.irfft(f * np.conj(f))[:n]
    if acf[0] <= 0:
        return 1.0
    rho = acf / acf[0]
    csum = 1.0 + 2.0 * np.cumsum(rho[1:])
    m = np.arange(1, n)
    ok = m >= 5.0 * csum
    tau = csum[np.argmax(ok)] if ok.any() else csum[-1]
    return float(min(max(tau, 1.0), n))


def predict_dut(d: DutData, fit: DutFit) -> np.ndarray:
    """Model prediction per sample (n, 3) in mg; NaN for orientations the fit never saw."""
    design = _Design(d, [get_effect(n) for n in fit.effects])
    P = len(d.pos_labels)
    a0 = np.nan_to_num(fit.acc0_g)[d.pos]  # (n, 3)
    ctx = design.context(fit.nl, a0)
    pred = np.empty((d.n, 3))
    for i in range(3):
        b = fit.beta[i]
        pred[:, i] = 1000.0 * b[:P][d.pos] + ctx.dt_c * (b[P] + b[P + 1] * a0[:, i] * 1e-3)
    k = P + 2
    for e in design.effects:
        c = e.columns(ctx, fit.nl.get(e.name, {}))
        m = c.shape[2]
        for i in range(3):
            if m:
                pred[:, i] += c[:, i, :] @ fit.beta[i][k:k + m]
        k += m
    unseen = np.isnan(fit.acc0_g[d.pos]).any(axis=1)
    pred[unseen] = np.nan
    return pred


def window_rms(d: DutData, resid_mg: np.ndarray, mask: np.ndarray | None = None,
               basis: str = "window") -> float:
    """RMS of the residual over axes: per sample, or of means over the RMS windows."""
    ok = ~np.isnan(resid_mg).any(axis=1)
    if mask is not None:
        ok &= mask
    if not ok.any():
        return float("nan")
    r = resid_mg[ok]
    if basis == "sample":
        return float(np.sqrt(np.mean(r**2)))
    wid = d.window[ok]
    cnt = np.bincount(wid).astype(float)
    sums = np.stack([np.bincount(wid, weights=r[:, i]) for i in range(3)], axis=1)
    keep = cnt > 0
    means = sums[keep] / cnt[keep, None]
    return float(np.sqrt(np.sum(cnt[keep, None] * means**2) / (3.0 * cnt[keep].sum())))


def heldout_residual(d: DutData, effect_names: list[str], full: DutFit, n_folds: int | None = None,
                     max_nfev: int = 8) -> np.ndarray:
    """Residual of each sample predicted by a fit that never saw its thermal leg nor the guard
    around it (blocked K-fold over whole legs, see Segmentation).

    An orientation seen only in held-out data has no fitted Acc0 (it is the fixture's reading, not
    a model parameter): its offset per axis is taken from the held-out residual itself, so the
    held-out error of such a leg is its shape error; every model gets the same treatment.
    """
    out = np.full((d.n, 3), np.nan)
    P = len(d.pos_labels)
    for k in range(d.n_folds):
        test = d.fold == k
        if not test.any():
            continue
        train_blocks = train_mask(d, k)
        if not train_blocks.any():
            continue
        f = fit_dut(d, effect_names, train_blocks, nl_start=full.nl, max_nfev=max_nfev)
        unseen = [p for p in range(P) if np.isnan(f.acc0_g[p]).any() and not np.isnan(full.acc0_g[p]).any()]
        if unseen:
            f.acc0_g = f.acc0_g.copy()
            f.beta = [b.copy() for b in f.beta]
            for p in unseen:
                f.acc0_g[p] = full.acc0_g[p]
                for i in range(3):
                    f.beta[i][p] = full.acc0_g[p, i]
        pred = predict_dut(d, f)
        r = d.acc_mg - pred
        for p in unseen:
            sel = test & (d.pos == p)
            if sel.any():
                r[sel] -= np.nanmean(r[sel], axis=0)
        out[test] = r[test]
    return out


__all__ = ["DutFit", "fit_dut", "predict_dut", "window_rms", "heldout_residual"]
