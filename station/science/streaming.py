"""The streaming thermal calibrator of martinez2022 section 3.3 (the MCU algorithm).

This module holds only the sample-by-sample segment detector, the part an MCU would run. Its
constants are in streaming_config, the end-of-test computation (TD_i, Acc0_i -> TDB, TDSF) in
drift_coefficients (the offline fit uses it too), and the per-sample record of the gate's
decisions that the offline analyses replay in gate_trace.

Per sample: exponential filter (alpha 0.05) on the three axes and the temperature; thermal gradient
of the filtered temperature in C/min from the sample times, filtered again (alpha 0.01). Logging
is allowed only while |gradient| < 1 C/min: the first 500 stable samples are discarded (the count
restarts whenever the gate closes), then 1000 samples are averaged, the segment is saved and the
calibrator waits. A filtered temperature more than 20 C from the last saved segment is a segment
change; every axis more than 0.8 g from it is an orientation change; both reset the filtered
gradient to a high value so the slow gradient filter cannot open the gate early. At the end,
per orientation, TD_i (eq. 3) and Acc0_i (eq. 4) from each pair of consecutive temperature
segments (averaged when more than two), then TDSF (eq. 8) and TDB (eq. 9) per axis; a positive
TDSF is clamped to 0 and flagged.

Choices the paper leaves open, made here:
- Segment averages use the RAW measurements, not the filtered ones. The exponential filter has a
  memory of ~20 samples, so a filtered average would carry samples from before the averaging
  window (partly inside the discard window) and lag a drifting temperature by (1-a)/a samples;
  the raw mean is the unbiased estimate of the segment's level and its std is the true sample
  scatter. The filtered values only drive decisions (gate, change detection).
- The gate also applies while averaging: if it closes, discard and average both restart (the paper
  logs "only while" the gradient is below the limit).
- The gradient is reset to gradient_reset_c_per_min (default 10 C/min, ~230 samples of alpha 0.01
  to decay below 1 C/min) and starts there at power-up, so the self-heating transient is skipped.
  The reset takes the sign of the change (cooling: -10 C/min; orientation: the sign of the current
  gradient): a +10 reset while cooling would be pulled through zero by the negative gradient and
  open the gate early, which is exactly what the reset is there to prevent.
- An orientation change is also looked for while settling/discarding/averaging (once per saved
  segment, `detect_orientation_while_logging`), so a plate turned before a segment completed does
  not mix two orientations in one average. Temperature changes are only looked for while waiting,
  as in the paper.
- A non-increasing sample time contributes a zero gradient (duplicated or reset timestamps).
- TD_i pairs too close in temperature are skipped (drift_coefficients).

Two entry points, `update` (one sample) and `update_batch` (numpy arrays), give identical
results to the last bit wherever the batches are cut: both run the same recursions with the same
floating-point operations in the same order (the batch path uses scipy.signal.lfilter, whose
direct-form-II-transposed step is `y = z + a x; z = (1-a) y`, the scalar path the same two lines;
running sums use the sequential np.add.accumulate). The batch path only steps through the state
machine at gate crossings, change events and count boundaries, found by vectorized searches.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter

from station.science.drift_coefficients import result_from_segments
from station.science.streaming_config import StreamingConfig
from contracts.types import Segment, ThermalResult

_WAITING = "waiting"
_CHUNK = 8192  # samples per internal step of update_batch


@dataclass
class _Recorder:
    """Per-chunk decisions of the batch path, kept when gate_trace.trace_gate replays a record."""

    grad: list = field(default_factory=list)
    orient: list = field(default_factory=list)
    acc: list = field(default_factory=list)
    temp: list = field(default_factory=list)


class StreamingCalibrator:
    """One DUT's streaming calibrator; keeps only the running values the MCU would keep."""

    def __init__(self, config: StreamingConfig | None = None) -> None:
        self.config = config or StreamingConfig()
        c = self.config
        self._a = float(c.alpha_acc)
        self._c = 1.0 - self._a
        self._ag = float(c.alpha_gradient)
        self._cg = 1.0 - self._ag
        self._b_f = np.array([self._a])
        self._a_f = np.array([1.0, -self._c])
        self._b_g = np.array([self._ag])
        self._a_g = np.array([1.0, -self._cg])
        self._init = False
        self._facc = [0.0, 0.0, 0.0]  # last filtered acceleration
        self._ftemp = 0.0  # last filtered temperature
        self._t_prev = 0.0
        self._grad = float(c.gradient_reset_c_per_min)
        self._waiting = False
        self._n_disc = 0
        self._n_avg = 0
        self._k_acc = [0.0, 0.0, 0.0]  # shift (first averaged sample) for stable sums of squares
        self._k_temp = 0.0
        self._s1 = [0.0, 0.0, 0.0]
        self._s2 = [0.0, 0.0, 0.0]
        self._s1t = 0.0
        self._s2t = 0.0
        self._t_start = 0.0
        self._last_acc: tuple[float, float, float] | None = None
        self._last_temp = 0.0
        self._armed = False  # an orientation change may still be registered since the last save
        self._orientation = 0
        self.segments: list[Segment] = []
        self._before_save: list[tuple] = []  # change references before each save (discard_last_segment)
        self.samples_seen = 0

    # ------------------------------------------------------------------ status
    @property
    def state(self) -> str:
        """settling (gate closed), discarding, averaging or waiting (segment saved)."""
        if self._waiting:
            return _WAITING
        if self._n_avg > 0 or (self._n_disc >= self.config.discard_samples and self._n_disc > 0):
            return "averaging"
        if self._n_disc > 0:
            return "discarding"
        return "settling"

    @property
    def gradient_c_per_min(self) -> float:
        return self._grad

    @property
    def orientation(self) -> int:
        return self._orientation

    def restart_window(self) -> None:
        """The stream was interrupted (daemon restart, link gap): samples from both sides of the
        gap must not share one average, so discarding and averaging start over, as when the gate
        closes. Saved segments, the orientation and the filters are kept; a saved segment that is
        waiting for the next temperature or orientation change keeps waiting."""
        if not self._waiting:
            self._reset_counters()

    def discard_last_segment(self) -> Segment:
        """Forget the newest saved segment and log again from here: the station could not place it
        (the plate's position was unknown while it was averaged: boards connecting, the fixture
        moving). Otherwise the calibrator would wait for the next temperature or orientation change
        with a segment no step can use, and the step would time out. The change references go back
        to what they were before it was saved; the filters are kept (the gate stays as it is)."""
        seg = self.segments.pop()
        self._last_acc, self._last_temp, self._armed = self._before_save.pop()
        self._waiting = False
        self._reset_counters()
        return seg

    # ------------------------------------------------------------------ shared steps
    def _reset_counters(self) -> None:
        self._n_disc = 0
        self._n_avg = 0

    def _change(self, orientation: bool, negative: bool) -> None:
        """Segment or orientation change: reset the gradient high and start settling."""
        if orientation:
            self._orientation += 1
            self._armed = False
        self._waiting = False
        h = float(self.config.gradient_reset_c_per_min)
        self._grad = -h if (negative and self.config.gradient_reset_signed) else h
        self._reset_counters()

    def _emit(self, t_end_s: float) -> Segment:
        n = self._n_avg
        acc_mean, acc_std = [], []
        for k in range(3):
            m1 = self._s1[k] / n
            acc_mean.append(self._k_acc[k] + m1)
            acc_std.append(math.sqrt(max(self._s2[k] / n - m1 * m1, 0.0)))
        m1t = self._s1t / n
        seg = Segment(
            index=len(self.segments),
            orientation=self._orientation,
            n_samples=n,
            t_start_s=self._t_start,
            t_end_s=t_end_s,
            acc_mean_g=(acc_mean[0], acc_mean[1], acc_mean[2]),
            acc_std_g=(acc_std[0], acc_std[1], acc_std[2]),
            temp_mean_c=self._k_temp + m1t,
            temp_std_c=math.sqrt(max(self._s2t / n - m1t * m1t, 0.0)),
        )
        self.segments.append(seg)
        self._before_save.append((self._last_acc, self._last_temp, self._armed))
        self._last_acc = seg.acc_mean_g
        self._last_temp = seg.temp_mean_c
        self._armed = True
        self._waiting = True
        self._reset_counters()
        return seg

    # ------------------------------------------------------------------ one sample
    def update(self, time_s: float, acc_g, temp_c: float) -> list[Segment]:
        """Feed one sample; returns the segments it completed (none or one)."""
        t = float(time_s)
        ax, ay, az = (float(v) for v in acc_g)
        x = (ax, ay, az)
        temp = float(temp_c)
        a, c = self._a, self._c
        cfg = self.config
        self.samples_seen += 1
        if not self._init:
            self._init = True
            self._facc = [c * v + a * v for v in x]  # state (1-a) x0: the filter starts on x0
            self._ftemp = c * temp + a * temp
            self._t_prev = t
        else:
            self._facc = [self._facc[k] * c + a * x[k] for k in range(3)]
            ft = self._ftemp * c + a * temp
            dt = t - self._t_prev
            g = (ft - self._ftemp) / dt * 60.0 if dt > 0.0 else 0.0
            self._grad = self._grad * self._cg + self._ag * g
            self._ftemp = ft
            self._t_prev = t
        f = self._facc
        last = self._last_acc
        od = cfg.orientation_delta_g
        if (
            self._armed
            and (self._waiting or cfg.detect_orientation_while_logging)
            and abs(f[0] - last[0]) > od
            and abs(f[1] - last[1]) > od
            and abs(f[2] - last[2]) > od
        ):
            self._change(orientation=True, negative=self._grad < 0.0)
            return []
        if self._waiting:
            if abs(self._ftemp - self._last_temp) > cfg.segment_delta_c:
                self._change(orientation=False, negative=self._ftemp < self._last_temp)
            return []
        if not abs(self._grad) < cfg.gradient_limit_c_per_min:
            self._reset_counters()
            return []
        if self._n_disc < cfg.discard_samples:
            self._n_disc += 1
            return []
        if self._n_avg == 0:
            self._k_acc = list(x)
            self._k_temp = temp
            self._s1 = [0.0, 0.0, 0.0]
            self._s2 = [0.0, 0.0, 0.0]
            self._s1t = 0.0
            self._s2t = 0.0
            self._t_start = t
        for k in range(3):
            d = x[k] - self._k_acc[k]
            self._s1[k] = self._s1[k] + d
            self._s2[k] = self._s2[k] + d * d
        d = temp - self._k_temp
        self._s1t = self._s1t + d
        self._s2t = self._s2t + d * d
        self._n_avg += 1
        if self._n_avg >= cfg.average_samples:
            return [self._emit(t)]
        return []

    # ------------------------------------------------------------------ a batch
    def update_batch(self, time_s, acc_g, temp_c) -> list[Segment]:
        """Feed n samples at once; same result as n calls of `update`, much faster."""
        return self._run(time_s, acc_g, temp_c, None)

    def _run(self, time_s, acc_g, temp_c, rec: _Recorder | None) -> list[Segment]:
        t = np.ascontiguousarray(time_s, dtype=np.float64).reshape(-1)
        acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
        temp = np.ascontiguousarray(temp_c, dtype=np.float64).reshape(-1)
        n = t.shape[0]
        if acc.shape[0] != n or temp.shape[0] != n:
            raise ValueError(f"batch columns differ in length: {n}, {acc.shape[0]}, {temp.shape[0]}")
        # Work in bounded chunks: a change event re-filters the gradient and re-searches to the end
        # of the chunk, so huge batches would cost O(n) per event. Chunking changes nothing else
        # (the recursions carry their state exactly).
        out: list[Segment] = []
        for i in range(0, n, _CHUNK):
            out += self._run_chunk(t[i : i + _CHUNK], acc[i : i + _CHUNK], temp[i : i + _CHUNK], rec)
        return out

    def _run_chunk(self, t: np.ndarray, acc: np.ndarray, temp: np.ndarray, rec: _Recorder | None) -> list[Segment]:
        n = t.shape[0]
        cfg = self.config
        a, c = self._a, self._c
        acc_t = np.ascontiguousarray(acc.T)  # (3, n): filter along the contiguous axis
        first = not self._init
        if first:
            zi = c * acc_t[:, :1]
            zt = np.array([c * temp[0]])
        else:
            zi = np.array([[v * c] for v in self._facc])
            zt = np.array([self._ftemp * c])
        facc_t, _ = lfilter(self._b_f, self._a_f, acc_t, axis=1, zi=zi)
        ftemp, _ = lfilter(self._b_f, self._a_f, temp, zi=zt)
        # raw gradient of the filtered temperature, C/min
        if first:
            ft_prev, t_prev = ftemp[:-1], t[:-1]
            ft_cur, t_cur = ftemp[1:], t[1:]
        else:
            ft_prev = np.concatenate(([self._ftemp], ftemp[:-1]))
            t_prev = np.concatenate(([self._t_prev], t[:-1]))
            ft_cur, t_cur = ftemp, t
        dt = t_cur - t_prev
        g = np.zeros(dt.shape[0])
        np.divide(ft_cur - ft_prev, dt, out=g, where=dt > 0.0)
        g *= 60.0
        grad = np.empty(n)
        off = 1 if first else 0  # g[j] belongs to sample j + off
        if first:
            grad[0] = self._grad
        if n > off:
            grad[off:], _ = lfilter(self._b_g, self._a_g, g, zi=np.array([self._grad * self._cg]))
        limit = cfg.gradient_limit_c_per_min
        od = cfg.orientation_delta_g
        facc = facc_t.T  # (n, 3) view

        def unstable_from(p: int) -> np.ndarray:
            return p + np.flatnonzero(~(np.abs(grad[p:]) < limit))

        def orient_from(p: int) -> np.ndarray:
            la = np.asarray(self._last_acc)
            return p + np.flatnonzero(np.all(np.abs(facc[p:] - la) > od, axis=1))

        def temp_from(p: int) -> np.ndarray:
            return p + np.flatnonzero(np.abs(ftemp[p:] - self._last_temp) > cfg.segment_delta_c)

        def nxt(idx: np.ndarray, p: int) -> int:
            j = np.searchsorted(idx, p)
            return int(idx[j]) if j < idx.shape[0] else n

        def reset_at(k: int) -> None:
            grad[k] = self._grad  # set by _change
            if k + 1 < n:
                grad[k + 1 :], _ = lfilter(
                    self._b_g, self._a_g, g[k + 1 - off :], zi=np.array([grad[k] * self._cg])
                )

        out: list[Segment] = []
        orient_label = np.empty(n, dtype=np.int64) if rec is not None else None
        u_idx = unstable_from(0)
        o_idx = orient_from(0) if self._armed else np.empty(0, dtype=np.int64)
        t_idx = temp_from(0) if self._waiting else np.empty(0, dtype=np.int64)
        p = 0
        while p < n:
            if self._waiting:
                k_o = nxt(o_idx, p) if self._armed else n
                k_t = nxt(t_idx, p)
                k = min(k_o, k_t)
                if orient_label is not None:
                    orient_label[p:k] = self._orientation
                if k >= n:
                    p = n
                    break
                if k == k_o:
                    self._change(orientation=True, negative=bool(grad[k] < 0.0))
                else:
                    self._change(orientation=False, negative=bool(ftemp[k] < self._last_temp))
                reset_at(k)
                if orient_label is not None:
                    orient_label[k] = self._orientation
                u_idx = unstable_from(k)
                p = k + 1
                continue
            check_o = self._armed and cfg.detect_orientation_while_logging
            k_o = nxt(o_idx, p) if check_o else n
            u = nxt(u_idx, p)
            stop = min(k_o, u)
            if orient_label is not None:
                orient_label[p:stop] = self._orientation
            # [p, stop): stable, no event: count discards, then average
            need_d = cfg.discard_samples - self._n_disc
            m = stop - p
            if m <= need_d:
                self._n_disc += m
            else:
                self._n_disc = cfg.discard_samples
                q = p + max(need_d, 0)
                r = min(stop, q + (cfg.average_samples - self._n_avg))
                if r > q:
                    self._accumulate(t, acc, temp, q, r)
                    if self._n_avg >= cfg.average_samples:
                        out.append(self._emit(float(t[r - 1])))
                        o_idx = orient_from(r)
                        t_idx = temp_from(r)
                        p = r
                        continue
            if stop >= n:
                p = n
                break
            if stop == k_o:
                self._change(orientation=True, negative=bool(grad[k_o] < 0.0))
                reset_at(k_o)
                u_idx = unstable_from(k_o)
            else:
                self._reset_counters()
            if orient_label is not None:
                orient_label[stop] = self._orientation
            p = stop + 1
        # carry the state
        self._init = True
        self._facc = [float(v) for v in facc[-1]]
        self._ftemp = float(ftemp[-1])
        self._t_prev = float(t[-1])
        self._grad = float(grad[-1])
        self.samples_seen += n
        if rec is not None:
            rec.grad.append(grad.copy())
            rec.orient.append(orient_label)
            rec.acc.append(facc.copy())
            rec.temp.append(ftemp.copy())
        return out

    def _accumulate(self, t: np.ndarray, acc: np.ndarray, temp: np.ndarray, q: int, r: int) -> None:
        """Add raw samples [q, r) to the running sums, sequentially (bit-identical to `update`)."""
        if self._n_avg == 0:
            self._k_acc = [float(v) for v in acc[q]]
            self._k_temp = float(temp[q])
            self._s1 = [0.0, 0.0, 0.0]
            self._s2 = [0.0, 0.0, 0.0]
            self._s1t = 0.0
            self._s2t = 0.0
            self._t_start = float(t[q])
        d = acc[q:r] - np.asarray(self._k_acc)
        s1 = np.add.accumulate(np.vstack((self._s1, d)), axis=0)[-1]
        s2 = np.add.accumulate(np.vstack((self._s2, d * d)), axis=0)[-1]
        dt_ = temp[q:r] - self._k_temp
        self._s1 = [float(v) for v in s1]
        self._s2 = [float(v) for v in s2]
        self._s1t = float(np.add.accumulate(np.concatenate(([self._s1t], dt_)))[-1])
        self._s2t = float(np.add.accumulate(np.concatenate(([self._s2t], dt_ * dt_)))[-1])
        self._n_avg += r - q

    # ------------------------------------------------------------------ the result
    def result(self) -> ThermalResult:
        """TDB/TDSF per axis from the saved segments (method "streaming"); InsufficientData if
        fewer than two orientations have two segments far enough apart in temperature."""
        return result_from_segments(self.segments, self.config)


__all__ = [
    "StreamingCalibrator",
]
