"""The person at a simulated plate without a motorized fixture.

A real line's operator is no robot: they read the prompt after a while (seconds, sometimes
minutes), turn the plate over a few seconds, sometimes press Done before turning, sometimes turn
it to the wrong position and correct it when the page says so. `Person` plays that on the
simulated world (drivers/sim/world.py turn_to: gravity rotates over the turn), acting only through
what a person has: their hands on the plate and the prompt's Done. Every time is SAMPLE time (the
plant's clock), so a compressed-time demo or test meets the same person as a real-time one.

`operator_hands` is the page's hands instead: the plate is turned (over a couple of seconds) when
somebody answers the prompt 'done' on the page, for tests that drive the page themselves.
"""

from __future__ import annotations

import asyncio
import logging
import math
import random
from collections.abc import Callable
from dataclasses import dataclass, field

from contracts.events import EventBus, PromptAnswered, PromptRaised
from contracts.positions import GRAVITY_DIRECTIONS, POSITION_NAMES

log = logging.getLogger(__name__)

HANDS_TURN_S = 2.0  # sample seconds the page's hands take to turn the plate


@dataclass(frozen=True)
class HumanTiming:
    """How one person behaves, in sample seconds. Each range is drawn log-uniformly per prompt."""

    react_s: tuple[float, float] = (2.0, 60.0)  # from the prompt to the hands on the plate
    long_pause_p: float = 0.1  # sometimes the person is away: a pause of minutes instead
    long_pause_s: tuple[float, float] = (120.0, 600.0)
    turn_s: tuple[float, float] = (1.5, 8.0)  # the turn itself
    done_first_p: float = 0.25  # presses Done first, then turns
    confirm_s: tuple[float, float] = (0.5, 6.0)  # from the end of the turn to Done
    wrong_turn_p: float = 0.0  # turns to another position first, corrects it when asked again

    @staticmethod
    def fixed(react_s: float, turn_s: float = 3.0, confirm_s: float = 1.0, *, done_first: bool = False,
              wrong_turn: bool = False) -> "HumanTiming":
        """One deterministic behaviour (tests pick each mistake on purpose)."""
        return HumanTiming(react_s=(react_s, react_s), long_pause_p=0.0, turn_s=(turn_s, turn_s),
                           done_first_p=1.0 if done_first else 0.0, confirm_s=(confirm_s, confirm_s),
                           wrong_turn_p=1.0 if wrong_turn else 0.0)


def _draw(rng: random.Random, lo_hi: tuple[float, float]) -> float:
    lo, hi = lo_hi
    if hi <= lo:
        return float(lo)
    return math.exp(rng.uniform(math.log(max(lo, 1e-3)), math.log(hi)))


@dataclass
class Person:
    """A simulated operator (module doc). `answer(batch_id, prompt_id)` presses Done (raises
    ValueError/KeyError when the prompt has closed meanwhile: the person just lets it be)."""

    world: object  # drivers.sim.world.SimWorld (turn_to, time_s, position)
    answer: Callable[[int, int], None]
    timing: HumanTiming = field(default_factory=HumanTiming)
    seed: int = 0
    poll_s: float = 0.01
    actions: list[str] = field(default_factory=list)  # what the person did, in words (tests, demo log)
    _rng: random.Random = field(init=False)
    _busy: asyncio.Task | None = field(default=None, init=False)
    _busy_for: int | None = field(default=None, init=False)  # the position the running handler turns to
    _goal: int | None = field(default=None, init=False)  # where the person means the plate to be
    _latest: tuple[int, int] | None = field(default=None, init=False)  # (batch, prompt) the newest asking
    _answered: set[int] = field(default_factory=set, init=False)

    def __post_init__(self) -> None:
        self._rng = random.Random(self.seed)

    async def run(self, bus: EventBus) -> None:
        """Watch the prompts until cancelled."""
        q = bus.subscribe(maxsize=10000, drop=True)
        try:
            while True:
                ev = await q.get()
                if not isinstance(ev, PromptRaised) or ev.position is None:
                    continue
                self._latest = (ev.batch_id, ev.prompt_id)
                running = self._busy is not None and not self._busy.done()
                if running and self._busy_for == int(ev.position):
                    continue  # asked again while already on it: the hands go on, Done at the end
                if running:
                    self._busy.cancel()  # asked for another position: the person reads the new words
                self._busy_for = int(ev.position)
                self._busy = asyncio.get_running_loop().create_task(
                    self._handle(ev.batch_id, ev.prompt_id, int(ev.position), ev.text))
        finally:
            bus.unsubscribe(q)
            if self._busy is not None:
                self._busy.cancel()

    async def _sleep(self, sample_s: float) -> None:
        """Wait sample_s of plant time (the world's clock)."""
        end = self.world.time_s + max(0.0, sample_s)
        while self.world.time_s < end:
            await asyncio.sleep(self.poll_s)

    def _press_done(self, batch_id: int, prompt_id: int) -> None:
        self._answered.add(prompt_id)
        try:
            self.answer(batch_id, prompt_id)
            self.actions.append(f"t={self.world.time_s:.0f} s Done (prompt {prompt_id})")
        except (ValueError, KeyError):
            pass  # the prompt closed meanwhile (the plate arrived, the batch ended)

    def _press_latest(self) -> None:
        """Done on the newest asking, once (a prompt asked again while the hands were busy)."""
        if self._latest is not None and self._latest[1] not in self._answered:
            self._press_done(*self._latest)

    async def _turn(self, position: int) -> None:
        dur = _draw(self._rng, self.timing.turn_s)
        self._goal = position
        self.actions.append(f"t={self.world.time_s:.0f} s turns to {POSITION_NAMES[position]} over {dur:.1f} s")
        self.world.turn_to(position, dur)
        await self._sleep(dur)

    async def _handle(self, batch_id: int, prompt_id: int, position: int, text: str) -> None:
        t = self.timing
        again = self._goal is not None and not text.startswith("turn the plate")
        if again and self._goal == position and self.world.position == position:
            # asked again while the plate is on its way or there: the person confirms once it is
            await self._sleep(_draw(self._rng, t.confirm_s))
            self._press_latest()
            return
        pause = t.long_pause_s if self._rng.random() < t.long_pause_p else t.react_s
        if again:
            pause = t.react_s  # a prompt asked again is read at once
        await self._sleep(_draw(self._rng, pause))
        done_first = self._rng.random() < t.done_first_p
        if done_first:
            self._press_done(batch_id, prompt_id)
            await self._sleep(_draw(self._rng, t.confirm_s))
        if not again and self._rng.random() < t.wrong_turn_p:
            await self._turn(self._wrong_position(position))
            if not done_first:
                await self._sleep(_draw(self._rng, t.confirm_s))
                self._press_latest()
            return  # the station names the wrong turn and asks again: handled as a new prompt
        if self.world.position != position or self.world.turn is not None:
            await self._turn(position)
        self._goal = position
        await self._sleep(_draw(self._rng, t.confirm_s))
        self._press_latest()  # Done (or, having pressed it first, Done on a prompt asked meanwhile)

    def _wrong_position(self, position: int) -> int:
        """A plausible wrong turn: another of the six faces, never one pointing where the asked one
        does (sfem-y90 is +z) nor where the plate already is."""
        choices = [POSITION_NAMES.index(n) for n in ("+x", "-x", "+y", "-y", "+z", "-z")]
        here = self.world.gravity()
        return self._rng.choice([c for c in choices if GRAVITY_DIRECTIONS[c] @ GRAVITY_DIRECTIONS[position] < 0.99
                                 and GRAVITY_DIRECTIONS[c] @ here < 0.99])


async def operator_hands(bus: EventBus, world, answered: list[int] | None = None,
                         turn_s: float = HANDS_TURN_S) -> None:
    """The page's hands: when a prompt is answered 'done', the plate is turned to its position
    over turn_s of sample time. Run until cancelled; answered, if given, collects the prompt ids."""
    q = bus.subscribe(maxsize=10000, drop=True)
    wanted: dict[int, int | None] = {}
    try:
        while True:
            ev = await q.get()
            if isinstance(ev, PromptRaised):
                wanted[ev.prompt_id] = ev.position
            elif isinstance(ev, PromptAnswered) and ev.answer == "done":
                pos = wanted.pop(ev.prompt_id, None)
                if pos is not None and (world.position != int(pos) or getattr(world, "turn", None) is not None):
                    if hasattr(world, "turn_to"):
                        world.turn_to(int(pos), turn_s)
                    else:
                        world.position = int(pos)
                if answered is not None:
                    answered.append(ev.prompt_id)
    finally:
        bus.unsubscribe(q)


async def operator_confirms(get_prompt: Callable[[], dict | None], answer: Callable[[int], None],
                            delay_s: float = 1.0, poll_s: float = 0.05) -> None:
    """Nobody at the page, and `operator_hands` turning the plate: confirms every open prompt
    `delay_s` WALL seconds after it appears, through the same answer the page sends (recorded
    batches of the replay tests). Runs until cancelled; a prompt that closed meanwhile is left."""
    seen: set[int] = set()
    while True:
        await asyncio.sleep(poll_s)
        try:
            prompt = get_prompt()
        except KeyError:
            return
        if prompt is None or prompt["id"] in seen:
            continue
        seen.add(prompt["id"])
        await asyncio.sleep(delay_s)
        try:
            answer(prompt["id"])
        except (ValueError, KeyError):
            pass
