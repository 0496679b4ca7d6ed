"""The verdict's checks: one registered object each (pure).

A check is a small object with a `name`, what it `needs` (the measurement names it reads; the run
it sees holds only those), the measurements it `declares` (what it computes itself, so the records
have its words) and `apply(run, spec) -> finding or None`. A finding is a `Check` (one measurement
judged: its outcome decides the verdict with every other check's, its words are among the reasons
when it did not pass), several of them, or a `Mark` (words that never decide, docs/verdicts.md:
the SFEM model check). The verdict (station/decisions/verdicts.py `decide`) runs every registered
check in registration order; adding a check is one class and one `register(...)`:

    class MaxAbsTdb:
        name = "max_abs_tdb"
        needs = frozenset({"tdb_mg_per_c"})
        declares = (MeasurementDef("max_abs_tdb_mg_per_c", "mg/C", "max |TDB|", ...),)
        def apply(self, run, spec):
            ...
            return judge(self.declares[0].measured(worst), Limit(...), spec.guard_sigma)

    register(MaxAbsTdb())

Built in: `SpecLimits` (every limit of the product in force for the run's analysis, with the
profile's requirements; station/decisions/judging.py), `SfemFitMark` (the SFEM model check's
words, a mark), `BoardSelfCalAgrees` (issue 42: the board's own calibrator against the station's
result, the named check `board_selfcal_agrees`) and `SfemOnBoardMarks` (issue 42: the cubic SFEM's
residual on the board per axis, beside the contract's verify_failed_axes); the last two read their
records through station/decisions/board_checks.py.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Protocol, Union

from station.decisions.judging import Check, judge, limits_in_force, matching, missing_checks
from station.decisions.limits import Limit, ProductSpec
from station.decisions.measurements import SFEM_RESIDUAL_RATIO, Measurement, MeasurementDef, declare, undeclare
from station.decisions.board_checks import (BOARD_SELFCAL_AGREES, BOARD_SELFCAL_TDB, BOARD_SELFCAL_TDSF, Finding as
                                            BoardFinding, selfcal_findings, sfem_verify_findings)
from station.decisions.measurements import SFEM_VERIFIED_RESIDUAL_MAX, SFEM_VERIFIED_RESIDUAL_RMS
from station.decisions.sfem_checks import sfem_fit_mark


@dataclass(frozen=True)
class RunView:
    """What a check reads of the run being judged (a check that `needs` names sees only those)."""

    measurements: tuple[Measurement, ...]
    analysis: str  # the profile's analysis: thermal, sfem, ...
    required: tuple[Limit | str, ...] = ()  # what the profile requires (verdicts.profile_requirements)
    result: Mapping[str, object] | None = None  # the analysis result as stored (None: decide() on measurements only)
    judged: tuple[Check, ...] = field(default=())  # the checks the checks registered before this one found
    verification: Mapping[str, object] | None = None  # program and verify, part 2 (None: no such record)
    board_selfcal: Mapping[str, object] | None = None  # the board's calibrator's opinion (None: option off)

    def named(self, name: str) -> list[Measurement]:
        return [m for m in self.measurements if m.name == name]


@dataclass(frozen=True)
class Mark:
    """Words on the verdict that never decide it: `check` (outcome pass) joins the verdict's checks
    after it is decided; with `tell`, its reason joins the reasons as well."""

    check: Check
    tell: bool = False


Finding = Union[Check, Mark, Sequence[Union[Check, Mark]], None]


class VerdictCheck(Protocol):
    """One check of the verdict (module doc)."""

    @property
    def name(self) -> str: ...

    @property
    def needs(self) -> frozenset[str] | None:
        """The measurement names it reads (None: every measurement of the run)."""
        ...

    @property
    def declares(self) -> tuple[MeasurementDef, ...]:
        """The measurements it computes itself (declared while it is registered)."""
        ...

    def apply(self, run: RunView, spec: ProductSpec) -> Finding: ...


# ---- the registry ----------------------------------------------------------------------------------
_CHECKS: dict[str, VerdictCheck] = {}


def register(check: VerdictCheck) -> VerdictCheck:
    """Add a check after the ones registered (and declare its measurements). A name taken by
    another check is refused; registering the same check again changes nothing."""
    other = _CHECKS.get(check.name)
    if other is check or (other is not None and other == check):
        return check
    if other is not None:
        raise ValueError(f"verdict check {check.name!r} is already registered: {other!r}")
    for d in check.declares:
        declare(d)
    _CHECKS[check.name] = check
    return check


def unregister(name: str) -> None:
    """Remove a check (a test's own) and its declarations; an unknown name is no error."""
    check = _CHECKS.pop(name, None)
    for d in check.declares if check is not None else ():
        undeclare(d.name)


@contextmanager
def registered(check: VerdictCheck) -> Iterator[VerdictCheck]:
    """`check` registered inside the block only."""
    register(check)
    try:
        yield check
    finally:
        unregister(check.name)


def verdict_checks() -> tuple[VerdictCheck, ...]:
    """The registered checks, in registration order (the order of the verdict's checks)."""
    return tuple(_CHECKS.values())


def run_checks(run: RunView, spec: ProductSpec,
               checks: Sequence[VerdictCheck] | None = None) -> tuple[list[Check], list[Mark]]:
    """Every check's findings: (checks that decide, marks), each in registration order."""
    decided: list[Check] = []
    marks: list[Mark] = []
    for chk in verdict_checks() if checks is None else checks:
        needs = chk.needs
        seen = run if needs is None else \
            replace(run, measurements=tuple(m for m in run.measurements if m.name in needs))
        found = chk.apply(replace(seen, judged=tuple(decided)), spec)
        items: Sequence[Check | Mark] = () if found is None else (found,) if isinstance(found, (Check, Mark)) else found
        for f in items:
            if isinstance(f, Mark):
                marks.append(f)
            else:
                decided.append(f)
    return decided, marks


# ---- the built-in checks ---------------------------------------------------------------------------
@dataclass(frozen=True)
class SpecLimits:
    """The product's limits in force for the run's analysis, with the profile's requirements made
    required (judging.limits_in_force): every matching measurement judged; a required one that is
    missing is an error check; an optional one that came out empty is not judged."""

    name: str = "spec_limits"
    needs: frozenset[str] | None = None
    declares: tuple[MeasurementDef, ...] = ()

    def apply(self, run: RunView, spec: ProductSpec) -> Finding:
        out: list[Check] = []
        for limit in limits_in_force(spec, run.analysis, run.required):
            found = matching(run.measurements, limit)
            if limit.required:
                out += missing_checks(limit, found)
            for m in found:
                c = judge(m, limit, spec.guard_sigma)
                if c.outcome == "error" and not limit.required:
                    continue  # an optional measurement that came out empty is not judged
                out.append(c)
        return out


@dataclass(frozen=True)
class SfemFitMark:
    """The SFEM model check marks the verdict, it never decides it (sfem_checks.py says why): a
    check with its words, and the words among the reasons when the model misses an effect. Not
    when the product's own limit judged the ratio, nor without an SFEM record."""

    name: str = "sfem_fit_mark"
    needs: frozenset[str] | None = frozenset()
    declares: tuple[MeasurementDef, ...] = ()

    def apply(self, run: RunView, spec: ProductSpec) -> Finding:
        if run.analysis != "sfem" or run.result is None:
            return None
        mark = sfem_fit_mark(run.result)
        if mark is None or any(c.measurement == SFEM_RESIDUAL_RATIO.name for c in run.judged):
            return None
        value, words = mark
        return Mark(Check(SFEM_RESIDUAL_RATIO.name, None, value, None, SFEM_RESIDUAL_RATIO.unit, None, None, "pass",
                          words), tell="misses an effect" in words)


def _as_finding(items: list[BoardFinding]) -> Finding:
    return [f.check if f.decides else Mark(f.check, tell=f.tell) for f in items] or None


@dataclass(frozen=True)
class BoardSelfCalAgrees:
    """The board's own calibrator as a second opinion (board_checks.py selfcal_findings): the flag
    decides, the figures side by side per axis are shown beside it; not applicable on a board
    without a calibrator; nothing when the profile's option is off."""

    name: str = "board_selfcal_agrees"
    needs: frozenset[str] | None = frozenset()
    declares: tuple[MeasurementDef, ...] = (BOARD_SELFCAL_AGREES, BOARD_SELFCAL_TDB, BOARD_SELFCAL_TDSF)

    def apply(self, run: RunView, spec: ProductSpec) -> Finding:
        return _as_finding(selfcal_findings(run.board_selfcal))


@dataclass(frozen=True)
class SfemOnBoardMarks:
    """The cubic SFEM verified on the board: residual rms and max per axis against the run's own
    limits, as marks (the failing ones told); verify_failed_axes (a contract limit) decides."""

    name: str = "sfem_on_board"
    needs: frozenset[str] | None = frozenset()
    declares: tuple[MeasurementDef, ...] = (SFEM_VERIFIED_RESIDUAL_RMS, SFEM_VERIFIED_RESIDUAL_MAX)

    def apply(self, run: RunView, spec: ProductSpec) -> Finding:
        return _as_finding(sfem_verify_findings(run.verification))


register(SpecLimits())
register(SfemFitMark())
register(BoardSelfCalAgrees())
register(SfemOnBoardMarks())


__all__ = ["RunView", "Mark", "Finding", "VerdictCheck", "register", "unregister", "registered", "verdict_checks",
           "run_checks", "SpecLimits", "SfemFitMark", "BoardSelfCalAgrees", "SfemOnBoardMarks"]
