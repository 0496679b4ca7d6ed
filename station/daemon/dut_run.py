"""One DUT in one batch (DutRun): what the daemon has received from its board, and whether it has
logged what the current step requires.

The sequencer judges steps by these records and the run's end judges the DUT from them; the pump
(intake.py) fills them. Kept apart from the state machine so the per-DUT bookkeeping (samples,
segments, step windows, resume state, program-and-verify outcome) reads in one place.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from contracts.positions import first_facing
from contracts.types import Identity, SampleBlock, Segment
from station.profiles import Step


@dataclass
class DutRun:
    """One DUT in one batch: what the supervisor has received and the sequencer judges."""

    slot: str
    link: str = ""
    state: str = "connecting"  # connecting, identified, running, done, faulted
    identity: Identity | None = None
    run_id: int | None = None
    fault_reason: str = ""
    calibrator: Any = None
    blocks: list[SampleBlock] = field(default_factory=list)
    block_steps: list[int] = field(default_factory=list)
    segments: list[Segment] = field(default_factory=list)
    segment_steps: list[int] = field(default_factory=list)
    t0: float | None = None  # board time of the first sample in this batch
    last_t: float | None = None  # board time of the latest sample
    n_samples: int = 0
    step_t_start: float = -math.inf  # board time when the current step began logging
    step_facing: bool = True  # a static step's samples show its position (contracts.positions.first_facing)
    facing_scan: int = 0  # blocks already searched for the first facing sample
    step_windows: dict[int, tuple[float, float]] = field(default_factory=dict)  # step -> board time span
    result: dict | None = None
    link_stats: dict = field(default_factory=dict)
    # Resume of an interrupted batch: the serial the stored run belongs to, the board time its
    # stored stream ended at (the live stream is joined on after it) and the offset applied.
    expected_serial: str | None = None
    label_serial: str | None = None  # scanned from the part's label at the start; must be the board's serial
    resume_t: float | None = None
    time_offset_s: float = 0.0
    hold_calibrator: bool = False  # resumed: samples are stored but not calibrated until logging
    unstored_segments: list[tuple[Segment, int]] = field(default_factory=list)
    verdict: dict | None = None  # the station's decision (station/decisions/moment.py)
    extra_measurements: list = field(default_factory=list)  # more station.decisions.verdicts.Measurement to judge
    program: dict | None = None  # program and verify: what was written and read back (CRC, comp)
    verification: dict | None = None  # program and verify: verified drift error E (science.verify)
    steps_done: int = 0  # steps this DUT completed while live (the page's progress dots, issue 9)

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

    def status(self) -> dict:
        return {
            "slot": self.slot,
            "link": self.link,
            "serial": self.serial,
            "label_serial": self.label_serial,
            "sensor": self.identity.sensor if self.identity else None,
            "state": self.state,
            "fault_reason": self.fault_reason,
            "run_id": self.run_id,
            "samples": self.n_samples,
            "segments": len(self.segments),
            "sample_time_s": self.elapsed_s,
            "calibrator_state": getattr(self.calibrator, "state", None),
            "link_stats": dict(self.link_stats),
            "result": self.result,
            "decision": self.verdict,
            "program": self.program,
            "verification": self.verification,
            "steps_done": self.steps_done,
        }

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

    def step_done(self, step: Step, step_index: int) -> bool:
        """Has this DUT logged what step `step_index` requires: a segment at its position, the
        temperature rise of a heat step, or the dwell (after settle) of a static/none step; the
        dwell starts at the first sample facing the step's position."""
        d = self
        if step.require == "segment":
            return any(
                st == step_index and seg.position == step.position and seg.t_end_s > d.step_t_start
                for seg, st in zip(d.segments, d.segment_steps)
            )
        if d.last_t is not None and not math.isfinite(d.step_t_start) and d.t0 is not None:
            # No sample had arrived when the step began logging (a step that needs no move, a slow
            # link): the DUT's first sample of the batch starts its dwell, instead of never.
            d.step_t_start = d.t0
        if d.last_t is None or not math.isfinite(d.step_t_start):
            return False
        if not d.step_facing and not d._find_facing(step):
            return False
        if step.require == "heat":
            return d.last_t - d.step_t_start >= step.settle_s and d.temp_rise_c(d.step_t_start) >= step.heat_c
        need = step.dwell_s + (step.settle_s if step.require == "static" else 0.0)
        return d.last_t - d.step_t_start >= need

    def _find_facing(self, step: Step) -> bool:
        """Search the blocks that arrived since the last look for the first sample facing the
        step's position; when found, the step's settle and dwell start at it."""
        d = self
        blocks = d.blocks[d.facing_scan:]
        d.facing_scan += len(blocks)
        for blk in blocks:
            later = blk.time_s > d.step_t_start
            k = first_facing(blk.acc_g[later], step.position)
            if k is not None:
                d.step_t_start = float(blk.time_s[later][k])
                d.step_facing = True
                return True
        return False


def annotate_segment(seg: Segment, position: int | None) -> Segment:
    return replace(seg, position=position)


def wall_text(t: float) -> str:
    """A wall time as the operator reads it in a message: '2026-11-23 14:02:05 UTC'."""
    return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(t))


def iso_utc(t: float) -> str:
    """RFC 3339 UTC with seconds, as the REST API gives times."""
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t))
