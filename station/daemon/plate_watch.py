"""The plate after Done: which DUTs are not where the step wants them, and what to tell the person.

A person presses Done before turning the plate, turns it over seconds, pauses, turns it to the
wrong position or back. The sequencer keeps logging the DUTs that are placed (station/science/
placement.py) and, for the others, asks again with the mistake in words: "s03 still faces N 40 s
after Done", "the plate faces -x, not P (a wrong turn?)", "s01, s02 left P and face N". Only a
plate that never arrives within the step's timeout ends its DUTs as error, with that reason.

Pure reading of DutRun records: no events, no state of its own.
"""

from __future__ import annotations

from collections import defaultdict

from station.daemon.dut_run import DutRun
from station.daemon.intake_monitor import ATTRIBUTE_BEHIND_S
from station.steps import Step
from station.science.placement import direction_id, direction_name


def away(pending: list[DutRun]) -> list[DutRun]:
    """The DUTs (of those still logging the step) that are not placed at its position now."""
    return [d for d in pending if not d.at_step_position()]


def facing_words(d: DutRun) -> str:
    """What the DUT faces now, in words: 'faces N', 'is moving (no position)'."""
    settled = d.placement.settled_direction()
    if settled is not None:
        return f"faces {direction_name(settled)}"
    now = d.placement.facing_now()
    if now >= 0:
        return f"is coming to {direction_name(now)} (not still yet)"
    return "is between positions (facing none)"


def wrong_turn(d: DutRun, step: Step) -> bool:
    """Settled somewhere the step does not want, other than where the plate was before the person
    was asked (a wrong turn), or anywhere else after it had arrived (turned away, turned back)."""
    settled = d.placement.settled_direction()
    if settled is None or settled == direction_id(step.position):
        return False
    before = d.faced_before if d.faced_before is not None else d.first_settled
    return d.arrived_t is not None or (before is not None and settled != before)


def overdue(pending: list[DutRun], step: Step, again_after_s: float) -> list[DutRun]:
    """The DUTs not placed whose plate is asked for again now: again_after_s of their own stream
    after Done, or at once when they settled at a wrong position."""
    return [d for d in away(pending) if d.since_plate_check_s() >= again_after_s or wrong_turn(d, step)]


def _slots(duts: list[DutRun]) -> str:
    return ", ".join(d.slot for d in duts)


def not_there_words(step: Step, duts: list[DutRun], after: str = "Done") -> str:
    """Why the plate is asked for again, one clause per group of DUTs facing the same way:
    's03 still faces N 40 s after Done', 's01, s02 face -x, not P (a wrong turn?)'."""
    since_s = max((d.since_plate_check_s() for d in duts), default=0.0)
    groups: dict[tuple[str, str, str], list[DutRun]] = defaultdict(list)
    for d in duts:
        settled = d.placement.settled_direction()
        if settled is not None and d.arrived_t is not None and wrong_turn(d, step):
            key = ("left", f" {step.position_name} and ", f"face{{s}} {direction_name(settled)}")
        elif settled is not None and wrong_turn(d, step):
            key = ("face{s}", f" {direction_name(settled)}, not {step.position_name}", " (a wrong turn?)")
        elif settled is not None:
            key = ("still face{s}", f" {direction_name(settled)}", f" {since_s:.0f} s after {after}")
        else:
            key = ("{is_moving}", "", f" {since_s:.0f} s after {after}")
        groups[key].append(d)
    out = []
    for (verb, middle, tail), g in groups.items():
        one = len(g) == 1
        words = (verb + middle + tail).format(s="s" if one else "", is_moving=(
            "is between positions" if one else "are between positions"))
        out.append(f"{_slots(g)} {words}")
    return "; ".join(out)


def never_arrived_reason(step: Step, d: DutRun, elapsed_s: float, others_arrived: bool, after: str) -> str:
    """The fault of a DUT whose plate never reached the step's position within its timeout."""
    if others_arrived:
        return (f"step '{step.name}': its output never faced {step.position_name} within {elapsed_s:.0f} s sample "
                f"time after {after} while the other DUTs did; it {facing_words(d)} "
                "(DUT not seated, mounted turned, or loose?)")
    return (f"step '{step.name}': plate never arrived at {step.position_name}: {elapsed_s:.0f} s sample time "
            f"after {after} it {facing_words(d)}")


def timed_out_reason(step: Step, d: DutRun, elapsed_s: float, station_s: float, others_arrived: bool,
                     after: str) -> str:
    """The fault of a DUT past the step's timeout, with why: a plate that never arrived at the
    position (its clock runs from `after`), a plate that left it, a board clock that slowed or
    stopped (the station's clock ran station_s, its own elapsed_s), or the step's requirement not
    met (the step's kind says what was missing)."""
    need = step.kind.need_words(step)
    if d.station_lost_samples or d.link_behind_s > ATTRIBUTE_BEHIND_S:
        # the station's own backlog hid what this board sent: not the part's fault
        return (f"step '{step.name}' could not be judged: station overloaded (it ran {d.link_behind_s:.0f} s "
                f"behind this board and lost {d.station_lost_samples} of its samples to its own backlog); "
                f"still without {need} after {elapsed_s:.0f} s of the sample time it received; not the part")
    if d.arrived_t is None:
        return never_arrived_reason(step, d, elapsed_s, others_arrived, after)
    if not d.at_step_position():
        return (f"step '{step.name}' timed out after {elapsed_s:.0f} s sample time without {need}: the "
                f"plate left {step.position_name} and it {facing_words(d)}")
    if elapsed_s < step.timeout_s:
        return (f"step '{step.name}' timed out without {need}: the station's clock ran {station_s:.0f} s "
                f"since Done, this board's own clock {elapsed_s:.0f} s (a board clock that slowed or stopped?)")
    return f"step '{step.name}' timed out after {elapsed_s:.0f} s sample time without {need}"
