"""An honest leftover: is the model's held-out error what the sensor's noise alone gives on those
legs, and if not, which view of the residual shows what is missing?

Why a module of its own: an Allan curve of the residual stops at a fraction of one dwell, so a
residual 3x above the noise on held-out legs (a shock mid-run, a temperature sensor that lags the
die) once read "at the sensor's noise at all averaging times compared". The question the engineer
asks is about the held-out legs themselves: this module answers it with the same noise model the
evidence uses (noise_gls: local level + AR(p) of the 10 s block means, per axis over the whole
log) and the same held-out legs, folds and guards the ranking uses.

Method, per DUT and axis (pure: prepared data and a fitted model in, numbers and words out):
- the noise model is fitted on the model's in-sample residual;
- N_DRAWS series of that noise are drawn on the log's own blocks and pushed through the held-out
  machinery at the model's fitted shape (nonlinear values fixed, every linear parameter refitted
  per fold, an orientation unseen in training takes its offset from the held-out leg): the held-out
  error those legs would show if the model were exact and the noise model right;
- the measured held-out error is compared with that distribution: a residual "remains" when it is
  >= LEFTOVER_RATIO times the expected error and above the draws' 97.5 % quantile;
- the views: the held-out residual grouped by temperature x orientation x heating/cooling, by
  dT/dt, by time (30 min) and by orientation; for each, the share of the residual's variance its
  group means explain, minus the share the same grouping explains in the noise draws (wandering
  noise always looks like "time"). The view with the largest excess carries the structure.

Assumptions, stated: the noise model fitted on the residual is the sensor's (a structure the model
misses inflates its random walk a little, which makes the expected error larger, never smaller:
the statement errs towards "at the noise"); the fitted nonlinear values are held fixed in the
draws (the real held-out refits them per fold: a small optimism of the measured error).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter

from station.diagnostics.design import _Design
from station.diagnostics.effects import get_effect
from station.diagnostics.fit import DutFit
from station.diagnostics.fold_support import unsupported
from station.diagnostics.noise_gls import NoiseFilter, _runs_of_blocks, ar_fit
from station.diagnostics.report_values import _r
from station.diagnostics.segmentation import DutData, train_mask
from station.science.chunked import keep_rows
from contracts.types import AXES

N_DRAWS = 48
LEFTOVER_RATIO = 1.15  # the held-out error must be at least this much above the expected ...
LEFTOVER_QUANTILE = 0.975  # ... and above this quantile of the noise draws
VIEW_MIN_EXCESS = 0.10  # a view "carries the structure" when its groups explain this much more than in noise
MIN_BLOCKS = 12  # fewer held-out blocks on an axis: nothing to compare
COVARIATE_VIEWS = ("temperature", "rate", "orientation")
TIME_BIN_S = 1800.0
TEMP_BIN_C = 5.0
RATE_BIN_C_PER_MIN = 0.25

VIEWS = {
    "temperature": ("residual vs temperature, by orientation and heating/cooling", "residual_vs_temperature"),
    "rate": ("residual vs dT/dt", "residual_vs_rate"),
    "time": ("residual vs time", "residual_vs_time"),
    "orientation": ("residual vs orientation", "residual_vs_orientation"),
}


@dataclass
class AxisLeftover:
    heldout_rms_mg: float
    expected_rms_mg: float
    expected_hi_rms_mg: float  # the draws' LEFTOVER_QUANTILE
    views: dict[str, float] = field(default_factory=dict)  # excess share of variance per view
    structured: list[str] = field(default_factory=list)  # covariate views whose excess no noise draw reaches

    @property
    def ratio(self) -> float:
        return self.heldout_rms_mg / self.expected_rms_mg if self.expected_rms_mg > 0 else math.inf

    @property
    def above(self) -> bool:
        """A residual remains: the held-out error is above what the noise gives on these legs, or it
        follows temperature, its rate or the orientation more than any noise draw does (noise that
        wanders can look like anything in time, never like a function of those)."""
        return (self.ratio >= LEFTOVER_RATIO and self.heldout_rms_mg > self.expected_hi_rms_mg) or bool(self.structured)


SIM_ROWS = 4096  # blocks of a piece whose draws are made at once (_simulate)


def _simulate(nf: NoiseFilter, n: int, pieces: list[np.ndarray], rng: np.random.Generator, k: int) -> np.ndarray:
    """k draws (n, k) of the fitted noise: AR(p) innovations through the local level (IMA(1,1)).

    Each piece is drawn SIM_ROWS rows at a time, the filters' states carried from one to the next:
    the same stream of normals and the same recursions as the whole piece at once (a long log's
    piece of 80 000 blocks held five arrays of 30 MB)."""
    out = np.zeros((n, k))
    a_ar = np.concatenate([[1.0], -nf.phi])
    for idx in pieces:
        m = idx.size
        burn = 4 * max(nf.phi.size, 1)
        zi_u = np.zeros((a_ar.size - 1, k))
        zi_y = np.zeros((1, k))
        first: np.ndarray | None = None
        for row in range(0, m + burn, SIM_ROWS):
            w = rng.standard_normal((min(SIM_ROWS, m + burn - row), k)) * nf.sigma
            if nf.phi.size:
                u, zi_u = lfilter([1.0], a_ar, w, axis=0, zi=zi_u)
            else:
                u = w
            lo = max(burn - row, 0)  # the burn-in rows only settle the AR filter
            if lo >= u.shape[0]:
                continue
            y, zi_y = lfilter([1.0, -nf.theta], [1.0, -1.0], u[lo:], axis=0, zi=zi_y)
            if first is None:
                first = y[:1].copy()
            j = row + lo - burn
            out[idx[j:j + y.shape[0]]] = y - first
    return out


def _groups(d: DutData) -> dict[str, np.ndarray]:
    """Block -> group id, per view."""
    t = d.block_time_s
    temp = d.block_temp_smooth_c
    rate = np.gradient(temp, t) * 60.0 if t.size > 1 else np.zeros_like(t)
    heating = (rate > 0.05).astype(int) - (rate < -0.05).astype(int)
    tb = np.floor(temp / TEMP_BIN_C).astype(int)
    temp_id = (d.block_pos * 3 + (heating + 1)) * 1000 + (tb - tb.min())
    rb = np.floor(rate / RATE_BIN_C_PER_MIN).astype(int)
    return {"temperature": np.unique(temp_id, return_inverse=True)[1],
            "rate": np.unique(rb, return_inverse=True)[1],
            "time": np.floor((t - t[0]) / TIME_BIN_S).astype(int),
            "orientation": d.block_pos.astype(int)}


def _explained(x: np.ndarray, w: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Share of the weighted variance of each column of x (n, k) explained by the group means
    (adjusted for the number of groups)."""
    ng = int(g.max()) + 1
    wsum = np.bincount(g, weights=w, minlength=ng)
    means = np.stack([np.bincount(g, weights=w * x[:, j], minlength=ng) for j in range(x.shape[1])], axis=1)
    means = np.divide(means, wsum[:, None], out=np.zeros_like(means), where=wsum[:, None] > 0)
    mu = (w @ x) / w.sum()
    dev = x - mu
    sst = w @ np.square(dev, out=dev)  # (x - mu) ** 2 in one buffer
    ssb = wsum @ (means - mu) ** 2
    n, groups = x.shape[0], int(np.count_nonzero(wsum))
    adj = (sst - ssb) / max(n - groups, 1) / np.maximum(sst / max(n - 1, 1), 1e-300)
    return 1.0 - adj


def _window_ms(d: DutData, r: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Mean square of the 1-minute window means of r (n_blocks, k) over the blocks ok (per column)."""
    cnt = d.block_count[ok]
    wid = d.block_window[ok]
    cw = np.bincount(wid, weights=cnt)
    keep = cw > 0
    sums = np.stack([np.bincount(wid, weights=cnt * r[ok, j], minlength=cw.size) for j in range(r.shape[1])], axis=1)
    means = sums[keep] / cw[keep, None]
    return (cw[keep] @ means**2) / cw[keep].sum()


def _heldout(d: DutData, X: np.ndarray, Y: np.ndarray, P: int) -> np.ndarray:
    """Held-out residual of every column of Y (n_blocks, k) under the design X, linear refit per
    fold on its training blocks (the ranking's folds and guards). Written over Y (returned): every
    fold's refit is made first, from the draws as they are, then each fold's held-out rows (the
    folds' test rows do not overlap) are replaced by their residual, the others by NaN: no second
    array of the draws' size (48 columns of a long log's blocks)."""
    sw = np.sqrt(d.block_count)
    refits: list[tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]] = []  # (test rows, live, coef, unseen)
    for k in range(d.n_folds):
        test = d.block_fold == k
        train = train_mask(d, k)
        if not test.any() or not train.any():
            continue
        live = np.any(np.abs(X[train]) > 0, axis=0)
        # as fit._inner: an effect column with < 1 % of its full-log size in the training blocks (a
        # warm-up transient whose start is held out) is not extrapolated
        full_max = np.abs(X[:, P + 2:]).max(axis=0) if X.shape[1] > P + 2 else np.zeros(0)
        if full_max.size:
            live[P + 2:] &= np.abs(X[train][:, P + 2:]).max(axis=0) >= 1e-2 * full_max
            live[P + 2:] &= ~unsupported(X, np.flatnonzero(train), P)  # the fit's rule (fold_support.py)
        A = X[train][:, live] * sw[train, None]
        B = Y[train]
        B *= sw[train, None]  # Y[train] * sw, in its own copy
        coef, *_ = np.linalg.lstsq(A, B, rcond=None)
        del A, B
        # orientations with no training block: their offset comes from the held-out leg itself
        unseen = [p for p in range(P) if not (train & (d.block_pos == p)).any()]
        refits.append((test, live, coef, unseen))
    covered = np.zeros(Y.shape[0], dtype=bool)
    for test, live, coef, unseen in refits:
        r = Y[test] - X[test][:, live] @ coef
        tp = d.block_pos[test]
        for p in unseen:
            sel = tp == p
            if sel.any():
                r[sel] -= np.average(r[sel], axis=0, weights=d.block_count[test][sel])
        Y[test] = r
        covered |= test
    Y[~covered] = np.nan
    return Y


def dut_leftover(d: DutData, fit: DutFit, heldout_block: np.ndarray, seed: int = 0) -> dict[str, AxisLeftover]:
    """Per axis: the held-out error against what the noise model expects on the same legs."""
    mats, _ = _Design(d, [get_effect(n) for n in fit.effects]).block_matrices(fit.nl, fit.acc0_g)
    P = len(d.pos_labels)
    pieces = _runs_of_blocks(d)
    groups = _groups(d)
    rng = np.random.default_rng(seed)
    ok = ~np.isnan(heldout_block).any(axis=1)
    out: dict[str, AxisLeftover] = {}
    w = d.block_count
    for i, ax in enumerate(AXES):
        X = mats[i]
        y = d.y_block[:, i]
        live = np.any(np.abs(X) > 0, axis=0)
        coef, *_ = np.linalg.lstsq(X[:, live] * np.sqrt(w)[:, None], y * np.sqrt(w), rcond=None)
        nf = ar_fit(y - X[:, live] @ coef, pieces, robust=True)
        draws = _heldout(d, X, _simulate(nf, y.size, pieces, rng, N_DRAWS), P)
        okd = ok & ~np.isnan(draws).any(axis=1)
        if np.count_nonzero(okd) < MIN_BLOCKS:  # no held-out legs to compare (a model no fold can fit)
            out[ax] = AxisLeftover(heldout_rms_mg=math.nan, expected_rms_mg=math.nan, expected_hi_rms_mg=math.nan)
            continue
        ms_draws = _window_ms(d, draws, okd)
        h = heldout_block[:, i:i + 1]
        ms = float(_window_ms(d, h, okd)[0])
        views = {}
        structured = []
        draws_ok = keep_rows(okd, draws)[0]  # the compared rows, moved to the front of the draws (no copy)
        del draws
        for name, g in groups.items():
            gg = np.unique(g[okd], return_inverse=True)[1]
            real = float(_explained(h[okd], w[okd], gg)[0])
            noise = _explained(draws_ok, w[okd], gg)
            views[name] = real - float(np.mean(noise))
            if name in COVARIATE_VIEWS and views[name] >= VIEW_MIN_EXCESS and real > float(np.max(noise)):
                structured.append(name)
        out[ax] = AxisLeftover(heldout_rms_mg=math.sqrt(ms), expected_rms_mg=math.sqrt(float(np.mean(ms_draws))),
                               expected_hi_rms_mg=math.sqrt(float(np.quantile(ms_draws, LEFTOVER_QUANTILE))),
                               views=views, structured=structured)
    return out


def leftover(data: list[DutData], fits: list[DutFit], heldout: list[np.ndarray], effects: list[str]) -> dict:
    """The report's `leftover`: the held-out error against the noise model's expectation, per DUT
    and axis, the views that carry any structure, and the statement in words (said first when a
    residual remains)."""
    per_dut = {}
    above_all: list[str] = []
    num = den = num_e = 0.0
    best_views: dict[str, float] = {}
    for d, f, h in zip(data, fits, heldout):
        axes = dut_leftover(d, f, h)
        n = float(d.block_count.sum())
        for ax, a in axes.items():
            if not (math.isfinite(a.heldout_rms_mg) and math.isfinite(a.expected_rms_mg)):
                continue
            num += n * a.heldout_rms_mg**2
            num_e += n * a.expected_rms_mg**2
            den += n
            if a.above:
                above_all.append(f"{d.serial} {ax}" if len(data) > 1 else ax)
                for v, x in a.views.items():
                    best_views[v] = max(best_views.get(v, -1.0), x)
        per_dut[d.serial] = {ax: {"heldout_rms_mg": _r(a.heldout_rms_mg), "expected_rms_mg": _r(a.expected_rms_mg),
                                  "expected_hi_rms_mg": _r(a.expected_hi_rms_mg), "ratio": _r(a.ratio, 3),
                                  "above": a.above,
                                  "views_excess_share": {v: _r(x, 3) for v, x in a.views.items()},
                                  "follows": a.structured}
                             for ax, a in axes.items()}
    held = math.sqrt(num / den) if den else float("nan")
    exp = math.sqrt(num_e / den) if den else float("nan")
    model = "baseline" + "".join(f" + {e}" for e in effects)
    ranked_views = sorted(best_views.items(), key=lambda kv: -kv[1])
    carrying = [v for v, x in ranked_views if x >= VIEW_MIN_EXCESS]
    if not den:
        statement = (f"The held-out legs cannot be compared with the noise for {model}: no held-out leg was "
                     f"predicted (too short a log, or a model no fold can fit).")
    elif above_all:
        shape = (f"its shape shows in {VIEWS[carrying[0]][0]} (the groups explain "
                 f"{100 * best_views[carrying[0]]:.0f} % more of it than of the noise)"
                 + (", then " + ", ".join(VIEWS[v][0] for v in carrying[1:]) if carrying[1:] else "")
                 if carrying else
                 "no single view shows its shape (look at residual vs time for steps and drifts)")
        statement = (f"An unexplained residual remains: the held-out error of {model} is {held:.3g} mg, "
                     f"{held / exp:.2g}x the {exp:.3g} mg the noise model expects on those legs "
                     f"(above on {', '.join(above_all)}); {shape}.")
    else:
        statement = (f"Nothing unexplained that these legs can show: the held-out error of {model} is {held:.3g} mg, "
                     f"{held / exp:.2g}x the {exp:.3g} mg the noise model expects on those legs, and it follows "
                     f"neither temperature, its rate nor the orientation more than the noise does. (A disturbance "
                     f"that follows none of them, such as a draught or popcorn noise, reads as the sensor's own "
                     f"wander on one log: the noise view below compares the residual with a static stretch.)")
    return {"statement": statement, "above_floor": bool(above_all), "model": list(effects),
            "heldout_rms_mg": _r(held), "expected_rms_mg": _r(exp), "ratio": _r(held / exp if exp else None, 3),
            "above": above_all, "views": [{"view": v, "plot": VIEWS[v][1], "text": VIEWS[v][0],
                                           "excess_share": _r(x, 3)} for v, x in ranked_views],
            "carrying": [VIEWS[v][1] for v in carrying] if above_all else [],
            "per_dut": per_dut,
            "method": (f"{N_DRAWS} draws of the residual's noise model (local level + AR(p) of the 10 s block means, "
                       f"fitted on the model's in-sample residual) pushed through the same held-out legs, folds and "
                       f"guards; 'remains' = held-out error >= {LEFTOVER_RATIO:g}x the expected and above the draws' "
                       f"{100 * LEFTOVER_QUANTILE:g} % quantile; a view carries the structure when its group means "
                       f"explain >= {100 * VIEW_MIN_EXCESS:g} % more of the held-out residual's variance than of the "
                       f"noise draws'. Figures are of 1-minute means.")}


__all__ = ["leftover", "dut_leftover", "AxisLeftover", "LEFTOVER_RATIO", "VIEWS"]
