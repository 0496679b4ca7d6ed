"""Is this DUT's temperature sensor telling the truth? A stuck or implausible sensor, in words.

Pure (numpy in, a typed finding out, no I/O): one `TempWatch` per DUT and batch, fed every sample
block of that DUT (its own sample clock, seconds; its temperature, C) with what the station knows
besides: whether the lamp is on, the other live DUTs' watches (their rise since the lamp went on)
and the reference thermometer's plate temperature when the station has one. It returns None or a
`TempFinding` whose reason the operator reads; the daemon faults that DUT alone with it
(station/daemon/intake.py `ingest`, docs/design.md section 4).

Why: a heat step waits until every live DUT's own temperature has risen (and a hot segment needs
a temperature that rose and settled), so one stuck sensor held the lamp on for the whole plate
until the step's timeout (3,000 s for fast-thermal's P hot) and then said only "timed out without a
segment"; and a sensor that jumps to 91 C tripped the over-temperature safety for every DUT.

The physics the thresholds come from (docs/design.md section 6, drivers/sim/world.py): the lamp
drives the plate toward +32 C (+38 C over the lamp after the turn, lamp gain 0.95..1.05 per DUT)
with a time constant of 480 s; the die follows the plate with 60..120 s. Measured on the
simulator's 32-DUT population (LIS3DSH and ADXL355), the die rose, since the lamp went on:

    after    60 s   120 s   180 s   240 s   300 s   600 s
    median   1.0    3.5-3.8 6.0-6.2 9.0     11.6-12 21 C
    slowest  0.5    2.0     5.0     7.0     10      19 C   (slowest / median >= 0.5 at every time)

The fastest the lamp can change a die is the plate's initial slope, 38 C x 1.05 / 480 s = 0.08 C/s
(a chamber ramps 2 C/min = 0.03 C/s); a healthy run's 3-sample median never moved more than 2 C
(LIS3DSH: 1 C counts plus 0.3 C noise) or 0.45 C (ADXL355) within 5 s.

Rules (each a named constant below, with its unit):

- implausible, range: the median of the latest `LEVEL_N` samples lies outside the sensors' range
  `TEMP_RANGE_C` (-40..+125 C). One sample never decides (one odd frame is not a broken sensor).
- implausible, rate: the median of the latest `LEVEL_N` samples differs from the median of
  `LEVEL_N` samples `RATE_SPAN_S` (5 s) earlier by more than `JUMP_C` = `RATE_MAX_C_PER_S` x
  `RATE_SPAN_S` (2 C/s x 5 s = 10 C): 24x the lamp's fastest slope, and 10 LIS3DSH counts, where a
  healthy sensor's quantization and noise move that median by 2 counts at most. Measured over
  seconds, never sample to sample: a 1-count LIS3DSH step in one 0.32 s sample period is "3 C/s"
  and nothing wrong.
- stuck, against the peers (the plate's other live DUTs): at least `STUCK_MIN_S` (120 s, one die
  time constant and more) after the lamp went on, the peers' median rise at the same time since
  the lamp went on (each on its own sample clock, so a link that lags is compared at its own time)
  is at least `STUCK_PEER_RISE_C` (5 C, reached ~170 s after the lamp went on), and this DUT rose
  less than `STUCK_OWN_RISE_C` (0.75 C: under one LIS3DSH count; a level that moved by a whole count
  is a sensor that works, only late: a QEMU-emulated firmware board on a loaded CI host read 1.0 C
  when its peers read 5.0 C, 160 s after the lamp went on, and was faulted with 1.5 C here; a stuck
  sensor reads exactly one count, 0 C of rise), less than `STUCK_FRACTION` (0.25) of that median, and
  its reading has not changed at all for `STUCK_MIN_S` (a stuck sensor repeats one value; a late one
  changes, if only by noise: a second QEMU board under heavier load read 0.5 C of rise against 5.1 C
  and was faulted before this): a
  healthy DUT is at >= 0.5 of the median (2.5 C when the median is 5 C), twice the fraction, and a
  LIS3DSH that sits on one count at the start of heating reads 0 C of rise only while the peers
  are far below 5 C. The lamp's hot plateau (on for long, flat) still reads the whole rise since
  the lamp went on, so a flat plateau never looks stuck; nor does the turn (the plate hotter over
  the lamp: every DUT rises more).
- stuck, against the reference thermometer (no peer: a batch of one DUT): at least `STUCK_MIN_S`
  after the lamp went on, the plate rose at least `STUCK_REF_RISE_C` (10 C: the plate leads the
  die, which is at >= 5 C by then) and this DUT less than 0.75 C and 0.25 of that.
- stuck, absolute (no peer and no thermometer; also a backstop for a plate whose every sensor
  stuck): not one count of change for `STUCK_FLAT_S` (300 s), from a moment within the first
  `STUCK_FLAT_S` after a lamp-on from cool (the lamp had been off `COOL_OFF_S`, 480 s = one plate
  time constant, of this DUT's samples before): such a plate is at most 38 C / e = 14 C above the
  room, so the lamp still lifts it >= 16 C, and the die rises >= 5 C in any 300 s of its first
  600 s (5 LIS3DSH counts, 45 ADXL355 counts). Later the plate nears its plateau, where a reading
  flat for minutes is what a healthy sensor shows.

Nothing stuck is judged while the lamp is off, or in a lamp period whose start this watch did not
see (the first block of the batch already had the lamp on: a resumed batch). The lamp's switch-on
in this DUT's sample time is the newest sample before the first block read with the lamp on (the
sequencer's step_t_start for that step): samples still in the link's buffer then were measured
earlier, so the estimate is early by the link's backlog. In compressed time a busy link is tens of
sample seconds behind the others (0.2 s of wall time at x150 is 30 s): judged from the early
estimate, a healthy DUT 90 s behind read 0.9 C of rise "144 s after the lamp went on" while its
peers had 5 C (the simulator's run with lagging links, tests/test_temp_watch.py). So a DUT's own
time counts from the estimate plus its lag behind the fastest board then (`lag_s`), while the rise
its peers compare with counts from the early estimate: each error makes it look less stuck.
The reference thermometer is read now, ahead of a lagging DUT's samples: STUCK_REF_RISE_C (the
plate at 180 s, the slowest die at 5 C) leaves a minute of lag before a healthy die is below 1.5 C.
"""

from __future__ import annotations

import bisect

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

TEMP_RANGE_C = (-40.0, 125.0)  # the sensors' range (LIS3DSH, ADXL355): a reading outside is no temperature
LEVEL_N = 3  # samples whose median is "the reading now" (a single odd sample never decides)
RATE_SPAN_S = 5.0  # sample seconds a rate is measured over
RATE_MAX_C_PER_S = 2.0  # 24x the lamp's fastest slope (0.08 C/s)
JUMP_C = RATE_MAX_C_PER_S * RATE_SPAN_S  # 10 C within RATE_SPAN_S: implausible
RATE_GAP_S = 2 * RATE_SPAN_S  # a sample this long before is across a gap: no rate over it
STUCK_LEVEL_N = 8  # samples whose median is the level a rise is measured from and to
STUCK_MIN_S = 120.0  # sample seconds after the lamp went on before "stuck" is judged at all
STUCK_PEER_RISE_C = 5.0  # the peers' median rise that makes a flat DUT stuck
STUCK_REF_RISE_C = 10.0  # the reference thermometer's rise that makes a flat DUT stuck
STUCK_OWN_RISE_C = 0.75  # a stuck DUT rose less than this (under one LIS3DSH count, 1 C) ...
STUCK_FRACTION = 0.25  # ... and less than this fraction of the peers' (or the plate's) rise
STUCK_FLAT_S = 300.0  # no peer, no thermometer: not one count of change in this long after a lamp-on from cool
COOL_OFF_S = 480.0  # lamp off this long (one plate time constant) before: a lamp-on "from cool"
HISTORY_S = RATE_SPAN_S + 5.0  # recent samples kept (the rate's span and its windows)


@dataclass(frozen=True)
class TempFinding:
    """Why this DUT's temperature sensor cannot be believed (the DUT is faulted with `reason`)."""

    kind: Literal["stuck", "implausible"]
    reason: str
    time_s: float  # the DUT's sample time it was decided at


def _c(x: float) -> str:
    """A temperature as the operator reads it: '24 C' on whole degrees, '24.3 C' otherwise."""
    return f"{x:.0f} C" if abs(x - round(x)) < 0.05 else f"{x:.1f} C"


class TempWatch:
    """One DUT's temperature sensor over one batch (see the module doc for the rules)."""

    def __init__(self) -> None:
        self._t = np.empty(0)  # recent samples (the last HISTORY_S, at least STUCK_LEVEL_N)
        self._c = np.empty(0)
        self._lev = np.empty(0)  # _levels of _c, kept with it: only a block's new samples are computed
        self.last_t: float | None = None
        self.finding: TempFinding | None = None
        self.trusted_max_c: float | None = None  # hottest believable reading of the latest block
        # the lamp, in this DUT's sample time
        self._lamp_seen = False  # a block was read with the lamp on in the current lamp period
        self._off_since_t: float | None = None  # the lamp was (seen) off from this sample time
        self.lamp_on_t: float | None = None  # the lamp went on at this sample time (None: off or unseen)
        self._own_on_t = 0.0  # the same, late by this DUT's lag behind the station's clock then
        self._cool = False  # the lamp went on from cool (off for COOL_OFF_S before)
        self._off_s = 0.0  # sample seconds the lamp had been off before it went on
        self._base_c = 0.0  # level when the lamp went on
        self._plate_base_c: float | None = None
        self._flat_since_t: float | None = None  # first sample of the current run of one same reading
        self._since_on_s: list[float] = []  # (sample s since the lamp went on, rise C): what peers compare
        self._rise_c: list[float] = []

    # ------------------------------------------------------------------ what peers read
    def rise_at_c(self, since_on_s: float) -> float | None:
        """This DUT's rise since the lamp went on, `since_on_s` sample seconds after it went on
        (interpolated); its latest rise when it has not got that far yet (a lagging link: less,
        so a peer behind never makes another DUT look stuck); None without a lamp-on seen."""
        if self.lamp_on_t is None or not self._since_on_s:
            return None
        xs, ys = self._since_on_s, self._rise_c
        if since_on_s >= xs[-1]:
            return ys[-1]
        # np.interp on the lists converted each time cost O(history) per call, 63 peers per block:
        # the station's largest cost per sample late in a long batch. bisect is O(log n), same value.
        k = bisect.bisect_right(xs, since_on_s)
        if k == 0:
            return ys[0]
        x0, x1, y0, y1 = xs[k - 1], xs[k], ys[k - 1], ys[k]
        return y0 if x1 == x0 else y0 + (since_on_s - x0) * (y1 - y0) / (x1 - x0)

    # ------------------------------------------------------------------ one block
    def update(self, time_s: np.ndarray, temp_c: np.ndarray, *, lamp_on: bool, lag_s: float = 0.0,
               peers: Sequence["TempWatch"] = (), plate_temp_c: float | None = None) -> TempFinding | None:
        """Take one block of this DUT's samples. Returns a finding once (then None: the DUT is
        faulted); sets `trusted_max_c`, the hottest reading of the block the over-temperature
        check may believe: not one that jumped JUMP_C away from the readings before it or lies
        out of range (until it is confirmed implausible, or gone: a single odd sample).

        lamp_on: the lamp now. lag_s: how far this DUT's newest sample is behind the station's
        sample clock (the fastest board's), in sample seconds: at the switch-on, its newest samples
        were measured that much before the lamp went on (a busy link in compressed time), so its
        own time since then counts from lamp_on_t + lag_s; its peers compare with its rise counted
        from lamp_on_t (the later, the smaller: never a peer that looks hotter than it was).
        peers: the other live DUTs' watches. plate_temp_c: the reference thermometer now, or None."""
        t = np.asarray(time_s, dtype=np.float64).ravel()
        c = np.asarray(temp_c, dtype=np.float64).ravel()
        self.trusted_max_c = None
        if self.finding is not None or t.size == 0:
            return None
        self._see_lamp(lamp_on, float(t[0]), plate_temp_c, lag_s)
        n_old = self._t.size
        all_t, all_c = np.concatenate([self._t, t]), np.concatenate([self._c, c])
        lev = np.concatenate([self._lev, _levels_from(all_c, n_old)])
        self.trusted_max_c = _trusted_max(all_c, n_old, lev)
        self.finding = _implausible(all_t, all_c, n_old, lev)
        keep = max(int(np.searchsorted(all_t, all_t[-1] - HISTORY_S)), 0)
        keep = min(keep, max(all_t.size - STUCK_LEVEL_N, 0))
        self._t, self._c, self._lev = all_t[keep:], all_c[keep:], lev[keep:]
        self.last_t = float(t[-1])
        changed = np.flatnonzero(all_c[n_old:] != all_c[n_old - 1:-1]) if n_old else np.flatnonzero(np.diff(c)) + 1
        if changed.size or self._flat_since_t is None:
            self._flat_since_t = float(t[int(changed[-1])] if changed.size else t[0])
        if self.finding is None and self.lamp_on_t is not None:
            self.finding = self._stuck(peers, plate_temp_c)
        if self.finding is not None:
            self.trusted_max_c = None
        return self.finding

    def _see_lamp(self, lamp_on: bool, first_t: float, plate_temp_c: float | None, lag_s: float) -> None:
        """Follow the lamp in this DUT's sample time: its switch-on is the newest sample before
        the first block read with it on; a switch-off starts the count of COOL_OFF_S."""
        if not lamp_on:
            if self._lamp_seen or self._off_since_t is None:
                self._off_since_t = self.last_t if self._lamp_seen and self.last_t is not None else first_t
            self._lamp_seen = False
            self.lamp_on_t = None
            return
        if self._lamp_seen:
            return
        self._lamp_seen = True
        if self.last_t is None or self._c.size == 0:
            return  # already on at this DUT's first sample: its start is unknown, nothing judged
        self.lamp_on_t = self.last_t
        self._own_on_t = self.lamp_on_t + max(float(lag_s), 0.0)
        self._off_s = self.lamp_on_t - self._off_since_t if self._off_since_t is not None else 0.0
        self._cool = self._off_s >= COOL_OFF_S
        self._base_c = float(np.median(self._c[-STUCK_LEVEL_N:]))
        self._plate_base_c = plate_temp_c
        self._since_on_s, self._rise_c = [], []

    def _stuck(self, peers: Sequence["TempWatch"], plate_temp_c: float | None) -> TempFinding | None:
        assert self.lamp_on_t is not None and self.last_t is not None
        level = float(np.median(self._c[-STUCK_LEVEL_N:]))
        rise = level - self._base_c
        self._since_on_s.append(self.last_t - self.lamp_on_t)
        self._rise_c.append(rise)
        since_s = self.last_t - self._own_on_t
        if since_s < STUCK_MIN_S:
            return None
        own = f" (it rose {rise:.1f} C)" if rise >= 0.05 else ""
        head = f"temperature sensor stuck at {_c(level)}{own}"
        when = f"in the {since_s:.0f} s since the lamp went on"
        assert self._flat_since_t is not None
        # a stuck sensor repeats one reading; a late one (a lagging link) changes, if only by noise
        unchanged = self.last_t - self._flat_since_t >= STUCK_MIN_S
        rises = [r for p in peers if p is not self and (r := p.rise_at_c(since_s)) is not None]
        if rises:
            med = float(np.median(rises))
            if unchanged and med >= STUCK_PEER_RISE_C and rise < min(STUCK_OWN_RISE_C, STUCK_FRACTION * med):
                others = "DUT" if len(rises) == 1 else "DUTs"
                words = f"the plate's other {others} rose {med:.1f} C{' (median)' if len(rises) > 1 else ''} {when}"
                return TempFinding("stuck", f"{head}: {words}", self.last_t)
        elif plate_temp_c is not None and self._plate_base_c is not None:
            plate_rise = plate_temp_c - self._plate_base_c
            if unchanged and plate_rise >= STUCK_REF_RISE_C and rise < min(STUCK_OWN_RISE_C, STUCK_FRACTION * plate_rise):
                words = f"the plate's reference thermometer rose {plate_rise:.1f} C {when}"
                return TempFinding("stuck", f"{head}: {words}", self.last_t)
        flat_s = self.last_t - max(self._flat_since_t, self._own_on_t)
        early = self._flat_since_t - self.lamp_on_t <= STUCK_FLAT_S  # not the hot plateau: flat by nature
        if self._cool and early and flat_s >= STUCK_FLAT_S:
            words = (f"not one count of change for {flat_s:.0f} s {when}, after {self._off_s:.0f} s off "
                     f"(from cool: the lamp heats the plate by many C in that time)")
            return TempFinding("stuck", f"{head}: {words}", self.last_t)
        return None


def _levels(c: np.ndarray) -> np.ndarray:
    """Median of each sample and the LEVEL_N - 1 before it (NaN where fewer exist)."""
    out = np.full(c.size, np.nan)
    if c.size >= LEVEL_N:
        win = np.lib.stride_tricks.sliding_window_view(c, LEVEL_N)
        out[LEVEL_N - 1:] = np.median(win, axis=1)
    return out


def _levels_from(c: np.ndarray, n_old: int) -> np.ndarray:
    """_levels(c)[n_old:], computed from the LEVEL_N - 1 samples before n_old on: a block costs its
    own samples, not the history's (each median is of its own window, so the values are the same)."""
    a = max(n_old - (LEVEL_N - 1), 0)
    return _levels(c[a:])[n_old - a:] if a else _levels(c)[n_old:]


def _trusted_max(c: np.ndarray, n_old: int, lev: np.ndarray | None = None) -> float | None:
    """The hottest of the new samples (from index n_old) in range and within JUMP_C of the median
    of the (up to LEVEL_N) samples before each: a jump is not believed before it is judged."""
    lo, hi = TEMP_RANGE_C
    k = np.arange(n_old, c.size)
    prior = np.full(k.size, np.nan)  # the median of the LEVEL_N samples before each (fewer at the start)
    if lev is None:
        lev = _levels(c)
    full = k >= LEVEL_N
    prior[full] = lev[k[full] - 1]
    for m in np.flatnonzero(~full & (k > 0)):
        prior[m] = float(np.median(c[:k[m]]))
    x = c[k]
    ok = (x >= lo) & (x <= hi) & (np.isnan(prior) | (np.abs(x - prior) <= JUMP_C))
    return float(x[ok].max()) if ok.any() else None


def _implausible(t: np.ndarray, c: np.ndarray, n_old: int, lev: np.ndarray | None = None) -> TempFinding | None:
    """The range and rate rules on the new samples (from index n_old), the earlier ones as history.
    lev: _levels(c), when the caller has it."""
    if lev is None:
        lev = _levels(c)
    lo, hi = TEMP_RANGE_C
    k = np.arange(max(n_old, LEVEL_N - 1), c.size)
    if k.size == 0:
        return None
    now = lev[k]
    out = (now < lo) | (now > hi)
    j = np.searchsorted(t, t[k] - RATE_SPAN_S, side="right") - 1  # newest sample RATE_SPAN_S earlier
    # across a gap in the samples (lost on the link, or to the station's own backlog) there is no
    # rate: a plate that heated 15 C while no sample came is no jump of the sensor
    jj = np.maximum(j, 0)
    then = np.where((j >= LEVEL_N - 1) & (t[k] - t[jj] <= RATE_GAP_S), lev[jj], np.nan)
    with np.errstate(invalid="ignore"):
        jump = np.abs(now - then) > JUMP_C  # NaN (no history that far back): False
    hit = np.flatnonzero(out | jump)
    if hit.size == 0:
        return None
    m = int(hit[0])
    x, at_s = float(now[m]), float(t[k[m]])
    if out[m]:
        return TempFinding("implausible", f"temperature sensor implausible: reads {_c(x)}, outside its "
                                          f"{lo:g}..{hi:g} C range", at_s)
    a, old = int(j[m]), float(then[m])
    # the change in words: from the last sample still at the old reading to the first at the new
    # one (a jump: one sample period; a ramp: its length)
    tol = max(1.0, 0.1 * abs(x - old))
    seg = c[a:k[m] + 1]
    at_old = np.flatnonzero(np.abs(seg - old) <= tol)
    i0 = int(at_old[-1]) if at_old.size else 0
    at_new = np.flatnonzero(np.abs(seg[i0:] - x) <= tol)
    i1 = i0 + (int(at_new[0]) if at_new.size else seg.size - 1 - i0)
    dt = float(t[a + i1] - t[a + i0])
    return TempFinding("implausible", f"temperature sensor implausible: {_c(old)} -> {_c(x)} in {dt:.1f} s", at_s)
