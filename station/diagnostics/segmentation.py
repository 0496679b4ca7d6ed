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
from station.science.chunked import PIECE, keep_rows, median_step_s, pieces
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
    pos: np.ndarray  # (n,) orientation code 0..P-1
    pos_labels: list[str]
    block_starts: np.ndarray  # first sample of each fit block (contiguous, sorted)
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

    @property
    def temp_smooth_c(self) -> np.ndarray:
        """(n,) zero-phase 60 s mean of the measured temperature (effects.smooth_temperature), made
        when asked for: the diagnosis reads it a few times (its block means are kept), and 8 bytes a
        sample not kept are 20 MB on a 200 MB log."""
        return smooth_temperature(self.temp_c, self.time_s, 60.0)

    # The per-sample ids are the block's, repeated over its samples (a block lies in one window, leg,
    # fold and run): made when asked for, not kept (5 x 8 bytes a sample, 100 MB on a 200 MB log).
    def per_sample(self, per_block: np.ndarray) -> np.ndarray:
        """A per-block array repeated over each block's samples."""
        return np.repeat(per_block, np.diff(np.append(self.block_starts, self.n)), axis=0)

    @property
    def block(self) -> np.ndarray:
        """(n,) fit-block id of each sample."""
        return self.per_sample(np.arange(self.block_starts.shape[0], dtype=np.int64))

    @property
    def window(self) -> np.ndarray:
        """(n,) RMS window id of each sample."""
        return self.per_sample(self.block_window)

    @property
    def chunk(self) -> np.ndarray:
        """(n,) held-out segment id (a whole thermal leg) of each sample."""
        return self.per_sample(self.block_chunk)

    @property
    def fold(self) -> np.ndarray:
        """(n,) fold of each sample."""
        return self.per_sample(self.block_fold)

    @property
    def run(self) -> np.ndarray:
        """(n,) constant-orientation run id of each sample."""
        return self.per_sample(self.block_run)

    def block_mean(self, x: np.ndarray) -> np.ndarray:
        s = np.add.reduceat(x, self.block_starts, axis=0)
        shape = (-1,) + (1,) * (x.ndim - 1)
        return s / self.block_count.reshape(shape)


def at_positions(log: DutLog, in_place: bool = False) -> DutLog:
    """The log without its samples at position -1 (the contract's "moving or unknown": the daemon
    stores every sample of a plate move as -1). Those samples belong to no orientation, so they are
    never fitted as one; a log without a position column, or with every row at a position, is
    returned as it is. The gap they leave is a break between runs, like any gap in time.
    in_place: the kept rows are moved to the front of the log's own arrays (no copy of a long log;
    the given log is spent)."""
    if log.position is None:
        return log
    keep = np.asarray(log.position) >= 0
    if keep.all():
        return log
    if not keep.any():
        raise StationError(f"{log.serial or 'log'}: every sample is at position -1 (moving or unknown); "
                           f"nothing to diagnose")
    if in_place:
        extra = [x for x in (log.lamp, log.ref_dir) if x is not None]
        t, acc, temp, pos, *rest = keep_rows(keep, log.time_s, log.acc_g, log.temp_c, log.position, *extra)
        it = iter(rest)
        return DutLog(time_s=t, acc_g=acc, temp_c=temp, meta=log.meta, position=pos,
                      lamp=None if log.lamp is None else next(it), ref_dir=None if log.ref_dir is None else next(it))
    return DutLog(time_s=log.time_s[keep], acc_g=log.acc_g[keep], temp_c=log.temp_c[keep], meta=log.meta,
                  lamp=None if log.lamp is None else log.lamp[keep], position=log.position[keep],
                  ref_dir=None if log.ref_dir is None else log.ref_dir[keep])


def _orientation_codes(log: DutLog, in_place: bool = False) -> tuple[np.ndarray, list[str]]:
    """Orientation per sample: the log's position column, else clusters of the acceleration.
    (prepare() has dropped the rows at position -1 first.) in_place: the codes are written over the
    log's own position column (int64), a piece at a time."""
    if log.position is not None and np.all(log.position >= 0):
        uniq = np.unique(log.position)  # sorted: code k is the k-th distinct position
        p = np.asarray(log.position)
        codes = p if in_place and p.dtype == np.int64 else np.empty(p.shape[0], dtype=np.int64)
        for a, b in pieces([(0, p.shape[0])]):
            codes[a:b] = np.searchsorted(uniq, p[a:b])
        return codes, [str(int(u)) for u in uniq]
    # No position column: an orientation is a cluster of readings within 0.3 g on every axis.
    centers: list[np.ndarray] = []
    codes = np.empty(len(log), dtype=np.int64)
    prev = -1
    rounded = np.empty((0, 3))
    for k in range(len(log)):
        if k % PIECE == 0:  # the rounded readings a piece at a time
            rounded = np.round(log.acc_g[k:k + PIECE] / 0.05) * 0.05
        a = rounded[k % PIECE]
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


def prepare(log: DutLog, seg: Segmentation | None = None, consume: bool = False) -> DutData:
    """Cut a log into constant-orientation runs, fit blocks, RMS windows and held-out legs.

    Bounded memory (issue 40): what is kept per sample is the log's own columns (time, acceleration,
    temperature) and the orientation code; the smoothed temperature is made when asked for and
    every per-sample id (block, window, leg, fold, run) is its block's (DutData.per_sample).
    consume: the log's arrays may be overwritten (the rows at position -1 dropped in place, the
    acceleration scaled to mg in place, the position column turned into the orientation codes,
    then let go for a byte a sample): `station diagnose` reads its logs for this call alone."""
    seg = seg or Segmentation()
    given = log
    log = at_positions(log, in_place=consume)
    n = len(log)
    if n < 50:
        raise StationError(f"{log.serial or 'log'}: only {n} samples, too short to diagnose")
    time_s = np.asarray(log.time_s, dtype=np.float64)
    if any(np.any(time_s[a + 1:b + 1] <= time_s[a:b]) for a, b in pieces([(0, n - 1)])):
        raise StationError(f"{log.serial or 'log'}: time_s is not strictly increasing")
    dt = median_step_s(time_s)
    pos, labels = _orientation_codes(log, in_place=consume)
    if consume and len(labels) <= 127:  # the codes in a byte a sample; the log's 8-byte column let go
        pos = pos.astype(np.int8)
        given.position = log.position = None
    temp_c = np.asarray(log.temp_c, dtype=np.float64)
    temp_smooth = smooth_temperature(temp_c, time_s, 60.0)
    brk = np.concatenate([a + 1 + np.flatnonzero((pos[a + 1:b + 1] != pos[a:b]) |
                                                 (time_s[a + 1:b + 1] - time_s[a:b] > 10 * dt))
                          for a, b in pieces([(0, n - 1)])] or [np.empty(0, np.int64)])
    starts = np.concatenate([[0], brk])
    ends = np.concatenate([brk, [n]])
    bs = max(1, int(round(seg.fit_block_s / dt)))
    ws = bs * max(1, int(round(seg.window_s / seg.fit_block_s)))
    # held-out segments: thermal legs of every run (a run with no turn is one leg) ...
    slow = smooth_temperature(temp_smooth, time_s, 300.0)  # the same for every run: made once
    seg_starts = []  # absolute sample index of each segment start (run starts included)
    for a, b in zip(starts, ends):
        seg_starts += [a + k for k in _legs(time_s, slow, a, b, seg)]
    del slow
    # ... and when there are too few, each leg cut into equal pieces (never fewer than min_segments)
    if len(seg_starts) < seg.min_segments:
        n_pieces = int(math.ceil(seg.min_segments / len(seg_starts)))
        bounds = seg_starts + [n]
        seg_starts = [int(bounds[k] + (bounds[k + 1] - bounds[k]) * j // n_pieces)
                      for k in range(len(bounds) - 1) for j in range(n_pieces)]
    seg_cuts = np.unique(np.array(seg_starts[1:], dtype=np.int64))  # a sample's leg: the cuts at or before it
    # blocks never straddle a run or a segment boundary: from each cut, a block every bs samples
    # and an RMS window every ws (ws a multiple of bs: a block lies in one window)
    cut = np.unique(np.concatenate([starts, np.array(seg_starts, dtype=np.int64)]))
    cut_end = np.concatenate([cut[1:], [n]])
    block_starts = np.concatenate([np.arange(a, b, bs, dtype=np.int64) for a, b in zip(cut, cut_end)])
    n_win = np.array([(b - 1 - a) // ws + 1 for a, b in zip(cut, cut_end)], dtype=np.int64)
    first_win = np.concatenate([[0], np.cumsum(n_win)[:-1]])
    k_cut = np.searchsorted(cut, block_starts, side="right") - 1
    block_chunk = np.searchsorted(seg_cuts, block_starts, side="right").astype(np.int64)
    n_seg = int(np.searchsorted(seg_cuts, n - 1, side="right")) + 1
    n_folds = max(2, min(seg.n_folds, n_seg))
    meta_on = log.meta.get("t_power_on_s")
    t_on = float(meta_on) if meta_on not in (None, "") else min(0.0, float(time_s[0]))
    acc = np.asarray(log.acc_g, dtype=np.float64)
    d = DutData(
        serial=log.serial or "dut",
        time_s=time_s,
        acc_mg=np.multiply(acc, 1000.0, out=acc) if consume else acc * 1000.0,
        temp_c=temp_c,
        pos=pos, pos_labels=labels, block_starts=block_starts, t_power_on_s=t_on, lamp=log.lamp,
    )
    d.block_count = np.diff(np.concatenate([block_starts, [n]])).astype(np.float64)
    d.block_pos = pos[block_starts].astype(np.int64)
    d.block_chunk = block_chunk
    d.block_fold = block_chunk % n_folds
    d.block_time_s = d.block_mean(time_s)
    first = np.concatenate([[0], seg_cuts[seg_cuts > 0]])
    last = np.concatenate([first[1:] - 1, [n - 1]])
    d.seg_bounds_s = np.stack([time_s[first], time_s[last]], axis=1)
    d.guard_s = seg.guard_s
    d.n_folds = n_folds
    d.y_block = d.block_mean(d.acc_mg)
    d.block_temp_c = d.block_mean(temp_c)
    d.block_temp_smooth_c = d.block_mean(temp_smooth)
    d.block_window = first_win[k_cut] + (block_starts - cut[k_cut]) // ws
    d.block_run = (np.searchsorted(starts, block_starts, side="right") - 1).astype(np.int64)
    # the measurement's scatter inside its 10 s blocks (white noise, mostly): the per-sample RMS of a
    # model held constant over each block is its block residual plus this
    d.block_ss_within = _within_ss(d)
    return d


def _within_ss(d: DutData) -> np.ndarray:
    """(n_blocks, 3) sum over each block's samples of (acc - the block's mean)^2, mg^2: the same
    reduceat over blocks as on the whole record, a group of whole blocks at a time."""
    starts, n = d.block_starts, d.n
    counts = np.diff(np.append(starts, n))
    out = np.empty((starts.shape[0], 3))
    j = 0
    while j < starts.shape[0]:
        k = max(j + 1, int(np.searchsorted(starts, starts[j] + PIECE, side="right")) - 1)
        s0 = int(starts[j])
        s1 = int(starts[k]) if k < starts.shape[0] else n
        r = d.acc_mg[s0:s1] - np.repeat(d.y_block[j:k], counts[j:k], axis=0)
        out[j:k] = np.add.reduceat(r ** 2, starts[j:k] - s0, axis=0)
        j = k
    return out


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
