"""The operator's hands on a simulated plate without a motorized fixture.

When the page's "turn the plate to N" prompt is confirmed, a real operator has turned the plate;
in simulation this task does the turning: it watches the event bus and moves the simulated world
to the prompted position when the prompt is answered 'done'. With nobody at the page (a headless
`demo --once --no-fixture`), `operator_confirms` also answers the prompts, as the page would.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from contracts.events import EventBus, PromptAnswered, PromptRaised


async def operator_hands(bus: EventBus, world, answered: list[int] | None = None) -> None:
    """Run until cancelled. answered, if given, collects the ids of the prompts acted on."""
    q = bus.subscribe(maxsize=10000, drop=True)
    wanted: dict[int, int | None] = {}
    try:
        while True:
            ev = await q.get()
            if isinstance(ev, PromptRaised):
                wanted[ev.prompt_id] = ev.position
            elif isinstance(ev, PromptAnswered) and ev.answer != "abort":
                pos = wanted.pop(ev.prompt_id, None)
                if pos is not None:
                    world.position = int(pos)
                if answered is not None:
                    answered.append(ev.prompt_id)
    finally:
        bus.unsubscribe(q)


async def operator_confirms(get_prompt: Callable[[], dict | None], answer: Callable[[int], None],
                            delay_s: float = 1.0, poll_s: float = 0.05) -> None:
    """A headless demo's operator: confirms every open prompt `delay_s` wall seconds after it
    appears (the time to turn the plate), through the same answer the page sends. Runs until
    cancelled; a prompt that closed meanwhile (batch aborted) is left alone."""
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
