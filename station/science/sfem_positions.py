"""Static positions of a record for the SFEM fit (pure: arrays in, averaged positions out).

Why a module of its own: turning a log into the fit's input is the part of the SFEM that decides
which samples count: static intervals, soak discipline against a ramping chamber, merging the
intervals of one fixture position, temperature steps, equal weight per position. Those decisions
are about the test (sensors2023 4.3), not about the model or its optimiser, and they are tuned and
tested on their own.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from station.science.chunked import median_into, median_step_s, pairwise_sum, pieces, rows_mean_std, values
from station.science.static_detect import StaticDetectConfig, detect_static_intervals


# ---------------------------------------------------------------------------------------------
# static positions of a record (pure: arrays in)


@dataclass
class PositionSet:
    """Static positions of one temperature step: one averaged reading per fixture position."""

    mean: np.ndarray  # (m, 3) raw units
    noise_g: np.ndarray  # (m,) 1-sigma of each mean, RMS over axes (white-noise assumption)
    n_samples: np.ndarray  # (m,)
    temp_c: np.ndarray  # (m,) mean temperature of each position
    ref_dir: np.ndarray | None  # (m, 3)
    position: np.ndarray | None  # (m,) fixture position index, -1 where unknown
    spans: list[list[tuple[int, int]]]  # sample index ranges [start, stop) averaged per position

    @property
    def step_temp_c(self) -> float:
        return float(np.average(self.temp_c, weights=self.n_samples))

    def __len__(self) -> int:
        return int(self.mean.shape[0])


def _runs(labels: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) runs of equal consecutive rows of a (n,) or (n, k) label array."""
    n = labels.shape[0]
    if n == 0:
        return []
    lab = labels.reshape(n, -1)
    change = np.any(lab[1:] != lab[:-1], axis=1)
    edges = np.concatenate([[0], np.flatnonzero(change) + 1, [n]])
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def temperature_steps(temps_c: np.ndarray, gap_c: float = 3.0) -> np.ndarray:
    """Label values by temperature step: sorted, a new step wherever the gap exceeds gap_c."""
    t = np.asarray(temps_c, dtype=np.float64)
    order = np.argsort(t)
    labels = np.empty(len(t), dtype=np.int64)
    if len(t):
        labels[order] = np.concatenate([[0], np.cumsum(np.diff(t[order]) > gap_c)])
    return labels


def _temperature_trend(time_s: np.ndarray, temp_c: np.ndarray, window_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Centred moving mean of the temperature and its rate (C/min) from the two half-window means.
    The cumulative sum is the record's one buffer; the rest is computed a piece at a time."""
    n = len(temp_c)
    dt = median_step_s(time_s) if n > 1 else 1.0
    dt = dt if dt > 0 else 1.0
    h = max(2, int(round(window_s / dt / 2)))
    c = np.empty(n + 1)
    c[0] = 0.0
    for a, b in pieces([(0, n)]):  # np.cumsum(temp_c - temp_c[0]), its running sum carried
        x = temp_c[a:b] - temp_c[0]
        c[a + 1:b + 1] = np.cumsum(x) if a == 0 else np.cumsum(np.concatenate([c[a:a + 1], x]))[1:]
    smooth, rate = np.empty(n), np.empty(n)
    for a, b in pieces([(0, n)]):
        i = np.arange(a, b)
        lo, mid, hi = np.clip(i - h, 0, n), i, np.clip(i + h, 0, n)
        left = (c[mid] - c[lo]) / np.maximum(mid - lo, 1)
        right = (c[hi] - c[mid]) / np.maximum(hi - mid, 1)
        smooth[a:b] = (c[hi] - c[lo]) / np.maximum(hi - lo, 1) + temp_c[0]
        span_s = 0.5 * ((mid - lo) + (hi - mid)) * dt
        rate[a:b] = np.where((mid - lo > 0) & (hi - mid > 0), (right - left) / np.maximum(span_s, 1e-12) * 60.0, 0.0)
    return smooth, rate


def _label_runs(s: int, e: int, cols: list[Callable[[int, int], np.ndarray]]) -> list[tuple[int, int]]:
    """_runs of rows s..e-1 of the label columns side by side (each col(a, b) gives rows [a, b) as
    (m, k)), a piece at a time: no (n, k) label array of the whole record."""
    edges = [s]
    for a, b in pieces([(s, e)]):
        hi = min(b + 1, e)  # one row further: the change between this piece and the next
        lab = np.concatenate([col(a, hi) for col in cols], axis=1)
        edges.extend((a + np.flatnonzero(np.any(lab[1:] != lab[:-1], axis=1)) + 1).tolist())
    edges.append(e)
    return list(zip(edges[:-1], edges[1:])) if e > s else []


def group_static_positions(
    time_s: np.ndarray | None,
    acc: np.ndarray,
    temp_c: np.ndarray | None = None,
    ref_dir: np.ndarray | None = None,
    position: np.ndarray | None = None,
    *,
    config: StaticDetectConfig | None = None,
    acc_g_per_raw: float = 1.0,
    temp_gap_c: float = 3.0,
    merge_angle_deg: float = 2.0,
    temp_window_s: float = 120.0,
    max_temp_rate_c_per_min: float = 0.3,
    temp_tol_c: float = 0.5,
    equalize_positions: bool = True,
) -> list[PositionSet]:
    """Static intervals -> averaged positions, split into temperature steps (coldest first).

    Intervals are found on acc * acc_g_per_raw (detector thresholds are in g), cut wherever the
    position or reference column changes, then merged per (temperature step, position): by the
    position index when known, else by the reference direction, else by measured direction
    (within merge_angle_deg).
    Soak discipline (sensors2023 4.3) when temperature and time are given: a DUT resting in one
    position while the chamber ramps is static for the accelerometer but not a soak, so samples
    count only where the temperature, smoothed over temp_window_s, changes by at most
    max_temp_rate_c_per_min and lies within temp_tol_c of its step's median. Steps are
    temperature clusters separated by more than temp_gap_c.
    equalize_positions (with temperature and time): within a step, a position keeps at most the
    step's median sample count, taken from the end of its longest span. The position a DUT rests
    in while the chamber settles is static for many times the plan's hold; its extra samples are
    the soak's tail, where the die still converges by tenths of a degree that a 1 C thermometer
    cannot resolve (x TDB ~1 mg/C: ~0.1 mg), and their number would make that position's noise
    sigma the smallest, so the fit would trust the most biased position most. The end of the
    soak is its most settled part, and every position then weighs as the plan intends.
    """
    cfg = config or StaticDetectConfig()
    a = np.asarray(acc, dtype=np.float64).reshape(-1, 3)
    n = a.shape[0]
    temps = np.zeros(n) if temp_c is None else np.asarray(temp_c, dtype=np.float64).reshape(-1)
    refs = None if ref_dir is None else np.asarray(ref_dir, dtype=np.float64).reshape(-1, 3)
    pos = None if position is None else np.asarray(position, dtype=np.int64).reshape(-1)  # no copy of an int64 column
    intervals = detect_static_intervals(time_s, a if acc_g_per_raw == 1.0 else a * acc_g_per_raw, cfg)
    settled = np.ones(n, dtype=bool)
    ts = temps
    if temp_c is not None and time_s is not None and n > 2:
        ts, rate = _temperature_trend(np.asarray(time_s, dtype=np.float64).reshape(-1), temps, temp_window_s)
        settled = np.abs(rate) <= max_temp_rate_c_per_min
        del rate
    # an interval is cut wherever the soak, the position or the reference changes (label columns
    # side by side, built a piece at a time: bounded memory on a long log)
    cols: list[Callable[[int, int], np.ndarray]] = [lambda i, j: settled[i:j, None].astype(np.float64)]
    if pos is not None:
        cols.append(lambda i, j: pos[i:j, None].astype(np.float64))
    if refs is not None:
        cols.append(lambda i, j: np.round(refs[i:j], 6))
    cuts: list[tuple[int, int]] = []
    for iv in intervals:
        for s, e in _label_runs(iv.start, iv.stop, cols):
            if e - s >= cfg.min_samples and settled[s]:
                cuts.append((s, e))
    if refs is not None:
        cuts = [(s, e) for s, e in cuts if np.all(np.isfinite(refs[s])) and np.linalg.norm(refs[s]) > 0.5]
    if not cuts:
        return []
    piece_temp = np.array([ts[s:e].mean() for s, e in cuts])
    steps = temperature_steps(piece_temp, temp_gap_c)
    if temp_c is not None:  # keep only samples near their step's temperature
        kept, kept_steps = [], []
        for step in range(int(steps.max()) + 1):
            mine = [pc for pc, st in zip(cuts, steps) if st == step]
            ts_mine = values(ts, mine)
            med = median_into(ts_mine.fill(np.empty(ts_mine.n)))
            for s0, e0 in mine:
                near = np.abs(ts[s0:e0] - med) <= temp_tol_c
                for s, e in _runs(near):
                    if e - s >= cfg.min_samples and near[s]:
                        kept.append((s0 + s, s0 + e))
                        kept_steps.append(step)
        if not kept:
            return []
        cuts, steps = kept, np.array(kept_steps)
    out: list[PositionSet] = []
    cos_merge = math.cos(math.radians(merge_angle_deg))
    for step in range(int(steps.max()) + 1):
        groups: list[list[tuple[int, int]]] = []
        keys: list[object] = []
        for (s, e), st in zip(cuts, steps):
            if st != step:
                continue
            if pos is not None and pos[s] >= 0:
                key: object = ("p", int(pos[s]))
            elif refs is not None:
                key = ("r", tuple(np.round(refs[s], 4)))
            else:
                d = a[s:e].mean(axis=0)
                key = ("d", d / np.linalg.norm(d))
            hit = None
            for gi, kk in enumerate(keys):
                if key[0] == "d" and kk[0] == "d":
                    if float(np.dot(key[1], kk[1])) >= cos_merge:
                        hit = gi
                        break
                elif key[0] != "d" and kk == key:
                    hit = gi
                    break
            if hit is None:
                keys.append(key)
                groups.append([(s, e)])
            else:
                groups[hit].append((s, e))
        if not groups:
            continue
        if equalize_positions and temp_c is not None and time_s is not None and len(groups) > 1:
            cap = max(cfg.min_samples, int(np.median([sum(e - s for s, e in g) for g in groups])))
            for gi, spans in enumerate(groups):
                if sum(e - s for s, e in spans) > cap:
                    s, e = max(spans, key=lambda se: se[1] - se[0])
                    groups[gi] = [(max(s, e - cap), e)]
        means, noise, counts, tmeans, rlist, plist = [], [], [], [], [], []
        for g in groups:  # each position's samples, read span by span (numpy's own figures, no copy)
            m = sum(e - s for s, e in g)
            mean, std = rows_mean_std(lambda: (a[i:j] for i, j in pieces(g)), m)
            means.append(mean)
            std_g = std * acc_g_per_raw
            noise.append(float(np.sqrt(np.mean(std_g**2)) / math.sqrt(m)))
            counts.append(m)
            tv = values(temps, g)
            tmeans.append(float(pairwise_sum(tv.piece, m) / m))
            if refs is not None:
                buf = np.empty(m)
                rlist.append(np.array([median_into(values(refs[:, k], g).fill(buf)) for k in range(3)]))
            plist.append(int(pos[g[0][0]]) if pos is not None else -1)
        out.append(
            PositionSet(
                mean=np.array(means),
                noise_g=np.array(noise),
                n_samples=np.array(counts),
                temp_c=np.array(tmeans),
                ref_dir=np.array(rlist) if refs is not None else None,
                position=np.array(plist) if pos is not None else None,
                spans=groups,
            )
        )
    return out


__all__ = [
    "PositionSet",
    "group_static_positions",
    "temperature_steps",
]
