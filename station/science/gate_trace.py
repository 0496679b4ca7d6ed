"""The streaming calibrator's decisions sample by sample, over a whole record, for offline analyses.

Why a module of its own: the live station needs only the calibrator's saved segments. The offline
fit (offline_fit) and the residual analysis (residual) need, for every sample, what the gradient
gate and the orientation counter decided, so that they pick their samples by the calibrator's own
rule. That view is recorded by replaying the record through the calibrator's batch path with a
recorder attached; it lives here so that streaming.py stays the algorithm an MCU would run.

Bounded memory (issue 40): the trace keeps, per sample, only what the gate decided (stable: one
byte; the orientation counter: two). The filtered acceleration and temperature (32 bytes a sample,
160 MB on a 200 MB log) are not kept: the calibrator's exponential filter carries nothing but its
last output between its 8192-sample chunks, so the trace keeps that output at each chunk's end and
recomputes any span from the chunk it starts in, with the same scipy lfilter call on the same
numbers, bit for bit what the calibrator computed (tests/test_long_logs.py holds it to that).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from station.science.streaming import StreamingCalibrator, _Recorder
from station.science.streaming_config import StreamingConfig
from contracts.types import Segment

PASS_SAMPLES = 1 << 16  # samples a chunked pass over a trace handles at once (a multiple of the calibrator's chunk)


class _Into(list):
    """A recorder list that keeps nothing itself: each chunk the calibrator appends is handed to
    `put` (which stores its compact form), so no per-chunk copy piles up."""

    def __init__(self, put: Callable[[np.ndarray], None]) -> None:
        super().__init__()
        self._put = put

    def append(self, chunk: np.ndarray) -> None:  # type: ignore[override]
        self._put(chunk)


class _Sink:
    """What the calibrator's recorder hands over, stored compactly (module doc)."""

    def __init__(self, n: int, limit_c_per_min: float) -> None:
        self.limit = limit_c_per_min
        self.stable = np.empty(n, dtype=bool)
        self.orientation = np.empty(n, dtype=np.int16)  # widened if a record ever turns 32 767 times
        self.starts: list[int] = []  # first sample of each calibrator chunk
        self.acc_last: list[np.ndarray] = []  # its filtered acceleration's last row
        self.temp_last: list[float] = []
        self._at = {"grad": 0, "orient": 0, "acc": 0, "temp": 0}

    def _next(self, key: str, m: int) -> int:
        a = self._at[key]
        self._at[key] = a + m
        return a

    def grad(self, g: np.ndarray) -> None:
        a = self._next("grad", g.shape[0])
        self.stable[a:a + g.shape[0]] = np.abs(g) < self.limit  # GateTrace.stable's rule
        self.starts.append(a)

    def orient(self, o: np.ndarray) -> None:
        a = self._next("orient", o.shape[0])
        if o.shape[0] and int(o.max()) > np.iinfo(self.orientation.dtype).max:
            self.orientation = self.orientation.astype(np.int64)
        self.orientation[a:a + o.shape[0]] = o

    def acc(self, f: np.ndarray) -> None:
        self._next("acc", f.shape[0])
        self.acc_last.append(np.array(f[-1], dtype=np.float64))

    def temp(self, f: np.ndarray) -> None:
        self._next("temp", f.shape[0])
        self.temp_last.append(float(f[-1]))

    def recorder(self) -> _Recorder:
        return _Recorder(grad=_Into(self.grad), orient=_Into(self.orient), acc=_Into(self.acc), temp=_Into(self.temp))


@dataclass
class GateTrace:
    """Per-sample view of the calibrator's decisions, for the offline fit and for plots.

    stable (n,) bool: the gradient gate open (|filtered gradient| < limit); orientation (n,) the
    counter after each sample. The filtered signals are recomputed on demand (module doc):
    `acc_filt_between(a, b)`, `temp_filt_between(a, b)`; `acc_filt_g`, `temp_filt_c` give them whole."""

    stable: np.ndarray
    orientation: np.ndarray
    limit_c_per_min: float
    _acc: np.ndarray  # (n, 3) the samples the calibrator saw (a view, no copy)
    _temp: np.ndarray
    _starts: np.ndarray  # (k,) first sample of each calibrator chunk
    _acc_last: np.ndarray  # (k, 3) filtered acceleration at each chunk's last sample
    _temp_last: np.ndarray  # (k,)
    _b: np.ndarray
    _a: np.ndarray
    _c: float  # 1 - alpha, exactly as the calibrator holds it

    def __len__(self) -> int:
        return int(self.stable.shape[0])

    def _from(self, a: int) -> int:
        """Index of the calibrator chunk sample a falls in."""
        return int(np.searchsorted(self._starts, a, side="right")) - 1

    def acc_filt_between(self, a: int, b: int) -> np.ndarray:
        """(b - a, 3) the calibrator's filtered acceleration of samples [a, b)."""
        if b <= a:
            return np.empty((0, 3))
        j = self._from(a)
        s = int(self._starts[j])
        acc_t = np.ascontiguousarray(self._acc[s:b].T)
        c = self._c
        zi = c * acc_t[:, :1] if j == 0 else np.array([[v * c] for v in self._acc_last[j - 1].tolist()])
        f, _ = lfilter(self._b, self._a, acc_t, axis=1, zi=zi)
        return f.T[a - s:]

    def temp_filt_between(self, a: int, b: int) -> np.ndarray:
        """(b - a,) the calibrator's filtered temperature of samples [a, b)."""
        if b <= a:
            return np.empty(0)
        j = self._from(a)
        s = int(self._starts[j])
        temp = self._temp[s:b]
        zt = np.array([self._c * temp[0]]) if j == 0 else np.array([float(self._temp_last[j - 1]) * self._c])
        f, _ = lfilter(self._b, self._a, temp, zi=zt)
        return f[a - s:]

    def spans(self, a: int = 0, b: int | None = None) -> Iterator[tuple[int, int]]:
        """[start, end) pieces of PASS_SAMPLES covering [a, b): a chunked pass's steps."""
        end = len(self) if b is None else b
        for s in range(a, end, PASS_SAMPLES):
            yield s, min(s + PASS_SAMPLES, end)

    @property
    def acc_filt_g(self) -> np.ndarray:
        """(n, 3) the whole filtered acceleration (24 bytes a sample: a chunked pass needs less)."""
        out = np.empty((len(self), 3))
        for a, b in self.spans():
            out[a:b] = self.acc_filt_between(a, b)
        return out

    @property
    def temp_filt_c(self) -> np.ndarray:
        """(n,) the whole filtered temperature."""
        out = np.empty(len(self))
        for a, b in self.spans():
            out[a:b] = self.temp_filt_between(a, b)
        return out


def trace_gate(time_s, acc_g, temp_c, config: StreamingConfig | None = None) -> tuple[GateTrace, list[Segment]]:
    """Run the calibrator over a whole record and return its per-sample gate view and segments."""
    cal = StreamingCalibrator(config)
    t = np.ascontiguousarray(time_s, dtype=np.float64).reshape(-1)
    acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    temp = np.ascontiguousarray(temp_c, dtype=np.float64).reshape(-1)
    sink = _Sink(t.shape[0], cal.config.gradient_limit_c_per_min)
    cal._run(t, acc, temp, sink.recorder())
    trace = GateTrace(sink.stable, sink.orientation, cal.config.gradient_limit_c_per_min, acc, temp,
                      np.asarray(sink.starts, dtype=np.int64), np.asarray(sink.acc_last).reshape(-1, 3),
                      np.asarray(sink.temp_last, dtype=np.float64), cal._b_f, cal._a_f, cal._c)
    return trace, cal.segments


__all__ = [
    "GateTrace",
    "trace_gate",
    "PASS_SAMPLES",
]
