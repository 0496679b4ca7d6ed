"""One sequencer per batch: an explicit state machine running a profile (design 1.3, 4).

Written like labgrid's GraphStrategy: a plain table of states, each state a small coroutine method
`_state_<name>` returning the next state; every transition is checked against the table, logged and
published. The sequencer knows steps, positions and events, never bytes: the pumps (intake.py) feed
the DUT runs (samples, segments, faults) and call `notify()`.

    created -> connecting -> step_setup -> positioning -+-> moving ----------+-> logging -> step_done
                                  ^                      +-> waiting_operator +      |          |
                                  |                      +-> (already there) -+      |          |
                                  +-------------------- next step ------------------------------+
                                                                                     last step -> analysing -> finished
    any state -> aborted (operator) | interrupted (daemon shutdown) | failed (no live DUT, fixture,
                 safety trip)

A step ends when every live DUT has logged what the step requires (its kind says: station/steps),
or when the step's timeout (in SAMPLE time: the boards' clock) has passed; then the DUTs that are
late are faulted, the others go on. The plate's moves and prompts are positioning.py's. The lamp is
switched off by the LampGuard whenever the batch ends, whatever the end state.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from typing import Any, Protocol

from drivers.base import Chamber, Fixture
from contracts.events import BatchStateChanged, EventBus, PromptAnswered, StepCompleted, StepStarted
from contracts.trace import Trace
from station.daemon import batch_view, plate_watch
from station.daemon.board_selfcal import BoardCalibrators
from station.daemon.dut_run import DutRun, wall_text
from station.daemon.positioning import BatchFailed, Plate, device_call
from station.daemon.intake_monitor import ATTRIBUTE_BEHIND_S
from station.daemon.states import BATCH_STATE, TERMINAL, TRANSITIONS
from station.profiles import Profile
from station.steps import Step
from station.daemon.safety import LampGuard, LampTripped

__all__ = ["BatchFailed", "Hardware", "STATION_CLOCK_FACTOR", "Sequencer"]

log = logging.getLogger(__name__)

# A step's timeout runs on each DUT's own board clock (a link that delivers late is not judged by
# the fastest board's clock), but never beyond this multiple of it on the station's clock (the
# batch's sample clock since Done): a board clock that slowed or stopped while its seq ran on cannot
# hold a step, and the lamp, for ever. 3: a link delivering at a third of the others' pace (a busy
# CAN adapter, tests/test_sequencer.py) still logs its segment; a reset or a clock jump ends the
# run at once (drivers StreamBreak), so this only bounds a clock that runs slow.
STATION_CLOCK_FACTOR = 3.0


class _StopRequested(Exception):
    """stop() was called but its task cancellation was swallowed (asyncio.wait_for inside a
    Modbus client can eat a cancel on Python 3.11): the machine checks for it at every turn."""


class Hardware(Protocol):
    """What the sequencer needs of the station's hardware and slots (rig.Rig implements it)."""

    lamp: LampGuard
    fixture: Fixture | None
    chamber: Chamber | None
    fixture_timeout_s: float
    plate_again_after_s: float  # sample seconds after Done before a plate not yet there is asked for again
    speed: float  # plant seconds per wall second (1 on real hardware; a compressed-time simulation more)

    async def connect_duts(self, seq: "Sequencer") -> None: ...

    async def release_duts(self, seq: "Sequencer") -> None:
        """Stop the DUTs' streams; live DUTs end 'done' if seq.ending == 'finished', else
        'interrupted'. Called before the batch's terminal state is published."""

    def fault_dut(self, seq: "Sequencer", dut: DutRun, reason: str) -> None: ...

    async def analyse(self, seq: "Sequencer") -> None: ...

    async def program_duts(self, seq: "Sequencer") -> None:
        """Program and verify, part 1: analyse, then write/read back/compensation on per DUT;
        a DUT whose programming fails is faulted alone (fault_dut)."""


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
        trace: Trace | None = None,
    ) -> None:
        """start_step > 0 resumes an interrupted batch after its last completed step."""
        self.batch_id = batch_id
        self.profile = profile
        self.duts = duts
        self.hw = hw
        self.bus = bus
        self.operator = operator
        self.trace = trace or Trace()  # work order, part, lot, label serials (contracts/trace.py)
        self.poll_s = poll_s
        self.state = "created"
        self._running = False  # run() has begun (see stop())
        self.history: list[tuple[float, str, str]] = []  # (wall, from, to)
        if not 0 <= start_step <= len(profile.steps):
            raise ValueError(f"profile {profile.name!r} has no step {start_step}")
        self.start_step = start_step
        self.step_index = start_step - 1
        self.plate = Plate(batch_id, bus, hw)  # where the plate is, the operator's prompt
        self.step_clock_start = 0.0  # batch sample clock when the step began logging
        self.error = ""
        self.started_wall = time.time()
        self.ended_wall: float | None = None
        self._wake = asyncio.Event()
        self._stop: tuple[str, str] | None = None
        self.task: asyncio.Task[str] | None = None
        self.done = asyncio.Event()
        self.ending: str | None = None  # the terminal state being entered (set before cleanup)
        # Who ended the batch (a token's name for an operator's abort, "station" for an end it
        # reached by itself, "daemon" for a shutdown): the page says "aborted by Ana at 14:02".
        self.ended_by: str | None = None
        for d in duts:  # a resumed batch: the steps before start_step were completed before the crash
            d.steps_done = max(d.steps_done, start_step)
        # the first step's plate is where the first samples belong, from the first sample on (not
        # from when the step is set up after every board connected: the labels are the samples')
        self._placement_step = -1
        self._set_up_placement(start_step)
        self.storage_error: str | None = None  # set by release_duts: the batch's data is not stored
        # profile option board_selfcal: the boards' own calibrators on before the thermal steps, read at their end
        self.board_calibrators = BoardCalibrators(profile.board_selfcal, resumed_at_step=start_step)

    # ------------------------------------------------------------ helpers
    def _set_up_placement(self, index: int) -> None:
        """Tell every DUT where its samples belong from now on (before anything moves the plate):
        step `index`'s position, the one before it and the next (station/daemon/intake.place)."""
        steps = self.profile.steps
        if not 0 <= index < len(steps) or index == self._placement_step:
            return
        self._placement_step = index
        prev = steps[index - 1].position if index > 0 else None
        nxt = steps[index + 1].position if index + 1 < len(steps) else None
        for d in self.duts:
            d.begin_step(steps[index].position, prev, nxt)

    @property
    def position(self) -> int | None:
        """Where the plate is (confirmed); None: unknown (moving, being turned, before the first move)."""
        return self.plate.position

    @property
    def prompt(self) -> dict[str, Any] | None:
        """The operator's open prompt (positioning.Plate)."""
        return self.plate.prompt

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
        # The reason is the batch's error as stored and shown: a normal transition has none (it
        # once stored "analysing -> finished" as the error of a batch that finished fine).
        self.bus.publish(BatchStateChanged(self.batch_id, state=BATCH_STATE[new], reason=reason))

    def _ensure_live(self) -> None:
        self._check_stop()
        if not self.live_duts:
            raise BatchFailed("no DUT left: every slot is faulted")

    # ------------------------------------------------------------ public control
    def start(self) -> asyncio.Task[str]:
        self.task = asyncio.get_running_loop().create_task(self.run(), name=f"batch-{self.batch_id}")
        return self.task

    def stop(self, state: str, reason: str, by: str | None = None) -> None:
        """End the batch from outside: 'aborted' (operator), 'interrupted' (shutdown), 'failed' (trip).

        by: who asked (the token's name for an operator; None: the station itself)."""
        if self.state in TERMINAL or self._stop is not None or self.ending is not None:
            return  # already ending: its cleanup decides the end state (see _cleanup)
        self._stop = (state, reason)
        self.ended_by = by or ("daemon" if state == "interrupted" else "station")
        if self.task is not None and not self.task.done() and self._running:
            # (a task not yet running is left alone: cancelled before its first step, its body and
            # its cleanup would never run and the batch would never end; it sees _stop at once)
            if asyncio.current_task() is self.task:
                # asked from inside the batch's own task (a lamp trip raised by its own lamp command):
                # a cancel of the running task would stay pending past the handler's uncancel() and
                # hit its cleanup; cancel it once it is suspended, like any stop from outside
                asyncio.get_running_loop().call_soon(self._cancel_if_running)
            else:
                self.task.cancel()

    def _cancel_if_running(self) -> None:
        if self.task is not None and not self.task.done() and self.ending is None:
            self.task.cancel()

    def answer_prompt(self, prompt_id: int, answer: str = "done", by: str | None = None, note: str = "") -> None:
        future = self.plate.future
        if self.prompt is None or future is None:
            raise ValueError("no prompt is open for this batch")
        if int(prompt_id) != self.prompt["id"]:
            raise ValueError(f"prompt {prompt_id} is not the open prompt ({self.prompt['id']})")
        if answer not in ("done", "abort", "cannot"):
            raise ValueError("answer must be 'done', 'cannot' or 'abort'")
        if answer == "cannot" and not note.strip():
            raise ValueError("say why it cannot be done: the words are recorded with the DUTs it ends")
        self.bus.publish(PromptAnswered(self.batch_id, prompt_id=int(prompt_id), answer=answer))
        who = by or "operator"
        if answer == "abort":
            self.stop("aborted", f"aborted by {who} at the prompt at {wall_text(time.time())}", by=who)
            return
        if answer == "cannot":
            # The prompt concerns the plate, so every DUT on it: each ends as error with the
            # operator's own words (their verdict says why), then the batch ends failed.
            reason = f"{who} could not {self.prompt['text']}: {note.strip()}"
            for d in self.live_duts:
                self.hw.fault_dut(self, d, reason)
            self.stop("failed", reason, by=who)
            return
        if not future.done():
            future.set_result(answer)
        self.notify()

    # ------------------------------------------------------------ the machine
    async def run(self) -> str:
        self._running = True
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
            if self.ended_by is None:
                self.ended_by = "station"
            self.done.set()
        return self.state

    async def _end(self, state: str, reason: str) -> None:
        if self.state in TERMINAL:
            return
        state = await self._cleanup(state)
        if state == "failed" and not reason:
            reason = self.error or ""
        if state == "finished" and self.storage_error is not None:
            state, reason = "failed", f"results not stored: {self.storage_error}"
            self.error = reason
        self._transition(state, reason)

    def _check_stop(self) -> None:
        if self._stop is not None:
            raise _StopRequested(self._stop[1])

    async def _cleanup(self, final_state: str) -> str:
        """Lamp off, then release the DUTs (done or interrupted by `ending`); before the batch's
        own end is published, so a client that sees the batch ended sees its DUTs ended too.
        Returns the end state: a batch whose lamp the relay cannot confirm off has not finished."""
        self.ending = final_state
        self.plate.prompt = None
        # The lamp goes off on ANY batch end (design 3.3), before anything else can fail.
        off = await asyncio.shield(self.hw.lamp.off(f"batch {self.batch_id} {final_state}"))
        if off is False and final_state == "finished":
            final_state = self.ending = "failed"
            self.error = f"lamp relay did not take the OFF command at the end, lamp state unknown: " \
                         f"{getattr(self.hw.lamp, 'relay_error', None) or 'no answer'}"
        try:
            await asyncio.shield(self.hw.release_duts(self))
        except Exception:
            log.exception("releasing DUTs of batch %d", self.batch_id)
        return final_state

    # ------------------------------------------------------------ states
    async def _state_created(self) -> str:
        return "connecting"

    async def _state_connecting(self) -> str:
        await self.hw.connect_duts(self)
        self._ensure_live()
        await self.board_calibrators.start(self.hw, self.duts)
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
        self._set_up_placement(self.step_index)
        if step.kind.machine_state == "programming":
            return "programming"
        if step.chamber_setpoint_c is not None and self.hw.chamber is not None:
            async with device_call("thermal chamber", "its power, Modbus address (unit 4) and cable/network"):
                await self.hw.chamber.set_setpoint_c(step.chamber_setpoint_c)
        return "positioning"

    async def _state_programming(self) -> str:
        # No heat while writing: the lamp is off (the analysis and the writes take wall time).
        await self.hw.lamp.off(f"step {self.step_index} program")
        await self.board_calibrators.finish(self.hw, self.duts)  # the thermal steps are over
        await self.hw.program_duts(self)
        await self.board_calibrators.compare(self.duts)
        self._ensure_live()
        self._complete_step()
        return "step_done"

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
        assert step is not None
        await self.plate.move(step)
        return "logging"

    async def _state_waiting_operator(self) -> str:
        step = self.step
        assert step is not None
        await self.plate.ask(step, self.step_index, self.duts)
        return "logging"

    async def _state_logging(self) -> str:
        step = self.step
        assert step is not None
        # Lamp per step, once the plate is where the step wants it.
        async with device_call("lamp relay", "its power, Modbus address (unit 1) and cable/network"):
            await self.hw.lamp.set_lamp(step.lamp, f"step {self.step_index} {step.name}")
        self.step_clock_start = self.clock_s()
        self.plate.check_wall = time.monotonic()
        resumed_step = self.step_index == self.start_step and self.start_step > 0
        for d in self.duts:
            d.step_t_start = d.last_t if d.last_t is not None else -math.inf
            d.logging_block = len(d.blocks)
            if resumed_step and step.kind.counts_before_crash:
                # The step was interrupted: a segment it logged (at its position) before the crash counts.
                d.step_t_start = -math.inf
            # A step's requirement counts from its samples (placed after the step's setup), except
            # where the station itself changes what they measure at this moment: the batch's
            # first step (the operator's Done says the plate is loaded), a lamp switched, a heat.
            prev = self.profile.steps[self.step_index - 1] if self.step_index > self.start_step else None
            d.begin_logging(gated=step.kind.gated or prev is None or prev.lamp != step.lamp)
        try:
            while True:
                self._ensure_live()
                pending = [d for d in self.live_duts if not self.dut_step_done(d, step)]
                if not pending:
                    break
                self.plate.watch(step, self.step_index, pending, self.duts)
                if self._fault_late(step, pending):
                    continue
                await self._wait()
        finally:
            self.plate.close_prompt("step ended")
        self._complete_step()
        return "step_done"

    def _fault_late(self, step: Step, pending: list[DutRun]) -> bool:
        """Fault the DUTs past the step's timeout, each with why: a plate that never arrived at
        the position (its clock runs from Done), or a requirement not met (from its arrival)."""
        # Each DUT's timeout runs on its own board clock: a link that delivers late (a busy
        # CAN adapter) is not judged by the fastest board's clock. A silent board is the
        # stall watchdog's (wall time) to fault.
        # The station's clock bounds them all: a board whose own clock slowed or stopped while
        # its seq ran on would otherwise hold the step (and the plate's lamp) for ever.
        # A link the station runs behind (its own backlog: intake_monitor.py) has samples waiting
        # that may hold the step's requirement: it is judged once they are in, within the bound.
        station_s = self._station_step_s()
        late = [(d, e) for d in pending if ((e := d.step_elapsed_s(station_s)) >= step.timeout_s
                                            and d.link_behind_s <= ATTRIBUTE_BEHIND_S)
                or station_s >= step.timeout_s * STATION_CLOCK_FACTOR]
        if not late:
            return False
        others_arrived = any(d.arrived_t is not None for d in self.live_duts if all(d is not x for x, _ in late))
        for d, elapsed in late:
            self.hw.fault_dut(self, d, plate_watch.timed_out_reason(step, d, elapsed, station_s, others_arrived,
                                                                     self.plate.after()))
        return True

    def _complete_step(self) -> None:
        """Record each DUT's sample-time window of this step (from where the step's kind says it
        starts to its latest sample), count the step for the live DUTs and publish StepCompleted
        with their windows."""
        step = self.step
        assert step is not None
        for d in self.duts:
            if d.last_t is not None:
                d.step_windows[self.step_index] = (step.kind.window_start(d), d.last_t)
        for d in self.live_duts:
            d.steps_done += 1
        self.bus.publish(StepCompleted(
            self.batch_id, step_index=self.step_index,
            windows={d.slot: d.step_windows[self.step_index] for d in self.live_duts
                     if self.step_index in d.step_windows},
        ))

    def _station_step_s(self) -> float:
        """The station's clock in the current step: the batch's sample clock since Done."""
        return self.clock_s() - self.step_clock_start

    def dut_step_done(self, d: DutRun, step: Step) -> bool:
        """Has this DUT logged what the step requires (the step's kind: station/steps)?"""
        return step.kind.done(d, step, self.step_index)

    async def _state_step_done(self) -> str:
        if self.step_index + 1 < len(self.profile.steps):
            return "step_setup"
        return "analysing"

    async def _state_analysing(self) -> str:
        # The profile's steps are over: a sample from here on is placed at no step's position
        # (design 4), so the run's stored log holds the same placed samples as the analysis'
        # snapshot, and `station sfem` on the exported log gives the station's own SFEM.
        for d in self.duts:
            d.step_position = d.prev_position = d.next_position = None
        # Lamp off before the (possibly long) fits: the heat is no longer needed.
        await self.hw.lamp.off("profile complete")
        await self.board_calibrators.finish(self.hw, self.duts)  # the thermal steps are over
        await self.hw.analyse(self)
        await self.board_calibrators.compare(self.duts)
        return "finished"

    # ------------------------------------------------------------ reporting (batch_view.py)
    def waiting_for(self) -> str | None:
        return batch_view.waiting_for(self)

    def dut_waiting_for(self, d: DutRun) -> str | None:
        return batch_view.dut_waiting_for(self, d)

    def dut_counts(self) -> dict[str, int]:
        return batch_view.dut_counts(self)

    def status(self) -> dict[str, Any]:
        return batch_view.status(self)
