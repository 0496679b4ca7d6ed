"""What the page and the REST API see of a running batch (GET /api/batches/{id}): its state, the
step, the plate, the lamp, each slot, and what it waits for in the operator's words.

Pure reading of a Sequencer (no side effects), so the status can be asked for at any moment. What
a logging step waits for is its kind's words (station/steps StepKind.waits_for).
"""

from __future__ import annotations

import time
from typing import Any, Protocol

from contracts.positions import POSITION_NAMES
from contracts.trace import Trace
from station.daemon.dut_run import DutRun, iso_utc
from station.daemon.safety import LampGuard
from station.daemon.states import BATCH_STATE, TERMINAL
from station.profiles import Profile
from station.steps import Step


class _WithLamp(Protocol):
    @property
    def lamp(self) -> LampGuard: ...


class BatchView(Protocol):
    """What the status reads of a batch: the Sequencer (sequencer.py) is one. A Protocol, not the
    class: the sequencer imports this module for its status()."""

    @property
    def batch_id(self) -> int: ...
    @property
    def profile(self) -> Profile: ...
    @property
    def operator(self) -> str: ...
    @property
    def trace(self) -> Trace: ...
    @property
    def hw(self) -> _WithLamp: ...
    @property
    def duts(self) -> list[DutRun]: ...
    @property
    def state(self) -> str: ...
    @property
    def step_index(self) -> int: ...
    @property
    def step(self) -> Step | None: ...
    @property
    def position(self) -> int | None: ...
    @property
    def step_clock_start(self) -> float: ...
    @property
    def prompt(self) -> dict[str, Any] | None: ...
    @property
    def error(self) -> str: ...
    @property
    def started_wall(self) -> float: ...
    @property
    def ended_wall(self) -> float | None: ...
    @property
    def ended_by(self) -> str | None: ...
    @property
    def history(self) -> list[tuple[float, str, str]]: ...

    def clock_s(self) -> float: ...


def result_note(profile: Profile) -> str | None:
    """Said on the page for a profile without analysis: its DUTs end 'done' with no coefficients,
    which a newcomer otherwise takes for a failed calibration."""
    if profile.analysis != "none":
        return None
    return (f"profile {profile.name} logs data only: it yields no calibration result "
            "(no TDB/TDSF, no SFEM); review the runs' logs and plots")


def waiting_for(seq: BatchView) -> str | None:
    """What the batch is waiting for right now, in the operator's words (None once it ended):
    a newcomer must see why nothing seems to happen."""
    if seq.state in TERMINAL:
        return None
    step = seq.step
    if seq.state in ("created", "connecting"):
        return "boards"
    if seq.state == "waiting_operator":
        return "operator"
    if seq.state in ("positioning", "moving"):
        return "fixture"
    if seq.state == "step_setup":
        return "chamber" if step is not None and step.chamber_setpoint_c is not None else "step"
    if seq.state == "logging" and step is not None:
        return step.kind.waits_for or step.require
    return {"programming": "programming", "analysing": "analysis", "step_done": "next step"}.get(seq.state)

def dut_waiting_for(seq: BatchView, d: DutRun) -> str | None:
    """The batch's waiting_for for one DUT: 'other DUTs' once it has what the step needs."""
    if not d.live or seq.state in TERMINAL:
        return None
    step = seq.step
    if seq.state == "logging" and step is not None:
        if step.kind.done(d, step, seq.step_index):
            return "other DUTs"
        if not d.at_step_position() and seq.position is not None:
            return f"plate at {step.position_name}"  # confirmed, but this DUT does not measure it yet
    return waiting_for(seq)

def dut_counts(seq: BatchView) -> dict[str, int]:
    """DUTs per end state, live ones as 'running': an aborted batch has none running."""
    counts = {"running": 0, "done": 0, "faulted": 0, "interrupted": 0}
    for d in seq.duts:
        key = "running" if d.live else d.state
        counts[key] = counts.get(key, 0) + 1
    return counts

def status(seq: BatchView) -> dict[str, Any]:
    step = seq.step
    now = time.time()
    slots = [d.status() for d in seq.duts]
    for d, st in zip(seq.duts, slots):
        st["waiting_for"] = dut_waiting_for(seq, d)
    return {
        "id": seq.batch_id,
        "profile": seq.profile.name,
        "operator": seq.operator,
        **seq.trace.fields(),
        "labels": dict(seq.trace.labels),
        "state": BATCH_STATE[seq.state],
        "seq_state": seq.state,
        "step_index": seq.step_index,
        "step": step.to_json() if step else None,
        "n_steps": len(seq.profile.steps),
        "position": seq.position,
        "position_name": POSITION_NAMES[seq.position] if seq.position is not None else None,
        "sample_time_s": seq.clock_s(),
        "step_elapsed_s": max(0.0, seq.clock_s() - seq.step_clock_start) if seq.state == "logging" else 0.0,
        "lamp_on": seq.hw.lamp.is_on,
        "lamp_state": seq.hw.lamp.state,  # 'unknown' while the relay does not answer
        "lamp_relay_error": seq.hw.lamp.relay_error,
        "lamp_on_time_s": seq.hw.lamp.on_time_s(),
        "prompt": seq.prompt,
        "error": seq.error,
        "started": seq.started_wall,
        "ended": seq.ended_wall,
        "ended_by": seq.ended_by if seq.ended_wall is not None else None,
        "ended_at": iso_utc(seq.ended_wall) if seq.ended_wall is not None else None,
        "elapsed_s": max(0.0, (seq.ended_wall if seq.ended_wall is not None else now) - seq.started_wall),
        "waiting_for": waiting_for(seq),
        "analysis": seq.profile.analysis,
        "note": result_note(seq.profile),
        "counts": dut_counts(seq),
        "transitions": [{"time": t, "from": a, "to": b} for t, a, b in seq.history],
        "slots": slots,
    }
