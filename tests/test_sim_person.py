"""drivers/sim/operator.Person: the simulated operator is a person, timed in sample time.

Driven through what a station gives a person (PromptRaised events on the bus, a Done callback) on a
real SimWorld advanced by hand: the plate turns over seconds (gravity passes between positions),
reaction times are human and drawn per prompt, Done sometimes comes first, a wrong turn is
corrected when the station asks again.
"""

from __future__ import annotations

import asyncio

import numpy as np

from contracts.events import EventBus, PromptRaised
from contracts.positions import GRAVITY_DIRECTIONS, POSITION_INDEX
from drivers.sim.operator import HumanTiming, Person
from drivers.sim.physics import draw_population
from drivers.sim.world import SimWorld

P, N = POSITION_INDEX["P"], POSITION_INDEX["N"]


async def _play(timing: HumanTiming, prompts: list[tuple[float, int, str]], seed: int = 0, until_s: float = 900.0,
                stop_at_done: bool = False):
    """Run the person on a world ticking 1 sample per loop turn; prompts: (at sample s, position, text).
    Returns the world's gravity trace and the sample times at which Done was pressed."""
    world = SimWorld(draw_population(1, 1), seed=1)
    bus = EventBus()
    done: list[tuple[float, int]] = []
    person = Person(world, lambda b, pid: done.append((world.time_s, pid)), timing=timing, seed=seed, poll_s=0)
    task = asyncio.create_task(person.run(bus))
    await asyncio.sleep(0)  # the person is listening before the first prompt
    trace = []
    pending = sorted(prompts)
    pid = 0
    while world.time_s < until_s and not (stop_at_done and done):
        while pending and world.time_s >= pending[0][0]:
            _, pos, text = pending.pop(0)
            pid += 1
            bus.publish(PromptRaised(1, prompt_id=pid, text=text, position=pos))
        trace.append((world.time_s, world.gravity()))
        world.advance(1)
        await asyncio.sleep(0)
    task.cancel()
    return trace, done, person


async def test_the_person_turns_over_seconds_and_presses_done_after():
    timing = HumanTiming.fixed(react_s=20.0, turn_s=6.0, confirm_s=2.0)
    trace, done, person = await _play(timing, [(10.0, N, "turn the plate to N")], until_s=120.0)
    t = np.array([x for x, _ in trace])
    g = np.array([v for _, v in trace])
    at_n = np.flatnonzero(g @ GRAVITY_DIRECTIONS[N] > 0.9999)
    at_p = np.flatnonzero(g @ GRAVITY_DIRECTIONS[P] > 0.9999)
    between = (g @ GRAVITY_DIRECTIONS[N] < 0.99) & (g @ GRAVITY_DIRECTIONS[P] < 0.99)
    assert 29.0 <= t[at_p[-1]] <= 31.5  # hands on the plate 20 s after the prompt
    assert 5.0 <= between.sum() / 3.125 <= 7.0  # six seconds between P and N
    assert len(done) == 1 and done[0][0] >= t[at_n[0]] + 1.5  # Done after the turn
    assert any("turns to N" in a for a in person.actions)


async def test_done_first_then_the_turn():
    timing = HumanTiming.fixed(react_s=5.0, turn_s=4.0, confirm_s=3.0, done_first=True)
    trace, done, _ = await _play(timing, [(0.0, N, "turn the plate to N")], until_s=60.0)
    t = np.array([x for x, _ in trace])
    g = np.array([v for _, v in trace])
    first_moved = t[np.flatnonzero(g @ GRAVITY_DIRECTIONS[P] < 0.9999)[0]]
    assert done[0][0] < first_moved  # Done pressed before the plate moved


async def test_a_wrong_turn_is_corrected_when_asked_again():
    timing = HumanTiming.fixed(react_s=5.0, turn_s=3.0, confirm_s=1.0, wrong_turn=True)
    prompts = [(0.0, N, "turn the plate to N"), (40.0, N, "s01 faces +y, not N (a wrong turn?): turn the plate to N")]
    trace, done, _ = await _play(timing, prompts, until_s=90.0)
    g = {round(t, 2): v for t, v in trace}
    wrong_at = [t for t, v in g.items() if t < 40 and abs(v @ GRAVITY_DIRECTIONS[N]) < 0.9 and abs(v @ GRAVITY_DIRECTIONS[P]) < 0.9]
    assert wrong_at, "the plate went somewhere else first"
    final = trace[-1][1]
    assert final @ GRAVITY_DIRECTIONS[N] > 0.9999
    assert len(done) == 2


async def test_human_times_vary_from_seconds_to_minutes():
    reacts = []
    for seed in range(60):
        timing = HumanTiming(done_first_p=0.0)
        trace, done, _ = await _play(timing, [(0.0, N, "turn the plate to N")], seed=seed, until_s=800.0,
                                     stop_at_done=True)
        t = np.array([x for x, _ in trace])
        g = np.array([v for _, v in trace])
        moved = np.flatnonzero(g @ GRAVITY_DIRECTIONS[P] < 0.9999)
        reacts.append(t[moved[0]] if moved.size else np.inf)
    reacts = np.array(reacts)
    assert reacts.min() < 10.0 and np.median(reacts) < 60.0
    assert (reacts > 100.0).any()  # sometimes the person is away for minutes
    assert np.isfinite(reacts).all()
