"""The batch state machine's table (sequencer.py runs it): which state may follow which, which
states end a batch, and the coarse batch state the design's events and the page use.

A table of its own so that what reads a batch's state (the status, the run's end, the progress
estimate) needs only this, not the machine.
"""

from __future__ import annotations

# state -> states it may go to. Terminal states go nowhere.
TRANSITIONS: dict[str, tuple[str, ...]] = {
    "created": ("connecting",),
    "connecting": ("step_setup", "analysing"),  # analysing: a resumed batch whose steps were all done
    "step_setup": ("positioning", "programming"),
    "programming": ("step_done",),  # program and verify, part 1 (hw.program_duts)
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
