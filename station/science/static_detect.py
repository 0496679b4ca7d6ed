"""Static-interval detection for SFEM fits: where is the DUT held still, and what does it read there.

A sliding window of `window_samples` samples is *quiet* when, on every axis,
  1. its standard deviation is at most `std_factor` x sigma_noise   (variance test: vibration,
     handling, a fixture that is still turning), and
  2. the difference between the means of its two halves is at most `gradient_factor` x the
     standard error of that difference, 2 sigma_noise / sqrt(window)   (gradient test: a slow tilt or
     creep that is too smooth to raise the variance much).
sigma_noise is estimated per axis from the data itself, robustly: 1.4826 median|diff(a)| / sqrt(2)
(first differences cancel any slow motion, the median ignores the moving parts), floored at
`noise_floor_g` so that a heavily quantized, nearly constant signal still gets a usable threshold.
A sample is static when *every* window that contains it is quiet (morphological erosion), so motion
never leaks into an interval through the window's reach; runs shorter than `min_samples` are dropped.

Defaults (window 20 samples, std 2.5 sigma, gradient 5 standard errors, 0.1 mg floor, 20 samples
minimum) keep a false alarm rate per window far below 1e-3 on white noise: the window standard
deviation of 20 white samples scatters by about 16 %, so 2.5 sigma is > 9 standard deviations away;
the gradient test at 5 standard errors has a false alarm probability of 6e-7 per axis and window.
Thresholds adapt to the sensor, so the same defaults serve a 3.125 Hz LIS3DSH and a 200 Hz board.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class StaticDetectConfig:
    window_samples: int = 20
    std_factor: float = 2.5
    gradient_factor: float = 5.0
    noise_floor_g: float = 1e-4
    min_samples: int = 20


@dataclass(frozen=True)
class StaticInterval:
    """Samples [start, stop) held still; mean and standard deviation of the acceleration there."""

    start: int
    stop: int
    mean_g: np.ndarray  # (3,)
    std_g: np.ndarray  # (3,) sample standard deviation per axis
    t_start_s: float
    t_end_s: float

    @property
    def n_samples(self) -> int:
        return self.stop - self.start

    @property
    def sigma_mean_g(self) -> float:
        """1-sigma of the mean vector per axis (white-noise assumption), RMS over axes."""
        return float(np.sqrt(np.mean(self.std_g**2)) / np.sqrt(max(self.n_samples, 1)))


def robust_noise_g(acc_g: np.ndarray, floor_g: float = 1e-4) -> np.ndarray:
    """Per-axis white-noise sigma from the median absolute first difference (motion-insensitive)."""
    acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    if acc.shape[0] < 3:
        return np.full(3, floor_g)
    d = np.diff(acc, axis=0)
    mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    return np.maximum(1.4826 * mad / np.sqrt(2.0), floor_g)


def _window_sums(x: np.ndarray, w: int) -> np.ndarray:
    c = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(x, axis=0)])
    return c[w:] - c[:-w]


def static_mask(acc_g: np.ndarray, config: StaticDetectConfig | None = None) -> np.ndarray:
    """Boolean (n,) mask of static samples (before the minimum-length rule)."""
    cfg = config or StaticDetectConfig()
    acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    n = acc.shape[0]
    w = int(cfg.window_samples)
    if w < 4:
        raise ValueError("window_samples must be at least 4")
    if n < w:
        return np.zeros(n, dtype=bool)
    sigma = robust_noise_g(acc, cfg.noise_floor_g)
    centred = acc - acc.mean(axis=0)  # cumulative sums stay well conditioned
    s1 = _window_sums(centred, w)
    s2 = _window_sums(centred**2, w)
    mean = s1 / w
    var = np.maximum(s2 / w - mean**2, 0.0) * w / (w - 1)
    quiet = np.all(np.sqrt(var) <= cfg.std_factor * sigma, axis=1)
    h = w // 2
    first = _window_sums(centred, h)[: n - w + 1] / h  # first half of the window starting at k
    second = _window_sums(centred, h)[w - h : n - h + 1] / h
    grad_limit = cfg.gradient_factor * sigma * np.sqrt(2.0 / h)
    quiet &= np.all(np.abs(second - first) <= grad_limit, axis=1)
    # sample i is static when all windows k in [i-w+1, i] (those that exist) are quiet
    loud = (~quiet).astype(np.int64)
    c = np.concatenate([[0], np.cumsum(loud)])
    i = np.arange(n)
    k_lo = np.clip(i - w + 1, 0, n - w + 1)
    k_hi = np.clip(i + 1, 0, n - w + 1)
    return (c[k_hi] - c[k_lo]) == 0


def detect_static_intervals(
    time_s: np.ndarray | None,
    acc_g: np.ndarray,
    config: StaticDetectConfig | None = None,
    **overrides,
) -> list[StaticInterval]:
    """Static intervals of a record: index ranges plus per-interval means (see module docstring).

    time_s may be None (sample indices are used as time). Keyword overrides replace config fields,
    e.g. `detect_static_intervals(t, a, window_samples=50)`.
    """
    cfg = config or StaticDetectConfig()
    if overrides:
        cfg = StaticDetectConfig(**{**cfg.__dict__, **overrides})
    acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    n = acc.shape[0]
    t = np.arange(n, dtype=np.float64) if time_s is None else np.asarray(time_s, dtype=np.float64).reshape(-1)
    if t.shape[0] != n:
        raise ValueError(f"time_s has {t.shape[0]} samples, acc_g has {n}")
    mask = static_mask(acc, cfg)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    out: list[StaticInterval] = []
    for start, stop in zip(edges[::2], edges[1::2]):
        if stop - start < cfg.min_samples:
            continue
        seg = acc[start:stop]
        out.append(
            StaticInterval(
                start=int(start),
                stop=int(stop),
                mean_g=seg.mean(axis=0),
                std_g=seg.std(axis=0, ddof=1),
                t_start_s=float(t[start]),
                t_end_s=float(t[stop - 1]),
            )
        )
    return out


__all__ = ["StaticDetectConfig", "StaticInterval", "detect_static_intervals", "static_mask", "robust_noise_g"]
