"""Signal operators the effect library builds its terms from (pure: arrays in, arrays out).

Why a module of its own: the thermal lag, the hysteresis operators and the smoothing of the
measured temperature are the physics' shapes; an effect (effects.py) only decides which operator
of which input makes its regressor, and a user's effect file can use the same operators.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import lfilter

from station.science.chunked import PIECE, median_step_s




def lag_filter(x: np.ndarray, time_s: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order lag y' = (x - y)/tau, exact for x varying linearly between samples (a
    ramp-invariant discretization: the 10 s block means of a ramp are not a staircase, and holding
    each would delay the output by half a block); starts settled at x[0].

    Uses the median sample interval (logs are evenly sampled; a few lost samples barely matter).
    """
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return x.copy()
    dt = max(median_step_s(time_s) if x.size > 1 else 1.0, 1e-9)
    tau = max(tau_s, 1e-9)
    a = math.exp(-dt / tau)
    b0 = 1.0 - (tau / dt) * (1.0 - a)
    b1 = (1.0 - a) - b0
    y, _ = lfilter([b0, b1], [1.0, -a], x, zi=[(a + b1) * x[0]])
    return y


def smooth_temperature(temp_c: np.ndarray, time_s: np.ndarray, window_s: float = 60.0) -> np.ndarray:
    """Zero-phase moving average: removes the 1 C quantization staircase and its dither, no lag.

    The running sum is taken a piece at a time, carried from piece to piece in the order one
    np.cumsum over the padded record adds (issue 40: the same bits, and the output is the one array
    of the record's length it makes)."""
    n = temp_c.shape[0]
    if n < 3:
        return temp_c.astype(np.float64).copy()
    dt = median_step_s(time_s)
    w = max(1, int(round(window_s / max(dt, 1e-9))))
    if w <= 1:
        return temp_c.astype(np.float64).copy()
    half = w // 2
    x = np.asarray(temp_c, dtype=np.float64)
    first, last = x[0], x[-1]

    def padded(a: int, b: int) -> np.ndarray:
        """Samples [a, b) of [first] * half + temp_c + [last] * (w - half - 1)."""
        lo, hi = max(a, half), min(b, half + n)
        mid = x[lo - half:hi - half] if hi > lo else x[:0]
        return np.concatenate([np.full(max(min(b, half) - a, 0), first), mid,
                               np.full(max(b - max(a, half + n), 0), last)])

    out = np.empty(n)
    carry = np.zeros(1)  # c[a]: the running sum before padded sample a
    for a in range(0, n, PIECE):  # outputs a..b-1 need c[a..b-1+w]
        b = min(a + PIECE, n)
        c = np.cumsum(np.concatenate([carry, padded(a, b + w - 1)]), dtype=np.float64)
        out[a:b] = (c[w:] - c[:-w]) / w
        carry = c[b - a:b - a + 1]
    return out


def hysteresis_state(temp_c: np.ndarray, time_s: np.ndarray, width_c, shape: str = "smooth",
                     deadband_c: float = 0.1, grid_s: float = 5.0) -> np.ndarray:
    """State z(t) in [-1, 1] of a rate-independent hysteresis operator of the temperature, z(0) = 0:
    (n,) for one width, (n, W) for an array of widths (one pass over time for all of them).

    The input is the smoothed measured temperature; a backlash of deadband_c first removes its
    residual noise wiggles, which would otherwise (summed over an hour-long plateau) move the state
    while the true die temperature moves monotonically. Computed on a grid of at least grid_s (the
    temperature is smooth on that scale) and interpolated back.
    """
    widths = np.atleast_1d(np.asarray(width_c, float))
    n = temp_c.shape[0]
    if n == 0:
        return np.zeros((0,) if np.ndim(width_c) == 0 else (0, widths.size))
    dt = median_step_s(time_s) if n > 1 else grid_s
    step = max(1, int(round(grid_s / max(dt, 1e-9))))
    idx = np.arange(0, n, step)
    if idx[-1] != n - 1:
        idx = np.append(idx, n - 1)
    # the input after the noise deadband, and the points where it moves (only those change z)
    t = np.asarray(temp_c, float)[idx].tolist()
    half = deadband_c / 2.0
    y = [t[0]]
    for tk in t[1:]:
        y.append(tk - half if tk > y[-1] + half else tk + half if tk < y[-1] - half else y[-1])
    yk = np.asarray(y)
    moves = np.flatnonzero(np.diff(yk) != 0) + 1
    w = np.maximum(widths, 1e-9)
    z = np.zeros(widths.size)
    zk = np.zeros((yk.size, widths.size))
    hi = np.full(widths.size, yk[0])  # relay: extremes since its last switch
    lo = hi.copy()
    play = hi.copy()  # backlash: the play operator's output (radius w / 2)
    prev = 0
    for k in moves:
        zk[prev:k] = z
        prev = k
        v, dv = yk[k], yk[k] - yk[k - 1]
        if shape == "smooth":
            s_ = 1.0 if dv > 0 else -1.0
            z = s_ + (z - s_) * np.exp(-abs(dv) / w)
        elif shape == "relay":
            np.maximum(hi, v, out=hi)
            np.minimum(lo, v, out=lo)
            down = (z >= 0.0) & (v < hi - w)
            up = (z <= 0.0) & (v > lo + w)
            z = np.where(down, -1.0, np.where(up, 1.0, z))
            lo = np.where(down, v, lo)
            hi = np.where(up, v, hi)
        else:  # backlash
            play = np.minimum(np.maximum(play, v - w / 2.0), v + w / 2.0)
            z = (v - play) / (w / 2.0)
    zk[prev:] = z
    out = np.empty((n, widths.size))
    for j in range(widths.size):
        out[:, j] = np.interp(np.arange(n), idx, zk[:, j])
    return out[:, 0] if np.ndim(width_c) == 0 else out


__all__ = ["lag_filter", "smooth_temperature", "hysteresis_state"]
