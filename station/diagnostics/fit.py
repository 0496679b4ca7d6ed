"""Fit the baseline thermal model (martinez2022 eq. 1), optionally plus effects, to one DUT's log,
and predict from the fit, in sample and held out.

Why a module of its own: every figure the ranking weighs (in-sample and held-out residuals, the
fitted Acc0 and nonlinear values the GLS comparison starts from) and every saved model come from
this one fit, so a candidate effect is always fitted by the same solver as the baseline it must beat.

Per axis i and orientation p: Acc_i = Acc0_{p,i} + dT (TDB_i + TDSF_i Acc0_{p,i}) + effect terms.
Linear parameters (Acc0 per orientation, TDB, TDSF, effect amplitudes) are solved by weighted
least squares; the bilinear TDSF*Acc0 products use the current Acc0 estimate and are iterated to
the fixed point (the product is ~1e-3 of Acc0, so 3 passes converge to machine precision). Shared
nonlinear parameters (lag time constants, hysteresis width, warm-up time constant) are fitted by
variable projection over them with the linear solve inside: a coarse profile grid, then Brent's
method (one parameter) or scipy.optimize.least_squares (more). A family's discrete shape is tried
in turn (fit_dut says how one is chosen).

Every fit and held-out prediction runs on the 10 s fit blocks (design._Design.block_matrices: the
terms at the blocks' mean time and temperatures), which keeps a 10 h log at 3 600 rows; the
per-sample prediction (predict_dut) serves plots and saved models.
Residual = measured - model, in mg, always.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg.lapack import dpotrf, dpotrs
from scipy.optimize import least_squares, minimize_scalar

from station.diagnostics.design import _Design
from station.diagnostics.effects import Effect, get_effect
from station.diagnostics.fold_support import unsupported
from station.diagnostics.rms import block_rms, window_rms
from station.diagnostics.segmentation import DutData, train_mask
from station.science.chunked import pieces
from contracts.types import T_REF_C


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
    heldout_block: np.ndarray | None = None  # a family's held-out residual, when it chose its shape by it


def _solve(A: np.ndarray, yw: np.ndarray, want_cov: bool = True):
    """Least squares of the (already weighted) design A against yw, dropping columns that are zero
    on the training blocks.

    Columns scaled to unit norm, then the normal equations by Cholesky (a few dozen columns over a
    few thousand blocks: ~10x faster than an SVD); a nearly singular system falls back to lstsq.
    The factorization is LAPACK's potrf/potrs called directly (what scipy.linalg.cho_factor and
    cho_solve call, without their per-call checks: this runs thousands of times per diagnosis)."""
    norm = np.sqrt(np.einsum("ij,ij->j", A, A))
    # a column with no support in the training data (e.g. a warm-up transient whose start is held
    # out, with a tiny tau) carries no information: do not let column scaling blow it up
    live = norm > 1e-9 * max(1.0, float(norm.max(initial=0.0)))
    beta = np.zeros(A.shape[1])
    cov = np.full((A.shape[1], A.shape[1]), np.nan)
    if live.any():
        scale = norm[live]
        As = A[:, live]  # (the mask's copy is column-major: every product below depends on it)
        As /= scale
        G = As.T @ As
        try:
            c, info = dpotrf(G, lower=0, clean=0, overwrite_a=0)
            if info != 0:
                raise np.linalg.LinAlgError("not positive definite")
            dg = np.abs(np.diag(c))
            if dg.min() < 1e-6 * dg.max():
                raise np.linalg.LinAlgError("ill-conditioned")
            sol, info = dpotrs(c, As.T @ yw, lower=0, overwrite_b=0)
            if info != 0:
                raise ValueError("potrs")
        except (np.linalg.LinAlgError, ValueError):
            sol, *_ = np.linalg.lstsq(As, yw, rcond=None)
        beta[live] = sol / scale
        if not want_cov:
            return beta, cov, live
        try:
            inv = np.linalg.pinv(G)
            cov[np.ix_(live, live)] = inv / np.outer(scale, scale)
        except np.linalg.LinAlgError:
            pass
    return beta, cov, live


def _inner(design: _Design, nl, train_blocks: np.ndarray, acc0_init: np.ndarray, passes: int = 3,
           want_cov: bool = True):
    """Linear solve with the Acc0 fixed-point iteration; returns betas, covs, acc0, residuals,
    the number of columns of the last pass's design per axis and the parameter names (the designs
    themselves are not kept: three of them are 40 MB on a 200 MB log's blocks)."""
    d = design.d
    P = len(d.pos_labels)
    acc0 = acc0_init.copy()
    everything = bool(train_blocks.all())
    rows = None if everything else np.flatnonzero(train_blocks)  # (taking rows by index: faster than a mask)
    sw = np.sqrt(d.block_count if rows is None else d.block_count[rows])
    yw_all = (d.y_block if rows is None else d.y_block[rows]) * sw[:, None]
    names = design.names()
    mats: list[int] = []
    for _ in range(passes):
        full = design.block_parts(nl, acc0)
        parts = full if rows is None else full.rows(rows)
        weak = None
        if parts.n_effect_cols and rows is not None and rows.size:
            # an effect column with < 1 % of its full-log size in the training blocks (a warm-up
            # transient whose start is held out) would be extrapolated by 100x: not fitted here
            weak = parts.effect_absmax() < 1e-2 * full.effect_absmax()
        betas, covs, res, mats = [], [], [], []
        new_acc0 = np.full((P, 3), np.nan)
        for i in range(3):
            Xb = parts.matrix(i)
            if weak is not None:
                w_i = weak[i] | unsupported(full.matrix(i), rows, P, X_train=Xb)
                if w_i.any():
                    Xb[:, P + 2:][:, w_i] = 0.0
            A = np.multiply(Xb, sw[:, None], out=Xb)  # Xb * sw in place: the design is not needed after
            yw = yw_all[:, i]
            beta, cov, live = _solve(A, yw, want_cov=want_cov)
            betas.append(beta)
            covs.append(cov)
            mats.append(Xb.shape[1])
            res.append(yw - A @ beta)
            present = live[:P]
            new_acc0[present, i] = beta[:P][present]
        acc0 = new_acc0
    return betas, covs, acc0, np.concatenate(res), mats, names


def _initial_acc0(d: DutData, train_blocks: np.ndarray) -> np.ndarray:
    key = ("_fit_initial_acc0", train_blocks.tobytes())  # a function of the data and the training blocks
    acc0 = d.block_cache.get(key)
    if acc0 is None:
        P = len(d.pos_labels)
        acc0 = np.full((P, 3), np.nan)
        for p in range(P):
            m = train_blocks & (d.block_pos == p)
            if m.any():
                acc0[p] = np.average(d.y_block[m], axis=0, weights=d.block_count[m]) / 1000.0
        d.block_cache[key] = acc0
    return acc0.copy()


def _baseline_acc0(d: DutData, train_blocks: np.ndarray, acc0: np.ndarray) -> np.ndarray:
    """Acc0 of the baseline fit on the training blocks (two fixed-point passes from acc0, the
    blocks' own means): where every nonlinear search of a candidate starts; computed once per
    training set (each candidate's fold refits ask for the same ones)."""
    key = ("_fit_baseline_acc0", train_blocks.tobytes(), acc0.tobytes())
    out = d.block_cache.get(key)
    if out is None:
        out = d.block_cache[key] = _inner(_Design(d, []), {}, train_blocks, acc0, passes=2, want_cov=False)[2]
    return out.copy()


def _shape_choices(effects: list[Effect], nl_start: dict | None) -> list[dict[str, dict[str, float]]]:
    """Every combination of the families' discrete shapes to fit; an effect whose shape the start
    holds (a fold refit, or an effect admitted before) keeps it."""
    combos: list[dict[str, dict[str, float]]] = [{}]
    for e in effects:
        for p in e.nonlinear:
            if not p.choices:
                continue
            start = (nl_start or {}).get(e.name, {})
            ks = [float(start[p.name])] if p.name in start else [float(k) for k in range(len(p.choices))]
            combos = [{**c, e.name: {**c.get(e.name, {}), p.name: k}} for c in combos for k in ks]
    return combos


def _fit_continuous(design: _Design, effects: list[Effect], fixed: dict, train_blocks: np.ndarray,
                    base_acc0: np.ndarray, nl_start: dict | None, max_nfev: int, want_sigma: bool = True):
    """Variable projection over the continuous nonlinear parameters active for the fixed shapes:
    a coarse profile grid per parameter the start does not hold (others held), then a bounded
    local refine (Brent for one parameter, trust-region least squares for more). Returns the
    values, their sigmas (projected Jacobian, white-noise scaling) and the weighted residual."""
    specs = [(e.name, p) for e in effects for p in e.active(fixed.get(e.name, {}))]
    start = nl_start or {}

    def unpack(u):
        out = {e.name: dict(fixed.get(e.name, {})) for e in effects}
        for (name, p), v in zip(specs, u):
            out[name][p.name] = float(math.exp(v) if p.log else v)
        return out

    lo = np.array([math.log(p.lower) if p.log else p.lower for _, p in specs])
    hi = np.array([math.log(p.upper) if p.log else p.upper for _, p in specs])
    # The Acc0 fixed point is held during the search: one linear pass per evaluation, a
    # deterministic objective for the finite-difference Jacobian (the final solve iterates again).
    state = {"acc0": base_acc0}

    def resid(u):
        return _inner(design, unpack(u), train_blocks, state["acc0"], passes=1, want_cov=False)[3]

    if not specs:
        return unpack(np.zeros(0)), {e.name: {} for e in effects}, resid(np.zeros(0))
    u0 = np.empty(len(specs))
    half_step = np.full(len(specs), 0.25)  # the local refine's reach around a start (log units)
    gridded = []
    for k, (name, p) in enumerate(specs):
        if p.name in start.get(name, {}):
            v = start[name][p.name]
            u0[k] = min(max(math.log(v) if p.log else v, lo[k] + 1e-9), hi[k] - 1e-9)
        else:
            u0[k] = math.log(p.init) if p.log else p.init
            gridded.append(k)
    for k in gridded:  # coarse profile grid per parameter, the others held
        grid = np.linspace(lo[k], hi[k], specs[k][1].grid + 2)[1:-1]
        costs = []
        for g in grid:
            u = u0.copy()
            u[k] = g
            costs.append(float(np.sum(resid(u) ** 2)))
        u0[k] = grid[int(np.argmin(costs))]
        half_step[k] = grid[1] - grid[0]
    state["acc0"] = _inner(design, unpack(u0), train_blocks, base_acc0, passes=2, want_cov=False)[2]
    if len(specs) == 1:
        a, b = max(lo[0], u0[0] - half_step[0]), min(hi[0], u0[0] + half_step[0])
        seen: dict[bytes, np.ndarray] = {}  # Brent's residuals: the point it returns is not evaluated twice

        def ssr1(x) -> float:
            u = np.array([x])
            r = seen[u.tobytes()] = resid(u)
            return float(np.sum(r ** 2))

        sol1 = minimize_scalar(ssr1, bounds=(a, b), method="bounded", options={"xatol": 2e-3, "maxiter": max_nfev})
        x = np.array([sol1.x]) if sol1.fun <= float(np.sum(resid(u0) ** 2)) else u0
        fun = seen.get(x.tobytes())
        if fun is None:
            fun = resid(x)
        h = 1e-3
        J = ((resid(x + h) - resid(x - h)) / (2 * h))[:, None] if want_sigma else np.zeros((fun.size, 1))
    else:
        sol = least_squares(resid, u0, bounds=(lo, hi), diff_step=1e-3, x_scale=1.0, max_nfev=max_nfev)
        x, fun, J = sol.x, sol.fun, sol.jac
    nl = unpack(x)
    nl_sigma: dict[str, dict[str, float]] = {e.name: {} for e in effects}
    s2 = float(np.sum(fun**2)) / max(1, fun.size - J.shape[1])
    try:
        cov_u = np.linalg.pinv(J.T @ J) * s2
        for k, (name, p) in enumerate(specs):
            su = math.sqrt(max(cov_u[k, k], 0.0))
            val = nl[name][p.name]
            nl_sigma[name][p.name] = val * su if p.log else su
    except np.linalg.LinAlgError:
        pass
    return nl, nl_sigma, fun


def _shape_scores(design: _Design, tried: list, train_blocks: np.ndarray, base_acc0: np.ndarray):
    """Per fitted shape of a family: BIC of the residuals prewhitened by an AR(1) of the best
    shape's residual (the bias wander of a real part would otherwise make every residual look like
    a few independent numbers, or like thousands), and the number of parameters the shape brings:
    its nonlinear ones and its live amplitudes (a superposition's 18 against a single operator's 3)."""
    P = len(design.d.pos_labels)
    best = min(tried, key=lambda t: float(np.sum(t[2] ** 2)))[2]
    phi = [float(np.clip(x[1:] @ x[:-1] / max(float(x[:-1] @ x[:-1]), 1e-300), 0.0, 0.999))
           for x in np.split(best, 3)]
    n = best.size
    scores, ks = [], []
    for nl, _, r in tried:
        ssr = sum(float(np.sum((x[1:] - f * x[:-1]) ** 2)) for x, f in zip(np.split(r, 3), phi))
        mats, _ = design.block_matrices(nl, base_acc0)
        k = sum(get_effect(e).n_nonlinear(v) for e, v in nl.items()) + sum(
            int(np.count_nonzero(np.any(m[train_blocks, P + 2:] != 0, axis=0))) for m in mats)
        scores.append(n * math.log(max(ssr / n, 1e-300)) + k * math.log(n))
        ks.append(k)
    return scores, ks


def _choose_full(scores: list[float], held, ks: list[int]) -> int:
    """A family's shape on the full log: start from the simplest shapes (fewest parameters; the
    best prewhitened BIC among equals) and move to one with more parameters only when it wins on
    both counts: a prewhitened BIC lower by SHAPE_MARGIN and a held-out error (held(j), computed
    only for such a contender and the shape it would replace) lower by SHAPE_HELDOUT_MARGIN_REL.
    In-sample evidence alone let an 18-amplitude superposition fit a lag and a hysteresis that
    mask each other and predict held-out legs 16 % worse than the baseline; held-out error alone
    preferred a second-order lag on first-order data by 1.1 % (the 10 s blocks' discretization),
    at a BIC only 21 lower."""
    order = sorted(range(len(ks)), key=lambda j: (ks[j], scores[j]))
    cur = order[0]
    for j in order[1:]:
        if ks[j] > ks[cur] and scores[j] < scores[cur] - SHAPE_MARGIN and \
                held(j) < held(cur) * (1.0 - SHAPE_HELDOUT_MARGIN_REL):
            cur = j
    return cur


def _simplest_near(values: list[float], ks: list[int], margin: float) -> int:
    """The shape with the fewest parameters among those within margin of the best value."""
    near = [j for j in range(len(values)) if values[j] <= min(values) + margin]
    return min(near, key=lambda j: (ks[j], values[j]))


# The margin on delta BIC for an approximate noise model (here the AR(1) prewhitening); the
# admission gate uses the same one (gate.EVIDENCE_TIE = SHAPE_MARGIN). Measured: a first-order lag's truth gave its
# second-order fit (die 15 s + package 132 s, the 10 s blocks' discretization) a BIC 21 lower.
SHAPE_MARGIN = 30.0
# ... and on the full log a shape with more parameters must also predict held-out legs 1 % better
SHAPE_HELDOUT_MARGIN_REL = 0.01


def fit_dut(d: DutData, effect_names: list[str], train_blocks: np.ndarray | None = None,
            nl_start: dict[str, dict[str, float]] | None = None, max_nfev: int = 40) -> DutFit:
    """Fit baseline + effects on the training blocks (all blocks by default).

    A family (an effect with a discrete shape parameter) is fitted in every shape. On the full log
    a shape with more parameters is kept only when it wins both in sample and on held-out legs
    (_choose_full); on a part of it (a fold) the simplest within SHAPE_MARGIN of the best
    prewhitened BIC. With
    nl_start (a fold refit) the shape is the start's and only the continuous values are refined.
    """
    effects = [get_effect(n) for n in effect_names]
    if train_blocks is None:
        train_blocks = np.ones(d.block_starts.shape[0], bool)
    design = _Design(d, effects)
    acc0 = _initial_acc0(d, train_blocks)
    nl: dict[str, dict[str, float]] = {e.name: {} for e in effects}
    nl_sigma: dict[str, dict[str, float]] = {e.name: {} for e in effects}
    if any(e.nonlinear for e in effects):
        base_acc0 = _baseline_acc0(d, train_blocks, acc0)
        tried = [_fit_continuous(design, effects, fixed, train_blocks, base_acc0, nl_start, max_nfev,
                                 want_sigma=max_nfev >= 20)
                 for fixed in _shape_choices(effects, nl_start)]
        if len(tried) == 1:
            nl, nl_sigma, _ = tried[0]
        else:
            scores, ks = _shape_scores(design, tried, train_blocks, base_acc0)
            if bool(train_blocks.all()):  # the full fit: more parameters must also predict better
                fits: dict[int, DutFit] = {}

                def held(j: int) -> float:  # held-out error of shape j, computed when first asked
                    if j not in fits:
                        fits[j] = _finish(d, effect_names, design, tried[j][0], tried[j][1], train_blocks, acc0,
                                          max_nfev)
                        fits[j].heldout_block = heldout_blocks(d, effect_names, fits[j])
                    return block_rms(d, fits[j].heldout_block)

                j = _choose_full(scores, held, ks)
                held(j)
                return fits[j]
            nl, nl_sigma, _ = tried[_simplest_near(scores, ks, SHAPE_MARGIN)]
    return _finish(d, effect_names, design, nl, nl_sigma, train_blocks, acc0, max_nfev)


def _finish(d: DutData, effect_names: list[str], design: _Design, nl: dict, nl_sigma: dict,
            train_blocks: np.ndarray, acc0: np.ndarray, max_nfev: int) -> DutFit:
    """The linear solve at the chosen nonlinear values (Acc0 iterated to its fixed point), with
    parameter sigmas for a full fit."""
    nl_sigma = {k: dict(v) for k, v in nl_sigma.items()}
    want_sigma = max_nfev >= 20  # a fold refit only predicts its held-out leg
    betas, covs, acc0, r, mats, names = _inner(design, nl, train_blocks, acc0, passes=3, want_cov=want_sigma)
    nb = int(train_blocks.sum())
    rk = [r[k * nb:(k + 1) * nb] for k in range(3)]
    ssr = np.array([float(np.sum(x**2)) for x in rk])
    # autocorrelated residuals: inflate the white-noise covariance by the integrated
    # autocorrelation time of the (weighted) block residual
    tau = np.array([_tau_int(x) for x in rk]) if want_sigma else np.ones(3)
    sig = []
    for i in range(3):
        ncol = mats[i]
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


def _predict_baseline(d: DutData, fit: DutFit, axes: tuple[int, ...]) -> np.ndarray:
    """The baseline's prediction (n, len(axes)) in mg, sample by sample, a piece at a time (no
    per-sample temporaries of the whole log); NaN for orientations the fit never saw."""
    P = len(d.pos_labels)
    pred = np.empty((d.n, len(axes)))
    acc0 = np.nan_to_num(fit.acc0_g)
    for a, b in pieces([(0, d.n)]):
        pos = d.pos[a:b]
        a0_p, dt_c = acc0[pos], d.temp_c[a:b] - T_REF_C
        for j, i in enumerate(axes):
            bi = fit.beta[i]
            pred[a:b, j] = 1000.0 * bi[:P][pos] + dt_c * (bi[P] + bi[P + 1] * a0_p[:, i] * 1e-3)
        pred[a:b][np.isnan(fit.acc0_g[pos]).any(axis=1)] = np.nan
    return pred


def predict_dut_axis(d: DutData, fit: DutFit, axis: int) -> np.ndarray:
    """predict_dut(d, fit)[:, axis], for the baseline without the other two axes."""
    if not fit.effects:
        return _predict_baseline(d, fit, (axis,))[:, 0]
    return predict_dut(d, fit)[:, axis].copy()


def predict_dut(d: DutData, fit: DutFit) -> np.ndarray:
    """Model prediction per sample (n, 3) in mg; NaN for orientations the fit never saw."""
    design = _Design(d, [get_effect(n) for n in fit.effects])
    P = len(d.pos_labels)
    if not design.effects:
        return _predict_baseline(d, fit, (0, 1, 2))
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


def predict_blocks(d: DutData, fit: DutFit) -> np.ndarray:
    """Model prediction on the fit blocks (n_blocks, 3) in mg; NaN for orientations never seen."""
    mats, _ = _Design(d, [get_effect(n) for n in fit.effects]).block_matrices(fit.nl, fit.acc0_g)
    pred = np.stack([mats[i] @ fit.beta[i] for i in range(3)], axis=1)
    pred[np.isnan(fit.acc0_g[d.block_pos]).any(axis=1)] = np.nan
    return pred


def heldout_blocks(d: DutData, effect_names: list[str], full: DutFit, max_nfev: int = 8) -> np.ndarray:
    """Residual of each block predicted by a fit that never saw its thermal leg nor the guard
    around it (blocked K-fold over whole legs, see Segmentation); (n_blocks, 3) mg.

    A fold refit starts from the full fit's nonlinear values and keeps a family's shape (choosing
    among two or three shapes on all the data is a small optimism the gate's charge covers).
    An orientation seen only in held-out data has no fitted Acc0 (it is the fixture's reading, not
    a model parameter): its offset per axis is taken from the held-out residual itself, so the
    held-out error of such a leg is its shape error; every model gets the same treatment.
    """
    out = np.full((d.block_starts.shape[0], 3), np.nan)
    P = len(d.pos_labels)
    for k in range(d.n_folds):
        test = d.block_fold == k
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
        r = d.y_block - predict_blocks(d, f)
        for p in unseen:
            sel = test & (d.block_pos == p)
            if sel.any():
                r[sel] -= np.average(r[sel], axis=0, weights=d.block_count[sel])
        out[test] = r[test]
    return out


__all__ = ["DutFit", "fit_dut", "predict_dut", "predict_dut_axis", "predict_blocks", "window_rms", "block_rms", "heldout_blocks"]
