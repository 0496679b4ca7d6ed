"""A profile step (data) and its kind (one registered object): what a step waits for (design 4).

A `Step` says where the plate is, the lamp, the chamber set point, its timeout in sample time and
its parameters; its `require` names its kind. A `StepKind` is everything the station does
differently for that kind, asked by name through the registry:

    check          the profile's rules for it: Profile() and the config raise them at load, so an
                   unknown kind or a bad parameter never reaches a batch (no KeyError at run time)
    done           this DUT has logged what the step needs (the sequencer moves on when every live
                   DUT has, or faults the late ones at the step's timeout)
    need_words     what a DUT still lacked at its timeout ("... timed out without a segment")
    window_start   where a DUT's sample window of the step starts when the step ends (StepCompleted)
    expected_s     the step's expected duration, left_s a DUT's sample seconds still needed
                   (station/daemon/progress.py)
    waits_for      the page's words while the step logs (batch_view.waiting_for)
    row_kind       the kind of its row in the batch's step list (step, program, verify)
    configurable   a site profile's `[[profiles.NAME.steps]]` may name it (station/config.py)

A new kind is a subclass registered with `register(Kind())` (tests/test_step_registry.py defines
one in the test): no other file changes. The built-in kinds are in station/steps/builtin.py. A
kind that runs without logging (`machine_state = "programming"`: the program step, which calls
`Hardware.program_duts`) runs in that state of the machine (station/daemon/states.py).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Literal, TypeVar

from contracts.positions import POSITION_NAMES
from station.daemon.dut_run import DutRun


@dataclass(frozen=True)
class Step:
    name: str
    position: int
    lamp: bool = False
    chamber_setpoint_c: float | None = None
    require: str = "segment"  # the step's kind: a registered StepKind's name
    dwell_s: float = 0.0
    settle_s: float = 0.0
    timeout_s: float = 3600.0
    heat_c: float = 0.0  # require="heat": the rise of every DUT's temperature that ends the step

    @property
    def position_name(self) -> str:
        return POSITION_NAMES[self.position]

    @property
    def kind(self) -> StepKind:
        return kind_of(self.require)

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "position": self.position,
            "position_name": self.position_name,
            "lamp": self.lamp,
            "chamber_setpoint_c": self.chamber_setpoint_c,
            "require": self.require,
            "dwell_s": self.dwell_s,
            "settle_s": self.settle_s,
            "timeout_s": self.timeout_s,
            "heat_c": self.heat_c,
        }


def heats(steps: Sequence[Step], i: int) -> bool:
    """The step changes the plate's temperature (lamp or set point) against the step before."""
    prev_lamp, prev_sp = (steps[i - 1].lamp, steps[i - 1].chamber_setpoint_c) if i > 0 else (False, None)
    return steps[i].lamp != prev_lamp or steps[i].chamber_setpoint_c != prev_sp


@dataclass(frozen=True)
class Estimates:
    """What this batch has shown so far, for a kind's time estimate (station/daemon/progress.py)."""

    steps: Sequence[Step]
    completed: int  # steps completed so far (their windows are known)
    duts: Sequence[DutRun]
    heating_rate_c_per_s: float | None  # how fast the lamp heated the DUTs in this batch (None: not seen yet)

    def spans(self, i: int) -> list[float]:
        """Sample seconds completed step i took, per DUT that has its window."""
        return [b - a for d in self.duts if i in d.step_windows
                for a, b in (d.step_windows[i],) if math.isfinite(a)]


class StepKind(ABC):
    """One kind of step. Subclass, set the class attributes, implement `done` and `need_words`;
    the other methods have the defaults of a step that lasts a dwell (settle_s + dwell_s)."""

    name: ClassVar[str]
    summary: ClassVar[str] = ""  # one line: what every DUT logs before the step ends
    waits_for: ClassVar[str] = ""  # the page's words while it logs (default: the name)
    row_kind: ClassVar[str] = "step"
    configurable: ClassVar[bool] = True
    machine_state: ClassVar[Literal["logging", "programming"]] = "logging"
    # its requirement counts only from the step's logging start (Done, "reached"), as for a step
    # that switches the lamp: the station changes what the samples measure at that moment
    gated: ClassVar[bool] = False
    # a step resumed after a crash counts what it logged (at its position) before the crash
    counts_before_crash: ClassVar[bool] = False

    def check(self, steps: Sequence[Step], i: int, analysis: str) -> None:
        """Raise ValueError ('steps[i]: ...') when steps[i] breaks this kind's rules."""

    @abstractmethod
    def done(self, d: DutRun, step: Step, index: int) -> bool:
        """Has DUT d logged what step `index` needs?"""

    @abstractmethod
    def need_words(self, step: Step) -> str:
        """What a DUT lacks when the step times out: 'a segment', '60 s static'."""

    def window_start(self, d: DutRun) -> float:
        """Board time the DUT's window of the step starts at, when the step ends: the start of the
        run of samples its requirement counted (else when the step began logging)."""
        start = d.requirement_start_t()
        return start if start is not None else d.step_t_start

    def expected_s(self, step: Step, i: int, est: Estimates) -> tuple[float, float]:
        """Expected duration of step i: (sample seconds, wall seconds that run at wall speed)."""
        return min(step.timeout_s, step.settle_s + step.dwell_s), 0.0

    def left_s(self, step: Step, d: DutRun, elapsed_s: float, expected_s: float, est: Estimates) -> float | None:
        """Sample seconds DUT d still needs in the running step (elapsed_s of it logged so far on
        the batch's clock; expected_s: the step's expected sample seconds); None: no estimate."""
        return expected_s - elapsed_s


_KINDS: dict[str, StepKind] = {}
K = TypeVar("K", bound=StepKind)


def register(kind: K) -> K:
    """Make `kind` known by its name (a profile's `require`). Returns it (usable as a decorator's result)."""
    name = getattr(kind, "name", "")
    if not name:
        raise ValueError(f"{type(kind).__name__} has no name")
    if name in _KINDS:
        raise ValueError(f"step kind {name!r} is registered already ({type(_KINDS[name]).__name__})")
    _KINDS[name] = kind
    return kind


def unregister(name: str) -> None:
    _KINDS.pop(name, None)


def kind_of(name: str) -> StepKind:
    try:
        return _KINDS[name]
    except KeyError:
        raise ValueError(f"unknown step kind {name!r} (known: {', '.join(_KINDS)})") from None


def kind_names(configurable: bool = False) -> tuple[str, ...]:
    """The registered kinds' names (those a site profile's steps may name, with configurable=True)."""
    return tuple(n for n, k in _KINDS.items() if k.configurable or not configurable)


def row_kinds() -> tuple[str, ...]:
    """The kinds of rows a batch's step list may show for its steps (the analysis row aside)."""
    return tuple(dict.fromkeys(k.row_kind for k in _KINDS.values()))
