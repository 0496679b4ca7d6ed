"""One DUT in one batch (DutRun): what the daemon has received from its board, and the step-time
records (placement, requirement window, step clock) a step's kind reads to judge whether it has
logged what the current step requires (station/steps).

The sequencer judges steps by these records and the run's end judges the DUT from them; the pump
(intake.py) fills them. Kept apart from the state machine so the per-DUT bookkeeping (samples,
segments, step windows, resume state, program-and-verify outcome) reads in one place.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np

from contracts.run_records import ProgramRecord, ThermalReport
from contracts.sfem_result import SfemResult
from contracts.types import Identity, SampleBlock, Segment, ThermalResult
from station.daemon.temp_watch import TempFinding, TempWatch
from station.science.placement import Placement, same_direction


class Calibrator(Protocol):
    """What the daemon asks of a DUT's live calibrator (station/science/streaming.StreamingCalibrator
    is one): feed it placed samples, restart its averaging window after a gap, read its state and
    its result."""

    @property
    def state(self) -> str: ...

    def restart_window(self) -> None: ...

    def update_batch(self, time_s: np.ndarray, acc_g: np.ndarray, temp_c: np.ndarray) -> list[Segment]: ...

    def result(self) -> ThermalResult: ...


@dataclass
class DutRun:
    """One DUT in one batch: what its pump (intake.py) has received and the sequencer judges."""

    slot: str
    link: str = ""
    state: str = "connecting"  # connecting, identified, running, done, faulted
    identity: Identity | None = None
    run_id: int | None = None
    # the run's attempt number, read from the database when the run is made (or resumed): the
    # verdict at the run's end carries it without a database round trip (a database that is down
    # then must not stop a verdict)
    attempt: int | None = None
    fault_reason: str = ""
    calibrator: Calibrator | None = None
    blocks: list[SampleBlock] = field(default_factory=list)
    block_steps: list[int] = field(default_factory=list)
    # Per block, the position its samples were placed at (-1: not placed): blocks are cut where
    # the placement changes (station/science/placement.py), so one label holds for a whole block.
    block_positions: list[int] = field(default_factory=list)
    placement: Placement = field(default_factory=Placement)
    fed_last: bool = False  # the newest sample went to the calibrator (the next gap restarts its window)
    segments: list[Segment] = field(default_factory=list)
    segment_steps: list[int] = field(default_factory=list)
    t0: float | None = None  # board time of the first sample in this batch
    last_t: float | None = None  # board time of the latest sample
    n_samples: int = 0
    step_t_start: float = -math.inf  # board time when the current step began logging (Done, "reached")
    logging_block: int = 0  # len(blocks) when the current step began logging: what came after is its own
    # The current step's placement (station/science/placement.py, docs/design.md section 4), in
    # board time. Set at the step's setup, before anybody moves the plate: the step's position and
    # the one before it (still accepted until the DUT arrives: the plate sits there until turned),
    # the newest sample then (a segment step counts segments after it), the first sample of the
    # current run of placed samples and its position, the first sample placed at the step's own
    # position (None: not arrived yet) and when it last left it.
    step_position: int | None = None
    prev_position: int | None = None
    next_position: int | None = None
    step_setup_t: float = -math.inf
    # a static/heat/dwell requirement counts from samples after this board time: the step's setup,
    # or its logging start where the step switches the lamp (or heats): the lamp follows Done
    requirement_floor_t: float = -math.inf
    placed_since_t: float | None = None
    placed_at: int | None = None
    arrived_t: float | None = None
    left_t: float | None = None
    # What the DUT faced before the person was asked to turn (direction id: where the plate was
    # when the prompt came, else the first position it settled at in this batch), and the board time
    # the plate is watched from (Done, or the Done of a prompt asked again): station/daemon/plate_watch.py.
    faced_before: int | None = None
    first_settled: int | None = None
    plate_check_t: float = -math.inf
    step_windows: dict[int, tuple[float, float]] = field(default_factory=dict)  # step -> board time span
    result: ThermalReport | SfemResult | None = None  # the analysis (run_end.py): typed until the edges
    link_stats: dict[str, Any] = field(default_factory=dict)
    # The station's own backlog (station/daemon/intake_monitor.py): how far behind this link it runs
    # (wall s), the samples it lost while behind and their sample time, and that time when the
    # current step began logging: a step's clock does not count sample time the station lost.
    link_behind_s: float = 0.0
    station_lost_samples: int = 0
    station_lost_s: float = 0.0
    station_lost_step0_s: float = 0.0
    # Resume of an interrupted batch: the serial the stored run belongs to, the board time its
    # stored stream ended at (the live stream is joined on after it) and the offset applied.
    expected_serial: str | None = None
    label_serial: str | None = None  # scanned from the part's label at the start; must be the board's serial
    # tested without the MES's yes (its route check gave no usable answer, the site's policy is
    # proceed_and_flag): the words the page shows (the record holds route_check 'unanswered')
    route_flag: str = ""
    resume_t: float | None = None
    time_offset_s: float = 0.0
    hold_calibrator: bool = False  # resumed: samples are stored but not calibrated until logging
    unstored_segments: list[tuple[Segment, int]] = field(default_factory=list)
    verdict: dict[str, Any] | None = None  # the station's decision (station/decisions/moment.py)
    extra_measurements: list[Any] = field(default_factory=list)  # more station.decisions.verdicts.Measurement to judge
    program: ProgramRecord | None = None  # program and verify: what was written and read back (CRC, comp)
    verification: dict[str, Any] | None = None  # program and verify: verified drift error E (science.verify)
    steps_done: int = 0  # steps this DUT completed while live (the page's progress dots)
    # Is its temperature sensor believable (stuck, implausible)? station/daemon/temp_watch.py
    temp_watch: TempWatch = field(default_factory=TempWatch)

    @property
    def serial(self) -> str | None:
        return self.identity.serial if self.identity else None

    @property
    def live(self) -> bool:
        return self.state in ("connecting", "identified", "running")

    @property
    def elapsed_s(self) -> float:
        if self.t0 is None or self.last_t is None:
            return 0.0
        return self.last_t - self.t0

    def status(self) -> dict[str, Any]:
        return {
            "slot": self.slot,
            "link": self.link,
            "serial": self.serial,
            "label_serial": self.label_serial,
            "route_flag": self.route_flag,
            "sensor": self.identity.sensor if self.identity else None,
            "state": self.state,
            "fault_reason": self.fault_reason,
            "run_id": self.run_id,
            "samples": self.n_samples,
            "segments": len(self.segments),
            "sample_time_s": self.elapsed_s,
            "calibrator_state": getattr(self.calibrator, "state", None),
            "link_stats": dict(self.link_stats),
            "result": None if self.result is None else self.result.to_json(),
            "decision": self.verdict,
            "program": None if self.program is None else self.program.to_json(),
            "verification": self.verification,
            "steps_done": self.steps_done,
        }

    def watch_temp(self, block: SampleBlock, lamp_on: bool, live: list["DutRun"],
                   plate_temp_c: float | None) -> tuple[float | None, TempFinding | None]:
        """Show the block's temperatures to this DUT's sensor watch (the other live DUTs are its
        peers; how far its samples are behind the fastest of them is its lag): (the hottest reading
        the over-temperature check may believe or None, a finding that its sensor is stuck or
        implausible or None)."""
        peers = [p.temp_watch for p in live if p is not self]
        lag_s = max((p.elapsed_s for p in live), default=0.0) - self.elapsed_s
        finding = self.temp_watch.update(block.time_s, block.temp_c, lamp_on=lamp_on, lag_s=lag_s,
                                         peers=peers, plate_temp_c=plate_temp_c)
        return self.temp_watch.trusted_max_c, finding

    def temp_rise_c(self, t_from: float, n_edge: int = 8) -> float:
        """How far this DUT's own temperature has risen since board time t_from (a heat step):
        median of the latest n_edge samples minus median of the first n_edge after t_from."""
        tail: list[np.ndarray] = []
        for b in reversed(self.blocks):
            if len(b) == 0:
                continue
            if b.time_s[-1] <= t_from:
                break
            tail.append(b.temp_c[b.time_s > t_from])
        if not tail:
            return 0.0
        temps = np.concatenate(tail[::-1])
        if len(temps) < 2 * n_edge:
            return 0.0
        return float(np.median(temps[-n_edge:]) - np.median(temps[:n_edge]))

    def requirement_window(self) -> tuple[float, float] | None:
        """(from, to) board time of what a static, heat or dwell requirement has counted so far:
        from requirement_start_t to the newest sample; None while the DUT is not placed at the
        step's position (what a step kind's `done` reads: station/steps/builtin.py)."""
        if self.last_t is not None and not math.isfinite(self.step_t_start) and self.t0 is not None:
            # No sample had arrived when the step began logging (a step that needs no move, a slow
            # link): the DUT's first sample of the batch starts its dwell, instead of never.
            self.step_t_start = self.t0
        start = self.requirement_start_t()
        if self.last_t is None or start is None:
            return None
        return start, self.last_t

    def at_step_position(self) -> bool:
        """Is the DUT placed at its step's position now (settled there, by its own samples)?"""
        return (self.placed_since_t is not None and self.placed_at is not None and self.step_position is not None
                and same_direction(self.placed_at, self.step_position))

    def requirement_start_t(self) -> float | None:
        """Board time a static, heat or dwell requirement counts from: the start of the current run
        of samples placed at the step's position, not before the step began logging (the lamp, a
        program step's raw samples); None while the DUT is not placed there."""
        if not self.at_step_position():
            return None
        assert self.placed_since_t is not None
        return max(self.placed_since_t, self.requirement_floor_t)

    def segment_after_t(self) -> float:
        """A segment step counts the segments that end after this board time: the step's setup (the
        segment of the step before has ended by then; the plate may arrive, and a segment be logged,
        before a late Done), or -inf for a step resumed after a crash (a segment it logged counts)."""
        return min(self.step_setup_t, self.step_t_start)

    def begin_step(self, position: int, prev_position: int | None, next_position: int | None = None) -> None:
        """The step is set up (before the plate moves): its placement starts over, keeping a run of
        placed samples that goes on at the same position as the step before."""
        if not (self.placed_at is not None and same_direction(self.placed_at, position)):
            self.arrived_t = None
        else:
            self.arrived_t = self.placed_since_t
        self.step_position, self.prev_position, self.next_position = position, prev_position, next_position
        self.step_setup_t = self.last_t if self.last_t is not None else -math.inf
        self.left_t = None

    def begin_logging(self, gated: bool) -> None:
        """The step begins logging (Done, or the fixture reached): the plate is watched from here.
        gated: the step's requirement counts only from here (it switches the lamp, or heats)."""
        self.plate_check_t = self.step_t_start
        self.station_lost_step0_s = self.station_lost_s
        floor = self.step_setup_t if math.isfinite(self.step_setup_t) else (self.t0 if self.t0 is not None else -math.inf)
        self.requirement_floor_t = self.step_t_start if gated else floor

    def step_clock_start_t(self) -> float | None:
        """Board time this DUT's step timeout counts from (before it arrives): its newest sample
        when the step began logging, or, for a board that had sent nothing in this step by then (a
        slow link at a batch's start, a resumed step), the first sample it delivered after that.
        None: nothing delivered since. Never another board's clock: in compressed time, or behind
        a busy adapter, a late link is seconds of sample time behind the others."""
        if math.isfinite(self.step_t_start):
            return self.step_t_start
        for k in range(self.logging_block, len(self.blocks)):
            if len(self.blocks[k]):
                return float(self.blocks[k].time_s[0])
        return None

    def step_elapsed_s(self, batch_s: float) -> float:
        """Sample time this DUT has spent in the current step (its own board clock): since it
        arrived at the step's position, or, until it does, since the step began logging (Done).
        A board whose first sample of the step came after Done counts from that sample
        (step_clock_start_t): judged on the fastest board's clock, a link that lagged at the
        batch's start would be faulted 'without a segment' while it was still averaging at the
        position. Its first samples may have been measured before Done (a backlog), so its own
        figure is an upper bound, as is the batch's clock since Done (batch_s): the smaller one
        counts, and such a board is never timed out sooner than on the batch's clock. Only a board
        that has delivered nothing since is timed on the batch's clock alone (the stall watchdog
        faults a silent one long before). Sample time the station lost while it ran behind this
        link (its own backlog: intake_monitor.py) is not counted: a segment it hid is not the
        part's to deliver."""
        start = self.step_clock_start_t()
        if self.last_t is None or start is None:
            return batch_s
        if self.arrived_t is not None:
            start = max(self.arrived_t, start)
        lost_s = max(0.0, self.station_lost_s - self.station_lost_step0_s)
        if not math.isfinite(self.step_t_start):  # its board time at Done is unknown
            return min(self.last_t - start - lost_s, batch_s)
        return self.last_t - start - lost_s

    def since_plate_check_s(self) -> float:
        """Board seconds of this DUT's own stream since the plate is watched (its own clock: in
        compressed time a slow link is behind the others, and its plate must not be judged on their
        newer samples)."""
        if self.last_t is None:
            return 0.0
        ref = self.plate_check_t if math.isfinite(self.plate_check_t) else (self.t0 or self.last_t)
        return self.last_t - ref


    def release_samples(self) -> None:
        """The run has ended and its samples are stored: its raw blocks leave memory (its segments,
        result, verdict and counters stay, what the page shows of an ended run)."""
        self.blocks = []
        self.block_steps = []
        self.block_positions = []


def annotate_segment(seg: Segment, position: int | None) -> Segment:
    return replace(seg, position=position)


def wall_text(t: float) -> str:
    """A wall time as the operator reads it in a message: '2026-11-23 14:02:05 UTC'."""
    return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(t))


def iso_utc(t: float) -> str:
    """RFC 3339 UTC with seconds, as the REST API gives times."""
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t))
