"""The operator's hands on a simulated plate without a motorized fixture.

When the page's "turn the plate to N" prompt is confirmed, a real operator has turned the plate;
in simulation this task does the turning: it watches the event bus and moves the simulated world
to the prompted position when the prompt is answered 'done'.
"""

from __future__ import annotations

from station.events import EventBus, PromptAnswered, PromptRaised


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
