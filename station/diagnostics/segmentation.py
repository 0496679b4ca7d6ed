"""Cut one DUT's log into the pieces every diagnostic figure is computed on: constant-orientation
runs, 10 s fit blocks, 1-minute RMS windows, and held-out thermal legs with their folds and guards.

Why a module of its own: the held-out RMS that admits or rejects an effect is honest only if the
held-out units are whole thermal legs with a guard around them (a MEMS bias wanders, so
neighbouring minutes share their error). That cut is decided once, here, and the fit (fit.py),
the noise model (noise_gls.py) and the ranking all use it; nothing downstream re-cuts the log.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from station.diagnostics.effects import smooth_temperature
from contracts.logfile import DutLog
from contracts.types import StationError


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
    # block means of the inputs: every fit, held-out prediction and RMS window is computed on these
    block_temp_c: np.ndarray = field(default_factory=lambda: np.zeros(0))
    block_temp_smooth_c: np.ndarray = field(default_factory=lambda: np.zeros(0))
    block_window: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    block_run: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    block_ss_within: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # per block and axis, mg^2
    cache: dict = field(default_factory=dict)  # per-sample regressors that depend only on the data
    block_cache: dict = field(default_factory=dict)  # the same for block-level regressors

    @property
    def n(self) -> int:
        return int(self.time_s.shape[0])

    def block_mean(self, x: np.ndarray) -> np.ndarray:
        s = np.add.reduceat(x, self.block_starts, axis=0)
        shape = (-1,) + (1,) * (x.ndim - 1)
        return s / self.block_count.reshape(shape)


def at_positions(log: DutLog) -> DutLog:
    """The log without its samples at position -1 (the contract's "moving or unknown": the daemon
    stores every sample of a plate move as -1). Those samples belong to no orientation, so they are
    never fitted as one; a log without a position column, or with every row at a position, is
    returned as it is. The gap they leave is a break between runs, like any gap in time."""
    if log.position is None:
        return log
    keep = np.asarray(log.position) >= 0
    if keep.all():
        return log
    if not keep.any():
        raise StationError(f"{log.serial or 'log'}: every sample is at position -1 (moving or unknown); "
                           f"nothing to diagnose")
    return DutLog(time_s=log.time_s[keep], acc_g=log.acc_g[keep], temp_c=log.temp_c[keep], meta=log.meta,
                  lamp=None if log.lamp is None else log.lamp[keep], position=log.position[keep],
                  ref_dir=None if log.ref_dir is None else log.ref_dir[keep])


def _orientation_codes(log: DutLog) -> tuple[np.ndarray, list[str]]:
    """Orientation per sample: the log's position column, else clusters of the acceleration.
    (prepare() has dropped the rows at position -1 first.)"""
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
    log = at_positions(log)
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
    d.block_temp_c = d.block_mean(temp_c)
    d.block_temp_smooth_c = d.block_mean(temp_smooth)
    d.block_window = window[block_starts]
    d.block_run = run[block_starts]
    # the measurement's scatter inside its 10 s blocks (white noise, mostly): the per-sample RMS of a
    # model held constant over each block is its block residual plus this
    d.block_ss_within = np.add.reduceat((d.acc_mg - d.y_block[block]) ** 2, block_starts, axis=0)
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


__all__ = ["Segmentation", "DutData", "prepare", "train_mask", "at_positions"]
