"""How far a batch has come and how long it still needs: what GET /api/batches/{id} adds to the
sequencer's own status (decision summary, sorting list for the trays, the step list, progress and
time left).

Time left is an estimate from the plant's own behaviour in this batch, made by each step's kind
(station/steps: StepKind.expected_s, left_s): the calibrator's state and the temperature trend for
segment steps, dwell for static ones, the heating rate the lamp showed in this batch for a
verification (heat) step, the completed steps of the same kind for those to come, and the wall time
programming and analysis take. It can never break the status.

What the operator sees is a countdown, not the raw estimate: the raw figure jumps whenever a step
ends early or a segment takes longer (0:24 -> 0:20 -> 0:11 -> 0:19 on the old page). `Countdown`
only ever moves down, at one second per second while the estimate agrees, slower when the estimate
grew (so it does not reach 0:00 while work remains), faster (at most 4x) when it shrank.
"""

from __future__ import annotations

import math
import time
from typing import Any, Protocol

from station.daemon.dut_run import DutRun
from station.daemon.sequencer import Sequencer
from station.daemon.states import TERMINAL
from station.decisions.verdicts import summarize
from station.steps import Estimates

ANALYSIS_WALL_S = 3.0  # wall seconds of the end-of-batch analysis (thermal fit, verdicts, storage)
COUNTDOWN_MAX_RATE = 4.0  # the countdown may run at most this many seconds per second


class _Timing(Protocol):
    @property
    def speed(self) -> float: ...


class _Config(Protocol):
    @property
    def timing(self) -> _Timing: ...


class StationView(Protocol):
    """What the estimate reads of the station (the supervisor's Station): its config's timing.speed."""

    @property
    def config(self) -> _Config: ...


def _temp_at(d: DutRun, t: float) -> float | None:
    """The DUT's temperature at board time t (the nearest stored sample), None outside its data."""
    for b in reversed(d.blocks):
        if len(b) and b.time_s[0] <= t:
            i = min(len(b) - 1, int((b.time_s <= t).sum()))
            return float(b.temp_c[i])
    return None


def heating_rate_c_per_s(seq: Sequencer) -> float | None:
    """How fast the lamp heated the DUTs in this batch: the median over DUTs of the temperature
    rise per sample second across the completed lamp-on steps. None until one was seen.

    Computed once per step (it depends only on the completed steps' windows): looking the
    temperatures up walks the DUTs' stored blocks, which a status poll must not do each time."""
    key = max(0, seq.step_index)
    cached: tuple[int, float | None] | None = seq.__dict__.get("_heating_rate")
    if cached is not None and cached[0] == key:
        return cached[1]
    rate = _heating_rate(seq)
    seq.__dict__["_heating_rate"] = (key, rate)
    return rate


def _heating_rate(seq: Sequencer) -> float | None:
    rates: list[float] = []
    for i, s in enumerate(seq.profile.steps[:max(0, seq.step_index)]):
        if not s.lamp:
            continue
        for d in seq.duts:
            a, b = d.step_windows.get(i, (math.nan, math.nan))
            if not (math.isfinite(a) and math.isfinite(b)) or b - a < 10.0:
                continue
            ta, tb = _temp_at(d, a), _temp_at(d, b)
            if ta is not None and tb is not None and tb > ta:
                rates.append((tb - ta) / (b - a))
    return float(sorted(rates)[len(rates) // 2]) if rates else None


def estimates(seq: Sequencer) -> Estimates:
    """What the batch has shown so far, for the step kinds' estimates."""
    return Estimates(seq.profile.steps, max(0, seq.step_index), seq.duts, heating_rate_c_per_s(seq))


def expected_s(seq: Sequencer) -> list[tuple[float, float]]:
    """Per profile step its expected duration as (sample seconds, wall seconds): the wall part is
    what runs at wall speed whatever the plant's speed (programming)."""
    est = estimates(seq)
    return [s.kind.expected_s(s, i, est) for i, s in enumerate(seq.profile.steps)]


def _current_step_left_s(seq: Sequencer, expect: tuple[float, float]) -> tuple[float, float]:
    """(sample, wall) seconds left in the running step."""
    step = seq.step
    if seq.state == "programming":
        started = next((t for t, _, to in reversed(seq.history) if to == "programming"), time.time())
        return 0.0, max(0.0, expect[1] - (time.time() - started))
    if seq.state != "logging" or step is None:
        return expect  # not started yet: positioning, a prompt, the chamber
    elapsed = max(0.0, seq.clock_s() - seq.step_clock_start)
    kind, est = step.kind, estimates(seq)
    needs = []
    for d in seq.live_duts:
        if kind.done(d, step, seq.step_index):
            continue
        n = kind.left_s(step, d, elapsed, expect[0], est)
        if n is not None:
            needs.append(max(0.0, n))
    return min(max(needs, default=0.0), max(0.0, step.timeout_s - elapsed)), 0.0


def time_left(station: StationView, seq: Sequencer) -> dict[str, Any]:
    """Estimated sample and wall seconds left in the step and the batch (raw), with the batch's
    countdown (`batch_wall_s`, see Countdown) and the expected wall duration of every step."""
    speed = float(station.config.timing.speed) or 1.0
    if seq.state in TERMINAL:
        return {"step_s": 0.0, "batch_s": 0.0, "step_wall_s": 0.0, "batch_wall_s": 0.0, "raw_batch_wall_s": 0.0}
    steps = seq.profile.steps
    expect = expected_s(seq)
    walls = [a / speed + b for a, b in expect]
    if seq.step is None and seq.state != "analysing":  # connecting
        raw_wall = sum(walls) + ANALYSIS_WALL_S
        step_s: float | None = None
        step_wall: float | None = None
        batch_s = sum(a for a, _ in expect)
    else:
        if seq.state == "analysing":
            step_s, step_wall_extra, rest = 0.0, ANALYSIS_WALL_S, list[tuple[float, float]]()
        else:
            step_s, step_wall_extra = _current_step_left_s(seq, expect[seq.step_index])
            rest = expect[seq.step_index + 1:]
        step_wall = step_s / speed + step_wall_extra
        raw_wall = step_wall + sum(a / speed + b for a, b in rest) + (0.0 if seq.state == "analysing" else ANALYSIS_WALL_S)
        batch_s = step_s + sum(a for a, _ in rest)
    shown = Countdown.of(seq).update(raw_wall)
    return {"step_s": step_s, "batch_s": batch_s, "step_wall_s": step_wall, "batch_wall_s": shown,
            "raw_batch_wall_s": raw_wall, "estimated_at": time.time(), "expected_step_wall_s": walls,
            "n_steps": len(steps)}


class Countdown:
    """The batch's time left as the operator sees it: never up, steady.

    The countdown s follows ds/dt = -s / r(t), r the raw estimate, which falls at one second per
    second while the work goes as estimated. Between two looks dt apart, with r the new raw
    figure, that gives s_new = s_old * r / (r + dt): equal to the raw estimate when it agreed
    (one second per second), slower when the estimate grew (it nears 0 only as the work does,
    never 0:00 while work remains), faster when it shrank, but never faster than
    COUNTDOWN_MAX_RATE seconds per second (a step that ended early is caught up smoothly)."""

    def __init__(self) -> None:
        self.shown_s: float | None = None
        self.at: float = 0.0

    @classmethod
    def of(cls, seq: Sequencer) -> Countdown:
        c: Countdown | None = seq.__dict__.get("_countdown")
        if c is None:
            c = seq.__dict__["_countdown"] = cls()
        return c

    def update(self, raw_s: float, now: float | None = None) -> float:
        now = time.monotonic() if now is None else now
        raw_s = max(0.0, float(raw_s))
        if self.shown_s is None:
            self.shown_s, self.at = raw_s, now
            return raw_s
        dt = max(0.0, now - self.at)
        self.at = now
        if dt == 0.0:
            return self.shown_s
        followed = self.shown_s * raw_s / (raw_s + dt)
        self.shown_s = max(0.0, followed, self.shown_s - COUNTDOWN_MAX_RATE * dt)
        return self.shown_s


def step_rows(seq: Sequencer, expected_wall_s: list[float] | None = None) -> list[dict[str, Any]]:
    """The batch's step list as the page shows it: each profile step and the analysis, with its
    state (pending, running, done, skipped, failed) and wall duration (so far, when running),
    from the sequencer's own transitions."""
    steps = seq.profile.steps
    starts: dict[int, float] = {}
    ends: dict[int, float] = {}
    idx = seq.start_step - 1
    for t, _old, new in seq.history:
        if new == "step_setup":
            if idx >= 0:
                ends.setdefault(idx, t)
            idx += 1
            starts[idx] = t
        elif new == "analysing":
            if idx >= 0:
                ends.setdefault(idx, t)
            idx = len(steps)
            starts[idx] = t
        elif new in TERMINAL and idx >= 0:
            ends.setdefault(idx, t)
    ended = seq.state in TERMINAL
    now = time.time()
    rows = []
    names = [s.name for s in steps] + ["analysis"]
    for i, name in enumerate(names):
        s = steps[i] if i < len(steps) else None
        if i < seq.start_step:
            state = "done"  # completed before the batch was resumed
        elif i in ends and (i < idx or (ended and seq.state == "finished")):
            state = "done"
        elif i == idx and not ended:
            state = "running"
        elif i == idx and ended:
            state = "failed"
        else:
            state = "skipped" if ended else "pending"
        dur = None
        if i in starts:
            dur = (ends.get(i, now) if state != "pending" else now) - starts[i]
        exp = None
        if expected_wall_s is not None:
            exp = expected_wall_s[i] if i < len(expected_wall_s) else ANALYSIS_WALL_S
        rows.append({"index": i, "name": name, "kind": s.kind.row_kind if s else "analysis",
                     "position_name": s.position_name if s else None, "state": state,
                     "duration_s": None if dur is None else round(max(0.0, dur), 3),
                     "expected_s": None if exp is None else round(exp, 3)})
    return rows


def batch_extras(station: StationView, seq: Sequencer) -> dict[str, Any]:
    """Decision summary, sorting list, time left, step list and progress for GET /api/batches/{id}."""
    verdicts = [getattr(d, "verdict", None) for d in seq.duts]
    sorting = [
        {"slot": d.slot, "serial": d.serial, "verdict": v.get("verdict"), "grade": v.get("grade"), "tray": v.get("tray"),
         "reason": v.get("reason"), "attempt": v.get("attempt")}
        for d, v in zip(seq.duts, verdicts) if v
    ]
    try:
        left = time_left(station, seq)
    except Exception as exc:  # noqa: BLE001 - an estimate must never break the status
        left = {"error": f"{type(exc).__name__}: {exc}"}
    try:
        rows = step_rows(seq, left.get("expected_step_wall_s"))
    except Exception:  # noqa: BLE001 - the list is a view, never worth a broken status
        rows = []
    progress = None
    if seq.state in TERMINAL:
        progress = 1.0 if seq.state == "finished" else None
    elif isinstance(left.get("batch_wall_s"), float):
        elapsed = max(0.0, time.time() - seq.started_wall)
        progress = elapsed / (elapsed + left["batch_wall_s"]) if elapsed + left["batch_wall_s"] > 0 else 0.0
        seq.__dict__["_progress"] = progress = max(progress, seq.__dict__.get("_progress", 0.0))
    left.pop("expected_step_wall_s", None)
    return {"decision": summarize(verdicts), "sorting": sorting, "time_left": left, "steps": rows,
            "progress": progress}
