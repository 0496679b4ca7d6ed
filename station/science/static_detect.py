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

from station.science.chunked import PIECE, diffs, median_into, pieces, rows_mean_std


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
    """Per-axis white-noise sigma from the median absolute first difference (motion-insensitive).
    One axis at a time in one buffer (the same medians as of the (n - 1, 3) differences)."""
    acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    if acc.shape[0] < 3:
        return np.full(3, floor_g)
    mad = np.empty(3)
    buf = np.empty(acc.shape[0] - 1)
    for k in range(3):
        diffs(acc[:, k], [(0, acc.shape[0])]).fill(buf)
        buf -= median_into(buf)
        np.abs(buf, out=buf)
        mad[k] = median_into(buf)
    return np.maximum(1.4826 * mad / np.sqrt(2.0), floor_g)


def _window_sums(x: np.ndarray, w: int) -> np.ndarray:
    c = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(x, axis=0)])
    return c[w:] - c[:-w]


def static_mask(acc_g: np.ndarray, config: StaticDetectConfig | None = None) -> np.ndarray:
    """Boolean (n,) mask of static samples (before the minimum-length rule).

    A piece of windows at a time (issue 40): each piece's running sums start from the sums carried
    from the piece before, added in the same order as one cumulative sum over the record, so every
    window's figures are the same bits while only a piece of them exists at once."""
    cfg = config or StaticDetectConfig()
    acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    n = acc.shape[0]
    w = int(cfg.window_samples)
    if w < 4:
        raise ValueError("window_samples must be at least 4")
    if n < w:
        return np.zeros(n, dtype=bool)
    sigma = robust_noise_g(acc, cfg.noise_floor_g)
    centre = acc.mean(axis=0)  # cumulative sums of the centred data stay well conditioned
    h = w // 2
    grad_limit = cfg.gradient_factor * sigma * np.sqrt(2.0 / h)
    n_win = n - w + 1
    quiet = np.empty(n_win, dtype=bool)
    carry1 = carry2 = np.zeros((1, 3))
    for a in range(0, n_win, PIECE):  # windows starting at a..b-1 need the sums c[a..b-1+w]
        b = min(a + PIECE, n_win)
        centred = acc[a:b + w - 1] - centre
        c1 = np.cumsum(np.concatenate([carry1, centred]), axis=0)
        c2 = np.cumsum(np.concatenate([carry2, centred ** 2]), axis=0)
        carry1, carry2 = c1[b - a:b - a + 1], c2[b - a:b - a + 1]
        mean = (c1[w:] - c1[:-w]) / w
        var = np.maximum((c2[w:] - c2[:-w]) / w - mean ** 2, 0.0) * w / (w - 1)
        q = np.all(np.sqrt(var) <= cfg.std_factor * sigma, axis=1)
        first = (c1[h:h + b - a] - c1[:b - a]) / h  # first half of the window starting at k
        second = (c1[w:] - c1[w - h:w - h + b - a]) / h
        quiet[a:b] = q & np.all(np.abs(second - first) <= grad_limit, axis=1)
    # sample i is static when all windows k in [i-w+1, i] (those that exist) are quiet
    out = np.empty(n, dtype=bool)
    for a in range(0, n, PIECE):
        b = min(a + PIECE, n)
        lo = max(a - w + 1, 0)  # windows that can cover samples a..b-1: lo..min(b, n_win)-1
        loud = np.concatenate([[0], np.cumsum(~quiet[lo:min(b, n_win)], dtype=np.int64)])
        i = np.arange(a, b)
        k_lo = np.clip(i - w + 1, 0, n_win) - lo
        k_hi = np.clip(i + 1, 0, n_win) - lo
        out[a:b] = (loud[k_hi] - loud[k_lo]) == 0
    return out


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
        mean_g, std_g = rows_mean_std(lambda: (acc[a:b] for a, b in pieces([(int(start), int(stop))])), int(stop - start))
        out.append(
            StaticInterval(
                start=int(start),
                stop=int(stop),
                mean_g=mean_g,
                std_g=std_g,
                t_start_s=float(t[start]),
                t_end_s=float(t[stop - 1]),
            )
        )
    return out


__all__ = ["StaticDetectConfig", "StaticInterval", "detect_static_intervals", "static_mask", "robust_noise_g"]
