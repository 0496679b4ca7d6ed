"""One sequencer per batch: an explicit state machine running a profile (design 1.3, 4).

Written like labgrid's GraphStrategy: a plain table of states, each state a small coroutine method
`_state_<name>` returning the next state; every transition is checked against the table, logged and
published. The sequencer knows steps, positions and events, never bytes: the supervisor feeds the
DUT runs (samples, segments, faults) and calls `notify()`.

    created -> connecting -> step_setup -> positioning -+-> moving ----------+-> logging -> step_done
                                  ^                      +-> waiting_operator +      |          |
                                  |                      +-> (already there) -+      |          |
                                  +-------------------- next step ------------------------------+
                                                                                     last step -> analysing -> finished
    any state -> aborted (operator) | interrupted (daemon shutdown) | failed (no live DUT, fixture,
                 safety trip)

A step ends when every live DUT has logged what the step requires, or when the step's timeout
(in SAMPLE time: the boards' clock) has passed; then the DUTs that are late are faulted, the others
go on. The lamp is switched off by the LampGuard whenever the batch ends, whatever the end state.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

from drivers.base import Chamber, Fixture
from station.events import (
    BatchStateChanged,
    EventBus,
    PromptAnswered,
    PromptRaised,
    SlotStateChanged,
    StepCompleted,
    StepStarted,
)
from station.positions import POSITION_NAMES
from station.profiles import Profile, Step
from station.safety import LampGuard, LampTripped
from station.types import Identity, SampleBlock, Segment

log = logging.getLogger("station.sequencer")

# state -> states it may go to. Terminal states go nowhere.
TRANSITIONS: dict[str, tuple[str, ...]] = {
    "created": ("connecting",),
    "connecting": ("step_setup", "analysing"),  # analysing: a resumed batch whose steps were all done
    "step_setup": ("positioning",),
    "positioning": ("moving", "waiting_operator", "logging"),
    "moving": ("logging",),
    "waiting_operator": ("logging",),
    "logging": ("step_done",),
    "step_done": ("step_setup", "analysing"),
    "analysing": ("finished",),
    "finished": (),
    "failed": (),
    "aborted": (),
    "interrupted": (),
}
TERMINAL = ("finished", "failed", "aborted", "interrupted")
# Any non-terminal state may also go to failed, aborted (operator) or interrupted (daemon shutdown).
for _s, _t in list(TRANSITIONS.items()):
    if _s not in TERMINAL:
        TRANSITIONS[_s] = _t + ("failed", "aborted", "interrupted")

# Coarse batch state (design events: created, running, finished, aborted, failed) per sequencer state.
BATCH_STATE = {s: "running" for s in TRANSITIONS}
BATCH_STATE.update(created="created", waiting_operator="paused", finished="finished", failed="failed", aborted="aborted",
                   interrupted="interrupted")


class BatchFailed(Exception):
    """The batch cannot go on (no live DUT, fixture fault, lamp trip)."""


class _StopRequested(Exception):
    """stop() was called but its task cancellation was swallowed (asyncio.wait_for inside a
    Modbus client can eat a cancel on Python 3.11): the machine checks for it at every turn."""


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
    last_wall: float = field(default_factory=time.monotonic)
    n_samples: int = 0
    step_t_start: float = -math.inf  # board time when the current step began logging
    step_windows: dict[int, tuple[float, float]] = field(default_factory=dict)  # step -> board time span
    result: dict | None = None
    link_stats: dict = field(default_factory=dict)
    # Resume of an interrupted batch: the serial the stored run belongs to, the board time its
    # stored stream ended at (the live stream is joined on after it) and the offset applied.
    expected_serial: str | None = None
    resume_t: float | None = None
    time_offset_s: float = 0.0
    hold_calibrator: bool = False  # resumed: samples are stored but not calibrated until logging
    unstored_segments: list[tuple[Segment, int]] = field(default_factory=list)

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
        }


class Hardware(Protocol):
    """What the sequencer needs from the supervisor (the Station implements it)."""

    lamp: LampGuard
    fixture: Fixture | None
    chamber: Chamber | None
    fixture_timeout_s: float

    async def connect_duts(self, seq: "Sequencer") -> None: ...

    async def release_duts(self, seq: "Sequencer") -> None:
        """Stop the DUTs' streams; live DUTs end 'done' if seq.ending == 'finished', else
        'interrupted'. Called before the batch's terminal state is published."""

    def fault_dut(self, seq: "Sequencer", dut: DutRun, reason: str) -> None: ...

    async def analyse(self, seq: "Sequencer") -> None: ...


class Sequencer:
    def __init__(
        self,
        batch_id: int,
        profile: Profile,
        duts: list[DutRun],
        hw: Hardware,
        bus: EventBus,
        operator: str = "",
        poll_s: float = 0.2,
        start_step: int = 0,
    ) -> None:
        """start_step > 0 resumes an interrupted batch after its last completed step."""
        self.batch_id = batch_id
        self.profile = profile
        self.duts = duts
        self.hw = hw
        self.bus = bus
        self.operator = operator
        self.poll_s = poll_s
        self.state = "created"
        self.history: list[tuple[float, str, str]] = []  # (wall, from, to)
        if not 0 <= start_step <= len(profile.steps):
            raise ValueError(f"profile {profile.name!r} has no step {start_step}")
        self.start_step = start_step
        self.step_index = start_step - 1
        self.position: int | None = None  # where the plate is (confirmed), None = unknown
        self.step_clock_start = 0.0  # batch sample clock when the step began logging
        self.error = ""
        self.started_wall = time.time()
        self.ended_wall: float | None = None
        self.prompt: dict | None = None
        self._prompt_future: asyncio.Future | None = None
        self._prompt_counter = 0
        self._wake = asyncio.Event()
        self._stop: tuple[str, str] | None = None
        self.task: asyncio.Task | None = None
        self.done = asyncio.Event()
        self.ending: str | None = None  # the terminal state being entered (set before cleanup)

    # ------------------------------------------------------------ helpers
    @property
    def step(self) -> Step | None:
        if 0 <= self.step_index < len(self.profile.steps):
            return self.profile.steps[self.step_index]
        return None

    @property
    def live_duts(self) -> list[DutRun]:
        return [d for d in self.duts if d.live]

    def clock_s(self) -> float:
        """The batch's sample clock: the furthest any DUT's board time has advanced in this batch."""
        return max((d.elapsed_s for d in self.duts), default=0.0)

    def notify(self) -> None:
        self._wake.set()

    async def _wait(self, timeout_s: float | None = None) -> None:
        try:
            await asyncio.wait_for(self._wake.wait(), timeout_s if timeout_s is not None else self.poll_s)
        except asyncio.TimeoutError:
            pass
        self._wake.clear()

    def _transition(self, new: str, reason: str = "") -> None:
        old = self.state
        if new not in TRANSITIONS[old]:
            raise RuntimeError(f"illegal sequencer transition {old} -> {new}")
        self.state = new
        self.history.append((time.time(), old, new))
        log.info("batch %d: %s -> %s %s", self.batch_id, old, new, reason)
        self.bus.publish(BatchStateChanged(self.batch_id, state=BATCH_STATE[new], reason=reason or f"{old} -> {new}"))

    def _ensure_live(self) -> None:
        self._check_stop()
        if not self.live_duts:
            raise BatchFailed("no DUT left: every slot is faulted")

    # ------------------------------------------------------------ public control
    def start(self) -> asyncio.Task:
        self.task = asyncio.get_running_loop().create_task(self.run(), name=f"batch-{self.batch_id}")
        return self.task

    def stop(self, state: str, reason: str) -> None:
        """End the batch from outside: 'aborted' (operator), 'interrupted' (shutdown), 'failed' (trip)."""
        if self.state in TERMINAL or self._stop is not None:
            return
        self._stop = (state, reason)
        if self.task is not None and not self.task.done():
            self.task.cancel()

    def answer_prompt(self, prompt_id: int, answer: str = "done") -> None:
        if self.prompt is None or self._prompt_future is None:
            raise ValueError("no prompt is open for this batch")
        if int(prompt_id) != self.prompt["id"]:
            raise ValueError(f"prompt {prompt_id} is not the open prompt ({self.prompt['id']})")
        if answer not in ("done", "abort"):
            raise ValueError("answer must be 'done' or 'abort'")
        self.bus.publish(PromptAnswered(self.batch_id, prompt_id=int(prompt_id), answer=answer))
        if answer == "abort":
            self.stop("aborted", "operator aborted at prompt")
            return
        if not self._prompt_future.done():
            self._prompt_future.set_result(answer)

    # ------------------------------------------------------------ the machine
    async def run(self) -> str:
        try:
            while self.state not in TERMINAL:
                self._check_stop()
                handler = getattr(self, f"_state_{self.state}")
                nxt = await handler()
                self._check_stop()
                if nxt in TERMINAL:
                    await self._end(nxt, "")  # DUTs released and lamp off before the batch says so
                    break
                self._transition(nxt)
        except (asyncio.CancelledError, _StopRequested):
            task = asyncio.current_task()
            if task is not None:
                while task.cancelling():  # handled here: later timeouts in cleanup must work normally
                    task.uncancel()
            state, reason = self._stop or ("aborted", "cancelled")
            self.error = reason
            await self._end(state, reason)
        except (BatchFailed, LampTripped) as exc:
            self.error = str(exc)
            await self._end("failed", str(exc))
        except Exception as exc:  # a bug must still end the batch safely
            log.exception("batch %d crashed", self.batch_id)
            self.error = f"internal error: {exc!r}"
            await self._end("failed", self.error)
        finally:
            self.ended_wall = time.time()
            self.done.set()
        return self.state

    async def _end(self, state: str, reason: str) -> None:
        if self.state in TERMINAL:
            return
        await self._cleanup(state)
        self._transition(state, reason)

    def _check_stop(self) -> None:
        if self._stop is not None:
            raise _StopRequested(self._stop[1])

    async def _cleanup(self, final_state: str) -> None:
        """Lamp off, then release the DUTs (done or interrupted by `ending`); before the batch's
        own end is published, so a client that sees the batch ended sees its DUTs ended too."""
        self.ending = final_state
        self.prompt = None
        # The lamp goes off on ANY batch end (design 3.3), before anything else can fail.
        await asyncio.shield(self.hw.lamp.off(f"batch {self.batch_id} {final_state}"))
        try:
            await asyncio.shield(self.hw.release_duts(self))
        except Exception:
            log.exception("releasing DUTs of batch %d", self.batch_id)

    # ------------------------------------------------------------ states
    async def _state_created(self) -> str:
        return "connecting"

    async def _state_connecting(self) -> str:
        await self.hw.connect_duts(self)
        self._ensure_live()
        return "step_setup" if self.step_index + 1 < len(self.profile.steps) else "analysing"

    async def _state_step_setup(self) -> str:
        self.step_index += 1
        step = self.step
        assert step is not None
        self.bus.publish(
            StepStarted(
                self.batch_id,
                step_index=self.step_index,
                step_name=step.name,
                position=step.position,
                lamp_on=step.lamp,
                chamber_setpoint_c=step.chamber_setpoint_c,
            )
        )
        if step.chamber_setpoint_c is not None and self.hw.chamber is not None:
            await self.hw.chamber.set_setpoint_c(step.chamber_setpoint_c)
        return "positioning"

    async def _state_positioning(self) -> str:
        step = self.step
        assert step is not None
        if self.position == step.position:
            return "logging"
        if self.hw.fixture is not None:
            return "moving"
        return "waiting_operator"

    async def _state_moving(self) -> str:
        step = self.step
        assert step is not None and self.hw.fixture is not None
        fx = self.hw.fixture
        await fx.move_to(step.position)
        deadline = time.monotonic() + self.hw.fixture_timeout_s
        while True:
            if await fx.position() == step.position and not await fx.moving():
                break
            if time.monotonic() > deadline:
                raise BatchFailed(
                    f"fixture did not reach position {step.position_name} within {self.hw.fixture_timeout_s:g} s"
                )
            await asyncio.sleep(0.05)
        self.position = step.position
        return "logging"

    async def _state_waiting_operator(self) -> str:
        step = self.step
        assert step is not None
        self._prompt_counter += 1
        pid = self.batch_id * 1000 + self._prompt_counter
        text = f"turn the plate to {step.position_name}"
        self.prompt = {"id": pid, "text": text, "position": step.position, "position_name": step.position_name,
                       "step_index": self.step_index}
        self._prompt_future = asyncio.get_running_loop().create_future()
        self.bus.publish(PromptRaised(self.batch_id, prompt_id=pid, text=text, position=step.position))
        try:
            await self._prompt_future
        finally:
            self.prompt = None
            self._prompt_future = None
        self.position = step.position
        return "logging"

    async def _state_logging(self) -> str:
        step = self.step
        assert step is not None
        # Lamp per step, once the plate is where the step wants it.
        await self.hw.lamp.set_lamp(step.lamp, f"step {self.step_index} {step.name}")
        self.step_clock_start = self.clock_s()
        resumed_step = self.step_index == self.start_step and self.start_step > 0
        for d in self.duts:
            d.step_t_start = d.last_t if d.last_t is not None else -math.inf
            if resumed_step and step.require == "segment":
                # The step was interrupted: a segment it logged (at its position) before the crash counts.
                d.step_t_start = -math.inf
        while True:
            self._ensure_live()
            pending = [d for d in self.live_duts if not self.dut_step_done(d, step)]
            if not pending:
                break
            # Each DUT's timeout runs on its own board clock: a link that delivers late (a busy
            # CAN adapter) is not judged by the fastest board's clock. A silent board is the
            # stall watchdog's (wall time) to fault.
            late = [(d, e) for d in pending if (e := self._step_elapsed_s(d)) >= step.timeout_s]
            if late:
                need = {"segment": "a segment", "static": f"{step.dwell_s:g} s static", "none": "its dwell"}[step.require]
                for d, elapsed in late:
                    self.hw.fault_dut(
                        self, d, f"step '{step.name}' timed out after {elapsed:.0f} s sample time without {need}"
                    )
                continue
            await self._wait()
        for d in self.duts:
            if d.last_t is not None:
                d.step_windows[self.step_index] = (d.step_t_start, d.last_t)
        self.bus.publish(StepCompleted(
            self.batch_id, step_index=self.step_index,
            windows={d.slot: d.step_windows[self.step_index] for d in self.live_duts
                     if self.step_index in d.step_windows},
        ))
        return "step_done"

    def _step_elapsed_s(self, d: DutRun) -> float:
        """Sample time this DUT has spent in the current step (its own board clock)."""
        if d.last_t is not None and math.isfinite(d.step_t_start):
            return d.last_t - d.step_t_start
        return self.clock_s() - self.step_clock_start  # no sample before the step (or resumed step)

    def dut_step_done(self, d: DutRun, step: Step) -> bool:
        if step.require == "segment":
            return any(
                st == self.step_index and seg.position == step.position and seg.t_end_s > d.step_t_start
                for seg, st in zip(d.segments, d.segment_steps)
            )
        if d.last_t is None or not math.isfinite(d.step_t_start):
            return False
        need = step.dwell_s + (step.settle_s if step.require == "static" else 0.0)
        return d.last_t - d.step_t_start >= need

    async def _state_step_done(self) -> str:
        if self.step_index + 1 < len(self.profile.steps):
            return "step_setup"
        return "analysing"

    async def _state_analysing(self) -> str:
        # Lamp off before the (possibly long) fits: the heat is no longer needed.
        await self.hw.lamp.off("profile complete")
        await self.hw.analyse(self)
        return "finished"

    # ------------------------------------------------------------ reporting
    def status(self) -> dict:
        step = self.step
        return {
            "id": self.batch_id,
            "profile": self.profile.name,
            "operator": self.operator,
            "state": BATCH_STATE[self.state],
            "seq_state": self.state,
            "step_index": self.step_index,
            "step": step.to_json() if step else None,
            "n_steps": len(self.profile.steps),
            "position": self.position,
            "position_name": POSITION_NAMES[self.position] if self.position is not None else None,
            "sample_time_s": self.clock_s(),
            "step_elapsed_s": max(0.0, self.clock_s() - self.step_clock_start) if self.state == "logging" else 0.0,
            "lamp_on": self.hw.lamp.is_on,
            "lamp_on_time_s": self.hw.lamp.on_time_s(),
            "prompt": self.prompt,
            "error": self.error,
            "started": self.started_wall,
            "ended": self.ended_wall,
            "transitions": [{"time": t, "from": a, "to": b} for t, a, b in self.history],
            "slots": [d.status() for d in self.duts],
        }


def annotate_segment(seg: Segment, position: int | None) -> Segment:
    return replace(seg, position=position)


def publish_slot(bus: EventBus, batch_id: int, d: DutRun) -> None:
    bus.publish(SlotStateChanged(batch_id, slot=d.slot, serial=d.serial, state=d.state, fault_reason=d.fault_reason))
