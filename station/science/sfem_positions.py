"""Static positions of a record for the SFEM fit (pure: arrays in, averaged positions out).

Why a module of its own: turning a log into the fit's input is the part of the SFEM that decides
which samples count: static intervals, soak discipline against a ramping chamber, merging the
intervals of one fixture position, temperature steps, equal weight per position. Those decisions
are about the test (sensors2023 4.3), not about the model or its optimiser, and they are tuned and
tested on their own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

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
    """Centred moving mean of the temperature and its rate (C/min) from the two half-window means."""
    n = len(temp_c)
    dt = float(np.median(np.diff(time_s))) if n > 1 else 1.0
    dt = dt if dt > 0 else 1.0
    h = max(2, int(round(window_s / dt / 2)))
    c = np.concatenate([[0.0], np.cumsum(temp_c - temp_c[0])])
    i = np.arange(n)
    lo, mid, hi = np.clip(i - h, 0, n), i, np.clip(i + h, 0, n)
    left = (c[mid] - c[lo]) / np.maximum(mid - lo, 1)
    right = (c[hi] - c[mid]) / np.maximum(hi - mid, 1)
    smooth = (c[hi] - c[lo]) / np.maximum(hi - lo, 1) + temp_c[0]
    span_s = 0.5 * ((mid - lo) + (hi - mid)) * dt
    rate = np.where((mid - lo > 0) & (hi - mid > 0), (right - left) / np.maximum(span_s, 1e-12) * 60.0, 0.0)
    return smooth, rate


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
    pos = None if position is None else np.asarray(position).reshape(-1).astype(np.int64)
    intervals = detect_static_intervals(time_s, a * acc_g_per_raw, cfg)
    label_cols = []
    if pos is not None:
        label_cols.append(pos[:, None].astype(np.float64))
    if refs is not None:
        label_cols.append(np.round(refs, 6))
    labels = np.concatenate(label_cols, axis=1) if label_cols else None
    settled = np.ones(n, dtype=bool)
    ts = temps
    if temp_c is not None and time_s is not None and n > 2:
        ts, rate = _temperature_trend(np.asarray(time_s, dtype=np.float64).reshape(-1), temps, temp_window_s)
        settled = np.abs(rate) <= max_temp_rate_c_per_min
    split_cols = [settled[:, None].astype(np.float64)]
    if labels is not None:
        split_cols.append(labels)
    split = np.concatenate(split_cols, axis=1)
    pieces: list[tuple[int, int]] = []
    for iv in intervals:
        for s, e in _runs(split[iv.start : iv.stop]):
            if e - s >= cfg.min_samples and settled[iv.start + s]:
                pieces.append((iv.start + s, iv.start + e))
    if refs is not None:
        pieces = [(s, e) for s, e in pieces if np.all(np.isfinite(refs[s])) and np.linalg.norm(refs[s]) > 0.5]
    if not pieces:
        return []
    piece_temp = np.array([ts[s:e].mean() for s, e in pieces])
    steps = temperature_steps(piece_temp, temp_gap_c)
    if temp_c is not None:  # keep only samples near their step's temperature
        kept, kept_steps = [], []
        for step in range(int(steps.max()) + 1):
            mine = [pc for pc, st in zip(pieces, steps) if st == step]
            med = float(np.median(np.concatenate([ts[s:e] for s, e in mine])))
            near = np.abs(ts - med) <= temp_tol_c
            for s0, e0 in mine:
                for s, e in _runs(near[s0:e0]):
                    if e - s >= cfg.min_samples and near[s0 + s]:
                        kept.append((s0 + s, s0 + e))
                        kept_steps.append(step)
        if not kept:
            return []
        pieces, steps = kept, np.array(kept_steps)
    out: list[PositionSet] = []
    cos_merge = math.cos(math.radians(merge_angle_deg))
    for step in range(int(steps.max()) + 1):
        groups: list[list[tuple[int, int]]] = []
        keys: list[object] = []
        for (s, e), st in zip(pieces, steps):
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
        for spans in groups:
            idx = np.concatenate([np.arange(s, e) for s, e in spans])
            seg = a[idx]
            means.append(seg.mean(axis=0))
            std_g = seg.std(axis=0, ddof=1) * acc_g_per_raw
            noise.append(float(np.sqrt(np.mean(std_g**2)) / math.sqrt(len(idx))))
            counts.append(len(idx))
            tmeans.append(float(temps[idx].mean()))
            if refs is not None:
                rlist.append(np.median(refs[idx], axis=0))
            plist.append(int(pos[spans[0][0]]) if pos is not None else -1)
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
