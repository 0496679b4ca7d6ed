"""Is the station keeping up with its boards? Overload as a state, measured, never a part's fault.

A station given more boards (or a faster plant, in compressed time) than its CPU can follow falls
behind: the samples wait in the OS buffers, the boards' own buffers and the driver's queue, and
past their bounds they are lost. None of that is the part's doing, so it must never be judged as
the part's: this module measures it, the pump (intake.py) and the step clock (dut_run.py) act on it.

Pure bookkeeping (numbers in, numbers out; the caller passes the clocks), one monitor per station:

- **Behind, per link**: the samples waiting in the queues the station can see when its pump has
  just read (the OS buffer of the port, the bytes not parsed yet, the driver's queue:
  BoardDriver.backlog_samples), as the wall seconds the board takes to send them (ODR x speed,
  speed: plant seconds per wall second, 1 on real hardware). A queue, not the latency of the
  board's clock: a plant that runs slower than its nominal speed (a simulated one that waits for
  the station, a board clock slower than the station's) is no backlog, and a station that falls
  behind always has one.
- **Lost to the station**: a board's buffer overruns when the station does not read it in time.
  So a sequence gap found within `STRAIN_MEMORY_S` of a sign of strain is the station's loss: a
  link `ATTRIBUTE_BEHIND_S` behind, a pump that read `LOOP_LATE_S` later than it meant to (the
  event loop was held up: a board with a small buffer overruns long before the station is
  seconds behind), or a saturated process (its CPU time over the last window at least
  `SATURATED_CPU` of one core). So are the samples the driver dropped from its own full queue.
  The station's losses are counted per slot, said in the alarm and kept out of the part's
  lost-sample figure. A gap while the station keeps up (fresh samples, reads on time, idle CPU)
  is the link's (the board's, the cable's).
- **The alarm**: raised when any link is `ALARM_BEHIND_S` behind or the station lost samples in the
  last `ALARM_HOLD_S`; cleared once every link is back under `CLEAR_BEHIND_S` and nothing was lost
  for `ALARM_HOLD_S` (hysteresis: one alarm per episode, not one per block).
- **Capacity**: the station's CPU cost per sample (process CPU seconds per sample taken, measured
  over windows of at least `COST_WINDOW_S` while boards stream; before any, the configured figure)
  gives the samples per second it can follow on one core (`CORE_SHARE` of it: the page, the
  writer's bursts and the analyses need the rest). A batch whose boards would demand more is
  refused at its start, with the numbers (docs/design.md, capacity).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

log = logging.getLogger(__name__)

ALARM_BEHIND_S = 3.0  # wall seconds behind any link: the alarm
CLEAR_BEHIND_S = 1.0  # every link under this (and no loss for ALARM_HOLD_S): the alarm clears
ATTRIBUTE_BEHIND_S = 1.0  # a sequence gap while this far behind its link is the station's loss
ALARM_HOLD_S = 30.0  # a loss keeps the alarm up this long (wall seconds)
COST_WINDOW_S = 2.0  # CPU cost per sample is measured over windows at least this long (wall)
COST_MIN_SAMPLES = 500  # ... holding at least this many samples
COST_EMA = 0.3  # weight of a new window in the cost estimate
LOOP_LATE_S = 0.5  # a pump's read this much later than its period: the loop was held up
STRAIN_MEMORY_S = 10.0  # a gap found this long after a sign of strain is the station's
SATURATED_CPU = 0.85  # process CPU seconds per wall second: the station cannot take on more
CORE_SHARE = 0.8  # of one core, what the sample intake may use (the GIL: one core for all Python work)


@dataclass
class LinkLag:
    """One slot's link as the monitor follows it."""

    last_wall_s: float | None = None
    behind_s: float = 0.0
    lost_station: int = 0  # samples lost to the station's backlog (gaps while behind, queue drops)
    lost_link: int = 0  # samples the link lost while the station kept up
    odr_hz: float | None = None


@dataclass(frozen=True)
class Capacity:
    """What the station can follow and what a set of boards demands, in samples per second."""

    cost_us_per_sample: float
    measured: bool  # False: the configured figure (nothing streamed yet in this process)
    capacity_samples_per_s: float
    demand_samples_per_s: float
    n_duts: int
    odr_hz: float  # the boards' highest rate
    speed: float

    @property
    def load(self) -> float:
        """Demand over capacity: above 1 the station cannot follow."""
        return self.demand_samples_per_s / self.capacity_samples_per_s if self.capacity_samples_per_s > 0 else 0.0

    def words(self) -> str:
        plant = f" x{self.speed:g}" if self.speed != 1 else ""
        how = "measured" if self.measured else "configured"
        return (f"{self.n_duts} DUTs at {self.odr_hz:g} Hz{plant} demand {_rate(self.demand_samples_per_s)} "
                f"samples/s; this PC follows about {_rate(self.capacity_samples_per_s)} samples/s "
                f"({self.cost_us_per_sample:.1f} us of CPU per sample, {how}; {CORE_SHARE:.0%} of one core)")


@dataclass(frozen=True)
class OverloadState:
    """The monitor's verdict now: for /api/health, the batch status and the page."""

    behind_s: float  # the most the station runs behind any link, wall seconds
    alarm: str | None  # in words while the alarm is up, else None
    lost_station: int  # samples lost to the station's backlog since the monitor began
    lost_by_slot: dict[str, int] = field(default_factory=dict)  # slot -> samples lost to the station
    cost_us_per_sample: float | None = None
    capacity_samples_per_s: float | None = None
    intake_samples_per_s: float | None = None  # what the station took in over the last window
    cpu_share: float | None = None  # the process's CPU seconds per wall second over the last window


def _rate(v: float) -> str:
    if v >= 1e6:
        return f"{v / 1e6:.1f} M"
    if v >= 1e4:
        return f"{v / 1e3:.0f} k"
    return f"{v:.0f}"


READS_PER_S = 250.0  # block reads a second, all links together, before small reads are spaced out
# A read this big is not spaced out: its fixed cost (~0.75 ms) is then under half what its samples
# cost (~7 us each), so a longer wait would save little and delay what the station sees.
BIG_READ_SAMPLES = 256


def read_pace_s(read_period_s: float, links: int, samples_per_s: float = 0.0,
                reads_per_s: float = READS_PER_S) -> float:
    """Wall seconds between one link's block reads: the configured period, or longer when the
    station's links together would read more than `reads_per_s` times a second and this link's
    reads are small (fewer than BIG_READ_SAMPLES samples at the configured period).

    Why: a read costs the event loop about 0.5-1 ms whatever it carries (the calibrator's update,
    the temperature watch, the writer's hand-off, the events), so many small reads, not the
    samples, set how busy the loop is and how long a request waits for it. Measured with 64 DUTs
    at x60 (benchmarks/web_load.py, 19 samples a read at 0.1 s): 640 reads/s kept the loop ~55 %
    busy and its lag p99 at 9-11 ms; 256 reads/s (0.25 s each) put the lag p99 at 3.5-3.8 ms and
    the page's p99 near 5 ms and the CPU per sample at x240 from ~14 to ~12 us, the same samples
    taken. Big reads are cheap per sample already: spacing them out would only delay what the
    station sees. A station of up to 25 links keeps the period; a replay, whose world waits on
    the station, is configured never to space its reads (station/replay/runner.py: spaced out, a
    replay of 64 DUTs took 13.9 s instead of 9.3)."""
    if samples_per_s * read_period_s >= BIG_READ_SAMPLES:
        return read_period_s
    return max(read_period_s, links / reads_per_s)


class IntakeMonitor:
    """How far behind its boards the station runs, what it lost, what it can follow (module doc)."""

    def __init__(self, speed: float = 1.0, cost_us_per_sample: float = 8.0,
                 cpu_clock: Callable[[], float] = time.process_time, reads_per_s: float = READS_PER_S) -> None:
        self.reads_per_s = float(reads_per_s)
        self.speed = float(speed)
        self.cpu_clock = cpu_clock
        self.default_cost_us = float(cost_us_per_sample)
        self.links: dict[str, LinkLag] = {}
        self.pumping: set[str] = set()  # the slots whose pumps read now (read_pace_s)
        self._alarm: str | None = None
        self._last_loss_wall_s: float | None = None
        self._cost_us: float | None = None
        self._win: tuple[float, float, int] | None = None  # (wall, process CPU, samples) at the window's start
        self._samples = 0
        self._rate: float | None = None
        self.cpu_share = 0.0  # process CPU seconds per wall second over the last window
        self._strain_wall_s: float | None = None  # the last sign of strain (behind, a late read, saturated)
        self._said_wall_s = -1e18
        self._said: str | None = None
        self.alarms_raised = 0  # episodes since the monitor began
        self.peak_behind_s = 0.0

    def _say(self, alarm: str | None) -> None:
        """The station's log hears each alarm episode once, when it is raised and when it clears."""
        if alarm is not None and self._said is None:
            self.alarms_raised += 1
            log.warning("OVERLOAD: %s", alarm)
        elif alarm is None and self._said is not None:
            log.warning("overload cleared: the station follows its boards again (peak %.1f s behind)",
                        self.peak_behind_s)
        self._said = alarm

    # ------------------------------------------------------------------ per block
    def note_block(self, slot: str, wall_s: float, waiting: int, n: int, lost: int,
                   odr_hz: float | None, loop_late_s: float = 0.0) -> int:
        """A block of n samples taken in from `slot`, with `waiting` samples still queued for it (the
        driver's backlog_samples), the samples its link lost before it, how much later than meant its
        pump read it (wall s). Returns how many of the lost samples the station lost (module doc)."""
        self._samples += n
        if self._win is None or wall_s - self._win[0] >= COST_WINDOW_S:
            self.note_cpu(wall_s, self.cpu_clock(), self._samples)
        lag = self.links.setdefault(slot, LinkLag())
        if odr_hz:
            lag.odr_hz = float(odr_hz)
        rate = (lag.odr_hz or 0.0) * self.speed
        lag.behind_s = waiting / rate if rate > 0 else 0.0
        lag.last_wall_s = wall_s
        if lag.behind_s > ATTRIBUTE_BEHIND_S or loop_late_s > LOOP_LATE_S or self.saturated:
            self._strain_wall_s = wall_s
        station = 0
        if lost > 0:
            # the buffers overran while the station was strained, or just before it read again
            if self._strain_wall_s is not None and wall_s - self._strain_wall_s <= STRAIN_MEMORY_S:
                station = lost
                lag.lost_station += lost
                self._last_loss_wall_s = wall_s
            else:
                lag.lost_link += lost
        if wall_s - self._said_wall_s >= 1.0:
            self._said_wall_s = wall_s
            self._say(self.state(wall_s).alarm)
        return station

    def note_dropped(self, slot: str, n: int, wall_s: float) -> None:
        """The driver dropped n samples from its own full queue: the station's loss."""
        if n <= 0:
            return
        lag = self.links.setdefault(slot, LinkLag())
        lag.lost_station += n
        self._last_loss_wall_s = wall_s

    @property
    def saturated(self) -> bool:
        """The process used SATURATED_CPU of a core or more over the last window: it cannot take on
        more, and a board's buffer that overruns now overruns because of it."""
        return self.cpu_share >= SATURATED_CPU

    def behind_s(self, slot: str) -> float:
        """How far behind this slot's link the station runs now, wall seconds (0: unknown)."""
        lag = self.links.get(slot)
        return lag.behind_s if lag is not None else 0.0

    def pace_s(self, read_period_s: float, samples_per_s: float = 0.0) -> float:
        """How often a link sending samples_per_s is read now (read_pace_s over the pumps that run)."""
        return read_pace_s(read_period_s, len(self.pumping), samples_per_s, self.reads_per_s)

    def forget(self, slot: str) -> None:
        """The slot's run ended (or a new one starts on a new timeline): its lag is learned again.
        Its losses stay counted in the batch's record (LinkStats), not here."""
        self.links.pop(slot, None)

    # ------------------------------------------------------------------ CPU cost
    def note_cpu(self, wall_s: float, cpu_s: float, samples: int) -> None:
        """The process's CPU time and samples taken so far (cumulative). Windows of at least
        COST_WINDOW_S and COST_MIN_SAMPLES give the cost per sample, smoothed."""
        self._samples = samples
        if self._win is None:
            self._win = (wall_s, cpu_s, samples)
            return
        w0, c0, n0 = self._win
        dn, dw = samples - n0, wall_s - w0
        if dw < COST_WINDOW_S:
            return
        self._win = (wall_s, cpu_s, samples)
        self._rate = dn / dw
        self.cpu_share = max(0.0, cpu_s - c0) / dw
        if dn < COST_MIN_SAMPLES:
            return
        cost = 1e6 * max(0.0, cpu_s - c0) / dn
        self._cost_us = cost if self._cost_us is None else (1 - COST_EMA) * self._cost_us + COST_EMA * cost

    @property
    def cost_us_per_sample(self) -> float:
        return self._cost_us if self._cost_us is not None else self.default_cost_us

    def capacity(self, odr_hz: list[float], cost_us: float | None = None) -> Capacity:
        """What `odr_hz` (one entry per board) demand against what this station follows (at its
        cost per sample, or `cost_us`)."""
        cost = self.cost_us_per_sample if cost_us is None else cost_us
        cap = CORE_SHARE * 1e6 / cost if cost > 0 else float("inf")
        return Capacity(cost_us_per_sample=cost, measured=self._cost_us is not None, capacity_samples_per_s=cap,
                        demand_samples_per_s=sum(odr_hz) * self.speed, n_duts=len(odr_hz),
                        odr_hz=max(odr_hz, default=0.0), speed=self.speed)

    def refuse_start(self, odr_hz: list[float]) -> str | None:
        """Words refusing a batch whose boards demand more than the station follows, else None.
        The lower of the configured and the measured cost decides: a measured cost inflated by work
        that is not the intake's (an analysis, a plant simulated in the same process) must not
        refuse a batch this PC follows; set the configured figure from benchmarks/daemon_batch.py."""
        cap = self.capacity(odr_hz, cost_us=min(self.cost_us_per_sample, self.default_cost_us))
        if cap.load <= 1.0:
            return None
        return f"the station cannot follow this batch: {cap.words()}; run fewer DUTs at once or a lower rate"

    # ------------------------------------------------------------------ the state
    def state(self, wall_s: float) -> OverloadState:
        """Behind, lost and the alarm now (with hysteresis: see the module doc)."""
        behind = max((lag.behind_s for lag in self.links.values()), default=0.0)
        self.peak_behind_s = max(self.peak_behind_s, behind)
        lost = sum(lag.lost_station for lag in self.links.values())
        recent_loss = self._last_loss_wall_s is not None and wall_s - self._last_loss_wall_s < ALARM_HOLD_S
        if behind >= ALARM_BEHIND_S or recent_loss:
            self._alarm = self._words(behind, lost)
        elif self._alarm is not None and behind < CLEAR_BEHIND_S:
            self._alarm = None
        elif self._alarm is not None:
            self._alarm = self._words(behind, lost)
        cost = self.cost_us_per_sample
        return OverloadState(behind_s=round(behind, 3), alarm=self._alarm, lost_station=lost,
                             lost_by_slot={s: lag.lost_station for s, lag in self.links.items() if lag.lost_station},
                             cost_us_per_sample=round(cost, 2),
                             capacity_samples_per_s=round(CORE_SHARE * 1e6 / cost) if cost > 0 else None,
                             intake_samples_per_s=round(self._rate) if self._rate is not None else None,
                             cpu_share=round(self.cpu_share, 3))

    def _words(self, behind_s: float, lost: int) -> str:
        odrs = [lag.odr_hz for lag in self.links.values() if lag.odr_hz]
        cap = self.capacity([float(o) for o in odrs if o is not None])
        text = (f"station behind by {behind_s:.0f} s (CPU {self.cpu_share:.0%} of a core): {cap.words()}"
                if behind_s >= 0.5 or not lost else
                f"station overloaded (CPU {self.cpu_share:.0%} of a core): {cap.words()}")
        if lost:
            slots = sum(1 for lag in self.links.values() if lag.lost_station)
            text += f"; {lost} samples lost to the station's backlog on {slots} slot(s) (not the parts' fault)"
        return text
