"""Where the plate is and how it gets to a step's position (design 4, "Where the plate is"): the
fixture's move, or a person's turn after a "turn the plate" prompt, watched while the step logs.

The sequencer owns one `Plate` per batch and runs it from its positioning states (moving,
waiting_operator) and its logging loop; plate_watch.py says, from the DUTs' own samples, which
are not there yet and what to tell the person.
"""

from __future__ import annotations

import asyncio
import logging
import time
from types import TracebackType
from typing import Any, Protocol

from contracts.events import EventBus, PromptAnswered, PromptRaised
from contracts.positions import direction
from drivers.base import DriverError, Fixture
from station.daemon import plate_watch
from station.daemon.dut_run import DutRun
from station.steps import Step

log = logging.getLogger(__name__)

LINK_LAG_S = 0.5  # wall seconds a board's samples may lag what it measures (buffers, read period)


class BatchFailed(Exception):
    """The batch cannot go on (no live DUT, fixture fault, lamp trip)."""


class device_call:
    """A device call whose failure ends the batch with the device named and what to check, instead
    of an 'internal error' with a traceback."""

    def __init__(self, name: str, check: str) -> None:
        self.name, self.check = name, check

    async def __aenter__(self) -> None:
        return None

    async def __aexit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                        tb: TracebackType | None) -> bool:
        if exc is not None and isinstance(exc, (DriverError, OSError, asyncio.TimeoutError)):
            raise BatchFailed(f"{self.name} failed: {exc or type(exc).__name__} (check {self.check})") from None
        return False


class PlateHardware(Protocol):
    """What the plate needs of the station (the sequencer's Hardware has it)."""

    @property
    def fixture(self) -> Fixture | None: ...

    @property
    def fixture_timeout_s(self) -> float: ...

    @property
    def plate_again_after_s(self) -> float: ...  # sample seconds after Done before a plate is asked for again

    @property
    def speed(self) -> float: ...  # plant seconds per wall second


class Plate:
    """The plate of one batch: its confirmed position (None: unknown, moving or being turned) and
    the operator's open prompt."""

    def __init__(self, batch_id: int, bus: EventBus, hw: PlateHardware) -> None:
        self.batch_id, self.bus, self.hw = batch_id, bus, hw
        self.position: int | None = None  # where the plate is (confirmed), None = unknown
        self.prompt: dict[str, Any] | None = None
        self.future: asyncio.Future[str] | None = None  # the open prompt's answer
        self._counter = 0
        self.check_wall = 0.0  # monotonic time of the Done the plate is watched from

    def after(self) -> str:
        """What confirmed the position, for the words: a person's Done or the fixture."""
        return "the fixture reported it reached" if self.hw.fixture is not None else "Done"

    async def move(self, step: Step) -> None:
        """The fixture moves the plate to the step's position (confirmed by its 'reached')."""
        fx = self.hw.fixture
        assert fx is not None
        what = "its power, emergency stop, Modbus address (unit 3) and cable/network"
        # The plate leaves its position: samples read during the move are stored with position -1
        # (unknown) and the status says null, never the position it left (docs/design.md).
        self.position = None
        async with device_call("fixture", what):
            await fx.move_to(step.position)
        deadline = time.monotonic() + self.hw.fixture_timeout_s
        while True:
            async with device_call("fixture", what):
                reached = await fx.position() == step.position and not await fx.moving()
            if reached:
                break
            if time.monotonic() > deadline:
                raise BatchFailed(
                    f"fixture did not reach position {step.position_name} within {self.hw.fixture_timeout_s:g} s"
                )
            await asyncio.sleep(0.05)
        self.position = step.position

    async def ask(self, step: Step, step_index: int, duts: list[DutRun]) -> None:
        """A person turns the plate: prompt, and wait for Done (an abort or 'cannot' ends the task)."""
        self.position = None  # the operator turns the plate: unknown until confirmed (as during a move)
        for d in duts:  # where the plate is before the person touches it (a wrong turn is named)
            d.faced_before = d.placement.settled_direction()
        self.raise_prompt(step, step_index)
        assert self.future is not None
        try:
            await self.future
        finally:
            self.prompt = None
            self.future = None
        # Confirmed by a person: samples are placed at this position only where each DUT measures
        # it (station/science/placement.py); a plate not there yet is asked for again while logging.
        self.position = step.position

    def raise_prompt(self, step: Step, step_index: int, reason: str = "") -> None:
        """Open a "turn the plate" prompt; `reason` (a re-prompt while logging): what is wrong."""
        self._counter += 1
        pid = self.batch_id * 1000 + self._counter
        text = f"turn the plate to {step.position_name}"
        if reason:
            text = f"{reason}: {text}"
        self.prompt = {"id": pid, "kind": "turn_plate", "text": text, "position": step.position,
                       "position_name": step.position_name, "step_index": step_index,
                       "again": bool(reason), "reason": reason or None,
                       # the board's static reading there (g, its own frame): the page draws it
                       "direction": [round(float(v), 6) for v in direction(step.position)]}
        self.future = asyncio.get_running_loop().create_future()
        self.bus.publish(PromptRaised(self.batch_id, prompt_id=pid, text=text, position=step.position))

    def close_prompt(self, answer: str) -> None:
        """Close an open re-prompt the station no longer needs (every DUT arrived): the page hides it."""
        if self.prompt is None:
            return
        pid = self.prompt["id"]
        self.prompt = None
        self.future = None
        if answer != "done":  # a Done was published by answer_prompt already
            self.bus.publish(PromptAnswered(self.batch_id, prompt_id=pid, answer=answer))

    def watch(self, step: Step, step_index: int, pending: list[DutRun], duts: list[DutRun]) -> None:
        """Without a fixture, ask the person again (with the mistake in words) for a plate that is
        not where the step wants it: plate_again_after_s of sample time after Done, or at once when
        a DUT settles at a wrong position. A re-prompt's Done restarts that time; it closes by
        itself once every DUT is placed."""
        if self.hw.fixture is not None:
            return
        if self.prompt is not None:
            if not plate_watch.away(pending):
                self.close_prompt("arrived")
            elif self.future is not None and self.future.done():
                self.close_prompt("done")
                for d in duts:  # the person says it is done again: another while to get there
                    d.plate_check_t = d.last_t if d.last_t is not None else d.plate_check_t
                self.check_wall = time.monotonic()
            return
        # The while runs on both clocks: each DUT's own samples (a held plant sends none) and the
        # station's, wall x speed plus LINK_LAG_S of wall time: the samples read just after Done were
        # measured before it (a link's buffers; in compressed time they span many sample seconds).
        waited_s = time.monotonic() - self.check_wall
        if waited_s < LINK_LAG_S or waited_s * self.hw.speed < self.hw.plate_again_after_s:
            overdue = [d for d in plate_watch.away(pending) if plate_watch.wrong_turn(d, step)]
        else:
            overdue = plate_watch.overdue(pending, step, self.hw.plate_again_after_s)
        if overdue:
            reason = plate_watch.not_there_words(step, overdue, "Done")
            log.info("batch %d: %s", self.batch_id, reason)
            self.raise_prompt(step, step_index, reason)
