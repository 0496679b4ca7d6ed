"""Fit the baseline thermal model (martinez2022 eq. 1), optionally plus effects, to one DUT's log.

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

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from station.diagnostics.effects import Context, Effect, get_effect, smooth_temperature
from contracts.logfile import DutLog
from contracts.types import AXES, StationError, T_REF_C

MODEL_FORMAT = "station-diagnostic-model"
MODEL_VERSION = 1


@dataclass
class Segmentation:
    """Block structure used for fitting, scoring and held-out folds (all contiguous in time).

    Held-out units are whole thermal legs (a heating or a cooling ramp with its hold: one step of a
    profile), never short interleaved chunks: the bias of a real MEMS part wanders (random walk,
    flicker), so neighbouring minutes share their error and a chunk predicted from its neighbours
    looks better than it is. Legs are assigned to at most n_folds folds in turn, and every fit
    leaves out, besides its fold, a guard of guard_s on both sides of each held-out leg.
    """

    fit_block_s: float = 10.0  # regressors averaged over these for the fit
    window_s: float = 60.0  # residual RMS reported on means over these windows
    n_folds: int = 6  # folds of whole legs (fewer when the log has fewer legs)
    guard_s: float = 600.0  # training excludes this much data on each side of a held-out leg
    min_leg_s: float = 900.0  # shorter legs are merged into their neighbour
    turn_c: float = 3.0  # a temperature reversal of this much ends a leg
    min_segments: int = 5  # fewer legs than this: each is cut into equal pieces


@dataclass
class DutData:
    """One DUT's log prepared for fitting: orientation codes, blocks, windows and folds."""

    serial: str
    time_s: np.ndarray
    acc_mg: np.ndarray  # (n, 3)
    temp_c: np.ndarray
    temp_smooth_c: np.ndarray
    pos: np.ndarray  # (n,) orientation code 0..P-1
    pos_labels: list[str]
    block: np.ndarray  # (n,) fit-block id (contiguous, sorted)
    block_starts: np.ndarray
    window: np.ndarray  # (n,) RMS window id
    chunk: np.ndarray  # (n,) held-out segment id (a whole thermal leg)
    fold: np.ndarray  # (n,) fold of the sample
    run: np.ndarray  # (n,) constant-orientation run id
    t_power_on_s: float
    lamp: np.ndarray | None = None
    block_pos: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    block_count: np.ndarray = field(default_factory=lambda: np.zeros(0))
    block_fold: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    block_chunk: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    block_time_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    seg_bounds_s: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (n_segments, 2) time span
    guard_s: float = 600.0
    n_folds: int = 1
    y_block: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    cache: dict = field(default_factory=dict)  # per-sample regressors that depend only on the data

    @property
    def n(self) -> int:
        return int(self.time_s.shape[0])

    def block_mean(self, x: np.ndarray) -> np.ndarray:
        s = np.add.reduceat(x, self.block_starts, axis=0)
        shape = (-1,) + (1,) * (x.ndim - 1)
        return s / self.block_count.reshape(shape)


def _orientation_codes(log: DutLog) -> tuple[np.ndarray, list[str]]:
    """Orientation per sample: the log's position column, else clusters of the acceleration."""
    if log.position is not None and np.all(log.position >= 0):
        uniq = sorted(set(int(p) for p in np.unique(log.position)))
        lut = {p: k for k, p in enumerate(uniq)}
        return np.array([lut[int(p)] for p in log.position], dtype=np.int64), [str(p) for p in uniq]
    # No position column: an orientation is a cluster of readings within 0.3 g on every axis.
    centers: list[np.ndarray] = []
    codes = np.empty(len(log), dtype=np.int64)
    rounded = np.round(log.acc_g / 0.05) * 0.05
    prev = -1
    for k in range(len(log)):
        a = rounded[k]
        if prev >= 0 and np.max(np.abs(a - centers[prev])) < 0.3:
            codes[k] = prev
            continue
        for c, ctr in enumerate(centers):
            if np.max(np.abs(a - ctr)) < 0.3:
                prev = c
                break
        else:
            centers.append(a.copy())
            prev = len(centers) - 1
        codes[k] = prev
    return codes, [f"o{k}" for k in range(len(centers))]


def _legs(time_s: np.ndarray, temp_c: np.ndarray, a: int, b: int, seg: Segmentation) -> list[int]:
    """Start indices (relative to a) of the thermal legs of samples a:b: a leg ends at a temperature
    extreme once the temperature has turned back by seg.turn_c; legs shorter than min_leg_s merge."""
    t = time_s[a:b]
    T = temp_c[a:b]
    n = b - a
    starts = [0]
    step = 16  # the smoothed temperature is slow: every 16th sample finds the turns
    idx = np.arange(0, n, step)
    Td = T[idx]
    direction, ext = 0, 0
    for k in range(1, Td.shape[0]):
        if direction == 0:
            if Td[k] - Td[0] >= seg.turn_c:
                direction, ext = 1, int(np.argmax(Td[:k + 1]))
            elif Td[0] - Td[k] >= seg.turn_c:
                direction, ext = -1, int(np.argmin(Td[:k + 1]))
        elif direction > 0:
            if Td[k] > Td[ext]:
                ext = k
            elif Td[ext] - Td[k] >= seg.turn_c:
                starts.append(int(idx[ext]))
                direction, ext = -1, k
        else:
            if Td[k] < Td[ext]:
                ext = k
            elif Td[k] - Td[ext] >= seg.turn_c:
                starts.append(int(idx[ext]))
                direction, ext = 1, k
    # merge short legs into the previous one (the first into the next)
    out: list[int] = []
    bounds = starts + [n]
    for k in range(len(starts)):
        dur = t[bounds[k + 1] - 1] - t[bounds[k]]
        if out and dur < seg.min_leg_s:
            continue
        out.append(bounds[k])
    if len(out) > 1 and t[-1] - t[out[-1]] < seg.min_leg_s:
        out.pop()
    if len(out) > 1 and t[out[1] - 1] - t[0] < seg.min_leg_s:
        out.pop(1)
    return out or [0]


def prepare(log: DutLog, seg: Segmentation | None = None) -> DutData:
    """Cut a log into constant-orientation runs, fit blocks, RMS windows and held-out legs."""
    seg = seg or Segmentation()
    n = len(log)
    if n < 50:
        raise StationError(f"{log.serial or 'log'}: only {n} samples, too short to diagnose")
    time_s = np.asarray(log.time_s, dtype=np.float64)
    if np.any(np.diff(time_s) <= 0):
        raise StationError(f"{log.serial or 'log'}: time_s is not strictly increasing")
    dt = float(np.median(np.diff(time_s)))
    pos, labels = _orientation_codes(log)
    temp_c = np.asarray(log.temp_c, dtype=np.float64)
    temp_smooth = smooth_temperature(temp_c, time_s, 60.0)
    brk = np.flatnonzero((np.diff(pos) != 0) | (np.diff(time_s) > 10 * dt)) + 1
    starts = np.concatenate([[0], brk])
    ends = np.concatenate([brk, [n]])
    bs = max(1, int(round(seg.fit_block_s / dt)))
    ws = bs * max(1, int(round(seg.window_s / seg.fit_block_s)))
    # held-out segments: thermal legs of every run (a run with no turn is one leg) ...
    seg_starts = []  # absolute sample index of each segment start (run starts included)
    for a, b in zip(starts, ends):
        seg_starts += [a + k for k in _legs(time_s, smooth_temperature(temp_smooth, time_s, 300.0), a, b, seg)]
    # ... and when there are too few, each leg cut into equal pieces (never fewer than min_segments)
    if len(seg_starts) < seg.min_segments:
        pieces = int(math.ceil(seg.min_segments / len(seg_starts)))
        bounds = seg_starts + [n]
        seg_starts = [int(bounds[k] + (bounds[k + 1] - bounds[k]) * j // pieces)
                      for k in range(len(bounds) - 1) for j in range(pieces)]
    seg_id = np.zeros(n, np.int64)
    seg_id[np.array(seg_starts[1:], dtype=np.int64)] = 1
    seg_id = np.cumsum(seg_id)
    block = np.empty(n, np.int64)
    window = np.empty(n, np.int64)
    run = np.empty(n, np.int64)
    nb = nw = 0
    # blocks never straddle a run or a segment boundary
    cut = np.unique(np.concatenate([starts, np.array(seg_starts, dtype=np.int64)]))
    cut_end = np.concatenate([cut[1:], [n]])
    for a, b in zip(cut, cut_end):
        k = np.arange(b - a)
        block[a:b] = nb + k // bs
        window[a:b] = nw + k // ws
        nb = block[b - 1] + 1
        nw = window[b - 1] + 1
    for r, (a, b) in enumerate(zip(starts, ends)):
        run[a:b] = r
    n_seg = int(seg_id[-1]) + 1
    n_folds = max(2, min(seg.n_folds, n_seg))
    fold = seg_id % n_folds
    block_starts = np.flatnonzero(np.concatenate([[True], np.diff(block) != 0]))
    meta_on = log.meta.get("t_power_on_s")
    t_on = float(meta_on) if meta_on not in (None, "") else min(0.0, float(time_s[0]))
    d = DutData(
        serial=log.serial or "dut",
        time_s=time_s,
        acc_mg=np.asarray(log.acc_g, dtype=np.float64) * 1000.0,
        temp_c=temp_c,
        temp_smooth_c=temp_smooth,
        pos=pos, pos_labels=labels, block=block, block_starts=block_starts, window=window,
        chunk=seg_id, fold=fold, run=run, t_power_on_s=t_on, lamp=log.lamp,
    )
    d.block_count = np.diff(np.concatenate([block_starts, [n]])).astype(np.float64)
    d.block_pos = pos[block_starts]
    d.block_fold = fold[block_starts]
    d.block_chunk = seg_id[block_starts]
    d.block_time_s = d.block_mean(time_s)
    first = np.flatnonzero(np.concatenate([[True], np.diff(seg_id) != 0]))
    last = np.concatenate([first[1:] - 1, [n - 1]])
    d.seg_bounds_s = np.stack([time_s[first], time_s[last]], axis=1)
    d.guard_s = seg.guard_s
    d.n_folds = n_folds
    d.y_block = d.block_mean(d.acc_mg)
    return d


def train_mask(d: DutData, k: int) -> np.ndarray:
    """Training blocks of fold k: not in the fold, and not within the guard of a held-out segment."""
    held = np.flatnonzero(np.arange(d.seg_bounds_s.shape[0]) % d.n_folds == k)
    ok = d.block_fold != k
    tb = d.block_time_s
    for s_ in held:
        lo, hi = d.seg_bounds_s[s_]
        ok &= ~((tb > lo - d.guard_s) & (tb < hi + d.guard_s))
    return ok


# ---------------------------------------------------------------------------------------------
# fitting


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


TDSF_MIN_SPREAD_G = 0.25  # TDSF needs orientations whose Acc0 on the axis differ by at least this


def tdsf_identifiable(acc0_g: np.ndarray) -> np.ndarray:
    """(3,) bool: per axis, do the orientations seen give TDSF a lever arm (Acc0 spread)?

    TDSF multiplies Acc0 (martinez2022 eq. 1): with one orientation, or orientations with the same
    Acc0 on an axis, dT TDSF Acc0 is a multiple of dT and only the total drift TDB + TDSF Acc0 is
    measurable. The column is then left out (TDSF = 0, TDB = the total drift), never fitted to noise.
    """
    a = np.asarray(acc0_g, float)
    ok = ~np.isnan(a).any(axis=1)
    if ok.sum() < 2:
        return np.zeros(3, bool)
    return (a[ok].max(axis=0) - a[ok].min(axis=0)) >= TDSF_MIN_SPREAD_G


class _Design:
    """Builds the per-sample design matrix for a DUT, an effect list and nonlinear values."""

    def __init__(self, d: DutData, effects: list[Effect]):
        self.d = d
        self.effects = effects
        self.lag = [e for e in effects if type(e).temperature is not Effect.temperature]

    def temp_seen(self, nl: dict[str, dict[str, float]]) -> np.ndarray:
        t = self.d.temp_c
        for e in self.lag:
            t2 = e.temperature(t, self.d.time_s, nl.get(e.name, {}))
            if t2 is not None:
                t = t2
        return t

    def context(self, nl, acc0_sample_g: np.ndarray) -> Context:
        d = self.d
        return Context(time_s=d.time_s, temp_c=d.temp_c, temp_smooth_c=d.temp_smooth_c,
                       dt_c=self.temp_seen(nl) - T_REF_C, acc0_g=acc0_sample_g,
                       t_power_on_s=d.t_power_on_s, cache=d.cache)

    def names(self) -> list[list[str]]:
        d = self.d
        out = []
        for _ in range(3):
            nm = [f"acc0_g[{lab}]" for lab in d.pos_labels] + ["tdb_mg_per_c", "tdsf_ppm_per_c"]
            for e in self.effects:
                nm += [f"{e.name}.{ln}" for ln in e.linear]
            out.append(nm)
        return out

    def block_matrices(self, nl, acc0_g: np.ndarray) -> tuple[list[np.ndarray], list[list[str]]]:
        """Per axis: the block means of the design (n_blocks, k); same columns as matrices().

        Every fit block lies inside one constant-orientation run, so Acc0 is constant over a
        block and the orientation indicators and the TDSF column (dT * Acc0) are formed from
        block means directly; only the dT and effect columns are averaged sample by sample.
        """
        d = self.d
        P = len(d.pos_labels)
        a0 = np.nan_to_num(acc0_g)
        if self.effects:
            ctx = self.context(nl, a0[d.pos])
            dt_c = ctx.dt_c
            extra = [e.columns(ctx, nl.get(e.name, {})) for e in self.effects]
        else:
            dt_c = d.cache.get("_dt_c")
            if dt_c is None:
                dt_c = d.cache["_dt_c"] = self.temp_seen(nl) - T_REF_C
            extra = []
        ind = d.cache.get("_block_indicator")
        if ind is None or ind.shape[1] != P:
            ind = np.zeros((d.block_starts.shape[0], P))
            ind[np.arange(ind.shape[0]), d.block_pos] = 1000.0
            d.cache["_block_indicator"] = ind
        dtb = d.block_mean(dt_c)
        a0b = a0[d.block_pos] * tdsf_identifiable(acc0_g)[None, :]
        eff_blocks = [d.block_mean(c.reshape(d.n, -1)).reshape(-1, 3, c.shape[2]) for c in extra if c.shape[2]]
        mats = []
        for i in range(3):
            cols = [ind, dtb[:, None], (dtb * a0b[:, i] * 1e-3)[:, None]] + [eb[:, i, :] for eb in eff_blocks]
            mats.append(np.hstack(cols))
        return mats, self.names()

    def matrices(self, nl, acc0_g: np.ndarray) -> tuple[list[np.ndarray], list[list[str]]]:
        """Per axis: (n, k) design in mg per unit of parameter, and the parameter names."""
        d = self.d
        P = len(d.pos_labels)
        a0 = np.nan_to_num(acc0_g)[d.pos]  # (n, 3)
        ctx = self.context(nl, a0)
        tdsf_on = tdsf_identifiable(acc0_g)
        ind = np.zeros((d.n, P))
        ind[np.arange(d.n), d.pos] = 1000.0  # Acc0 in g -> mg
        extra = [e.columns(ctx, nl.get(e.name, {})) for e in self.effects]
        mats, names = [], []
        for i in range(3):
            cols = [ind, ctx.dt_c[:, None], (ctx.dt_c * a0[:, i] * 1e-3 * tdsf_on[i])[:, None]]
            nm = [f"acc0_g[{lab}]" for lab in d.pos_labels] + ["tdb_mg_per_c", "tdsf_ppm_per_c"]
            for e, c in zip(self.effects, extra):
                if c.shape[2]:
                    cols.append(c[:, i, :])
                    nm += [f"{e.name}.{ln}" for ln in e.linear]
            mats.append(np.hstack(cols))
            names.append(nm)
        return mats, names


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
        # nonlinear uncertainty from the projected Jacobian (white-noise scaling; see ranking)
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


# ---------------------------------------------------------------------------------------------
# saved model: compensation


@dataclass
class DiagnosticModel:
    """Baseline + effects with fitted values, per DUT (or per sensor type); saved as versioned JSON.

    compensate() inverts the model: returns the acceleration at 25 C (Acc0) in g.
    """

    serial: str
    effects: list[str]
    axes: dict[str, dict[str, float]]  # axis -> param name -> value (linear params, no acc0)
    nonlinear: dict[str, dict[str, float]]
    sigma: dict = field(default_factory=dict)
    t_ref_c: float = T_REF_C
    t_power_on_s: float = 0.0
    version: int = MODEL_VERSION

    @staticmethod
    def from_fit(serial: str, fit: DutFit, t_power_on_s: float = 0.0) -> "DiagnosticModel":
        axes, sigma = {}, {}
        for i, ax in enumerate(AXES):
            axes[ax] = {}
            sigma[ax] = {}
            for name, b, s in zip(fit.col_names[i], fit.beta[i], fit.beta_sigma[i]):
                if name.startswith("acc0_g["):
                    continue
                axes[ax][name] = float(b)
                sigma[ax][name] = float(s) if np.isfinite(s) else None
        sigma["nonlinear"] = fit.nl_sigma
        return DiagnosticModel(serial=serial, effects=list(fit.effects), axes=axes,
                               nonlinear={k: dict(v) for k, v in fit.nl.items()}, sigma=sigma,
                               t_power_on_s=t_power_on_s)

    def to_json(self) -> dict:
        return {"format": MODEL_FORMAT, "version": self.version, "serial": self.serial,
                "t_ref_c": self.t_ref_c, "t_power_on_s": self.t_power_on_s, "effects": self.effects,
                "axes": self.axes, "nonlinear": self.nonlinear, "sigma": self.sigma}

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_json(), indent=2) + "\n", encoding="utf-8")

    @staticmethod
    def from_json(obj: dict) -> "DiagnosticModel":
        if obj.get("format") != MODEL_FORMAT:
            raise StationError("not a station diagnostic model (format field missing)")
        if int(obj.get("version", 0)) > MODEL_VERSION:
            raise StationError(f"model version {obj.get('version')} is newer than this code ({MODEL_VERSION})")
        for e in obj["effects"]:
            get_effect(e)
        return DiagnosticModel(serial=obj.get("serial", ""), effects=list(obj["effects"]),
                               axes=obj["axes"], nonlinear=obj.get("nonlinear", {}),
                               sigma=obj.get("sigma", {}), t_ref_c=float(obj.get("t_ref_c", T_REF_C)),
                               t_power_on_s=float(obj.get("t_power_on_s", 0.0)),
                               version=int(obj.get("version", MODEL_VERSION)))

    @staticmethod
    def load(path: str | Path) -> "DiagnosticModel":
        p = Path(path)
        try:
            obj = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise StationError(f"{p}: cannot read model ({exc})") from None
        return DiagnosticModel.from_json(obj)

    def predict(self, time_s: np.ndarray, acc0_g: np.ndarray, temp_c: np.ndarray) -> np.ndarray:
        """Model output in g for true readings acc0_g (n, 3) at the measured temperatures."""
        time_s = np.asarray(time_s, np.float64)
        temp_c = np.asarray(temp_c, np.float64)
        acc0_g = np.asarray(acc0_g, np.float64).reshape(-1, 3)
        effects = [get_effect(n) for n in self.effects]
        t = temp_c
        for e in effects:
            t2 = e.temperature(t, time_s, self.nonlinear.get(e.name, {}))
            if t2 is not None:
                t = t2
        ctx = Context(time_s=time_s, temp_c=temp_c, temp_smooth_c=smooth_temperature(temp_c, time_s),
                      dt_c=t - self.t_ref_c, acc0_g=acc0_g, t_power_on_s=self.t_power_on_s, cache={})
        out = acc0_g * 1000.0
        for i, ax in enumerate(AXES):
            p = self.axes[ax]
            out[:, i] += ctx.dt_c * (p["tdb_mg_per_c"] + p["tdsf_ppm_per_c"] * acc0_g[:, i] * 1e-3)
        for e in effects:
            cols = e.columns(ctx, self.nonlinear.get(e.name, {}))
            for i, ax in enumerate(AXES):
                for m, ln in enumerate(e.linear):
                    out[:, i] += cols[:, i, m] * self.axes[ax].get(f"{e.name}.{ln}", 0.0)
        return out / 1000.0

    def compensate(self, time_s: np.ndarray, acc_g: np.ndarray, temp_c: np.ndarray) -> np.ndarray:
        """Acc0 (g, reading at 25 C without the modelled effects) from measured acc and temperature.

        Fixed-point inversion of predict(): the Acc0-dependent terms are ~1e-3 of Acc0, so a few
        passes converge.
        """
        acc_g = np.asarray(acc_g, np.float64).reshape(-1, 3)
        acc0 = acc_g.copy()
        for _ in range(6):
            acc0 = acc0 + (acc_g - self.predict(time_s, acc0, temp_c))
        return acc0


__all__ = ["Segmentation", "DutData", "DutFit", "prepare", "fit_dut", "predict_dut", "window_rms",
           "heldout_residual", "DiagnosticModel", "train_mask", "tdsf_identifiable"]
