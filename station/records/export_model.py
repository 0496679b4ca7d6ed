"""Exports for a factory's yield and traceability tools (docs/exports.md): the stored batch, its DUT
runs, their verdicts and every check of each verdict as one typed, format-neutral report.

Why a model of its own: STDF V4 (export_stdf.py) and OCP Test & Validation JSON (export_ocptv.py)
must say the same thing about the same parts. Deciding here, once, what a part's verdict is (an
unjudged run of an ended batch is `error`, never `pass`), which site a slot is, which test number a
measurement gets and which bins a verdict falls in keeps the two writers to pure formatting.

Pure core: `build_report(batch, runs)` takes db.repository's dicts (batch_detail and run_detail);
`load_report(db, ...)` is the thin adapter that reads them and refuses what cannot be exported yet.
"""

from __future__ import annotations

import math
import numbers
import zlib
from dataclasses import dataclass
from datetime import datetime
from typing import Any, Iterable

from db.database import BATCH_ACTIVE_STATES, RUN_ACTIVE_STATES  # still running: verdicts not final

VERDICTS = ("pass", "marginal", "fail", "error")
# Hard bin = the station's verdict (the physical outcome a handler sorts by); fixed, so the same
# number means the same thing in every file.
HARD_BINS = {"pass": 1, "marginal": 2, "fail": 3, "error": 4}
# Soft bins of the grades every spec shares (station/decisions/verdicts.py); a passing grade is
# 100 + its letter (A = 101 ... Z = 126), any other passing grade name 150+ in name order per file.
FIXED_SOFT_BINS = {("pass", "pass"): 100, ("marginal", "hold"): 201, ("fail", "reject"): 301, ("fail", "none"): 302,
                   ("error", "retest"): 401}
# STDF test numbers of the measurements the station judges (verdicts.py); + 1/2/3 for axis x/y/z.
# Stable across files so a yield tool can trend a test number. Unknown names are hashed (50000+).
TEST_NUMBERS = {
    "tdb_mg_per_c": 1000, "tdsf_ppm_per_c": 1010, "fit_agreement_tdb_mg_per_c": 1020,
    "fit_agreement_tdsf_ppm_per_c": 1030, "drift_error_fs_pct": 1040, "drift_error_mg": 1050, "bow_mg": 1060,
    "ramp_residual_rms_mg": 1070, "noise_ug_per_sqrt_hz": 1080, "sfem_bias_mg": 2000, "sfem_scale_error_pct": 2010,
    "sfem_heldout_rmse_mg": 2020, "sfem_residual_ratio": 2030,
    "link_errors": 3000, "lost_samples_pct": 3010, "program_crc_match": 4000, "compensation_on": 4010,
    "verified_drift_error_fs_pct": 4020, "verify_failed_axes": 4030,
}
AXIS_OFFSET = {None: 0, "x": 1, "y": 2, "z": 3}
MAX_SITES = 255  # STDF SITE_NUM is one byte


class ExportNotFound(LookupError):
    """No such batch or run."""


class ExportNotReady(Exception):
    """The batch or run is still running: its verdicts are not final yet."""


@dataclass(frozen=True)
class ExportTest:
    """One judged measurement (one check of the verdict) with the limits the run was judged by."""

    name: str  # the measurement, e.g. tdb_mg_per_c
    axis: str | None
    test_number: int
    value: float | None  # None: not measured (the check is an error)
    unit: str
    low: float | None
    high: float | None
    sigma: float | None
    outcome: str  # pass, marginal, fail, error
    reason: str = ""

    @property
    def label(self) -> str:
        """'tdb_mg_per_c x': STDF TEST_TXT; measurement name and axis as the operator page says them."""
        return f"{self.name} {self.axis}" if self.axis else self.name


@dataclass(frozen=True)
class ExportPart:
    """One DUT run: its identity, where it sat, its final verdict and its judged measurements."""

    run_id: int
    slot: str
    site: int  # STDF site number of the slot (1..255, in slot order)
    serial: str
    label_serial: str
    sensor: str
    firmware: str
    attempt: int  # 0: a run stopped for a label mismatch (never tested the part), no attempt
    state: str  # the run's end state: done, faulted, interrupted, ...
    verdict: str  # pass, marginal, fail, error
    grade: str
    tray: str
    reason: str
    limits_name: str
    limits_version: str
    started_at: datetime | None
    ended_at: datetime | None
    judged_at: datetime | None
    tests: tuple[ExportTest, ...]
    hard_bin: int
    soft_bin: int

    @property
    def passed(self) -> bool:
        return self.verdict == "pass"

    @property
    def completed(self) -> bool:
        """The run ran to its end (a faulted or interrupted run did not)."""
        return self.state == "done"


@dataclass(frozen=True)
class BinCount:
    number: int
    name: str
    passed: bool
    count: int


@dataclass(frozen=True)
class ExportReport:
    scope: str  # "batch" (every run of the batch) or "run" (one run)
    batch_id: int
    station: str
    operator: str
    profile: str
    batch_state: str
    batch_reason: str
    replay_of: str
    work_order: str
    part_number: str
    part_revision: str
    lot: str
    created_at: datetime | None
    ended_at: datetime | None
    software_version: str
    parts: tuple[ExportPart, ...]

    @property
    def started_at(self) -> datetime | None:
        """When the first part started (the batch's creation when no run has a start)."""
        starts = [p.started_at for p in self.parts if p.started_at is not None]
        return min(starts) if starts else self.created_at

    @property
    def finished_at(self) -> datetime | None:
        """When the last part was judged or ended (for a run export: that run's, not the batch's)."""
        ends = [t for p in self.parts for t in (p.ended_at, p.judged_at) if t is not None]
        if self.scope == "batch" and self.ended_at is not None:
            ends.append(self.ended_at)
        return max(ends) if ends else self.started_at

    def hard_bins(self) -> list[BinCount]:
        return _bins((p.hard_bin, p.verdict, p.passed) for p in self.parts)

    def soft_bins(self) -> list[BinCount]:
        return _bins((p.soft_bin, f"{p.verdict} {p.grade}".strip(), p.passed) for p in self.parts)


def _bins(items: Iterable[tuple[int, str, bool]]) -> list[BinCount]:
    counts: dict[int, list] = {}
    for number, name, passed in items:
        counts.setdefault(number, [name, passed, 0])[2] += 1
    return [BinCount(n, name, passed, c) for n, (name, passed, c) in sorted(counts.items())]


# ----------------------------------------------------------------------------------- pure core
def _time(value: Any) -> datetime | None:
    if not value:
        return None
    return value if isinstance(value, datetime) else datetime.fromisoformat(str(value))


def _number(value: Any) -> float | None:
    """A finite real number or None (a bool, NaN or text is no measurement)."""
    if isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(float(value)):
        return float(value)
    return None


def _text(value: Any) -> str:
    return "" if value is None else str(value)


def measurement_test_number(name: str, axis: str | None) -> int:
    """The STDF test number of a measurement on an axis: fixed for the station's own measurements,
    a stable hash for any other name."""
    base = TEST_NUMBERS.get(name)
    if base is None:
        base = 50_000 + 10 * (zlib.crc32(name.encode()) % 4_000)
    return base + AXIS_OFFSET.get(axis, 4)


def part_verdict(run: dict) -> tuple[str, str]:
    """(verdict, reason) to export: the stored verdict; a run never judged (its batch ended while
    it ran, or the daemon died) is `error` with why, and so is any word the station does not know:
    nothing unjudged can leave the station as a pass."""
    verdict = run.get("verdict")
    reason = _text(run.get("reason"))
    if verdict in VERDICTS:
        return verdict, reason
    why = f"not judged: run {run.get('state') or 'unknown'}"
    if run.get("fault_reason"):
        why += f" ({run['fault_reason']})"
    if verdict is not None:
        why = f"unknown verdict {verdict!r}; {why}"
    return "error", why


def soft_bin(verdict: str, grade: str, other_pass_grades: list[str]) -> int:
    fixed = FIXED_SOFT_BINS.get((verdict, grade))
    if fixed is not None:
        return fixed
    if verdict == "pass":
        if _letter(grade):
            return 100 + ord(grade.upper()) - ord("A") + 1
        return 150 + other_pass_grades.index(grade)
    return HARD_BINS[verdict] * 100 + 99  # a grade word the station does not use for that verdict


def _tests(checks: list[dict]) -> tuple[ExportTest, ...]:
    out: list[ExportTest] = []
    seen: dict[int, int] = {}
    for c in checks:
        name = _text(c.get("measurement")) or "unnamed"
        axis = c.get("axis") or None
        number = measurement_test_number(name, axis)
        k = seen.get(number, 0)  # the same measurement judged by two limits: a second test number
        seen[number] = k + 1
        outcome = c.get("outcome") if c.get("outcome") in VERDICTS else "error"
        value = _number(c.get("value"))
        out.append(ExportTest(name=name, axis=axis, test_number=number + 100_000 * k, value=value,
                              unit=_text(c.get("unit")), low=_number(c.get("low")), high=_number(c.get("high")),
                              sigma=_number(c.get("sigma")), outcome="error" if value is None else outcome,
                              reason=_text(c.get("reason"))))
    return tuple(out)


def build_report(batch: dict, runs: list[dict], scope: str = "batch", software_version: str = "") -> ExportReport:
    """The report of `runs` (run_detail dicts, with verdict_detail) of `batch` (a batch_detail dict)."""
    slots = sorted({_text(r.get("slot")) for r in runs})
    if len(slots) > MAX_SITES:
        raise ValueError(f"{len(slots)} slots: STDF numbers at most {MAX_SITES} sites")
    site_of = {s: i + 1 for i, s in enumerate(slots)}
    judged = [(r, *part_verdict(r)) for r in runs]
    other_pass = sorted({_text(r.get("grade")) for r, v, _ in judged
                         if v == "pass" and soft_bin_is_other(_text(r.get("grade")))})
    labels = batch.get("labels") or {}
    parts = []
    for r, verdict, reason in judged:
        identity = r.get("identity") or {}
        grade = _text(r.get("grade")) or ("retest" if verdict == "error" else "")
        checks = list(((r.get("verdict_detail") or {}).get("checks")) or [])
        slot = _text(r.get("slot"))
        parts.append(ExportPart(
            run_id=int(r["id"]), slot=slot, site=site_of[slot], serial=_text(r.get("serial")),
            label_serial=_text(r.get("label_serial") or labels.get(slot)),
            sensor=_text(identity.get("sensor")), firmware=_text(identity.get("fw") or identity.get("firmware")),
            attempt=int(r["attempt"]) if r.get("attempt") is not None else 1, state=_text(r.get("state")), verdict=verdict, grade=grade,
            tray=_text(r.get("tray")), reason=reason, limits_name=_text(r.get("limits_name")),
            limits_version=_text(r.get("limits_version")), started_at=_time(r.get("started_at")),
            ended_at=_time(r.get("ended_at")), judged_at=_time(r.get("judged_at")), tests=_tests(checks),
            hard_bin=HARD_BINS[verdict], soft_bin=soft_bin(verdict, grade, other_pass)))
    return ExportReport(
        scope=scope, batch_id=int(batch["id"]), station=_text(batch.get("station")),
        operator=_text(batch.get("operator")), profile=_text(batch.get("profile")),
        batch_state=_text(batch.get("state")), batch_reason=_text(batch.get("reason")),
        replay_of=_text(batch.get("replay_of")), work_order=_text(batch.get("work_order")),
        part_number=_text(batch.get("part_number")), part_revision=_text(batch.get("part_revision")),
        lot=_text(batch.get("lot")), created_at=_time(batch.get("created_at")), ended_at=_time(batch.get("ended_at")),
        software_version=software_version, parts=tuple(parts))


def _letter(grade: str) -> bool:
    return len(grade) == 1 and grade.upper() in "ABCDEFGHIJKLMNOPQRSTUVWXYZ"


def soft_bin_is_other(grade: str) -> bool:
    """A passing grade with no fixed soft bin (not 'pass', not one letter A-Z): numbered per file."""
    return ("pass", grade) not in FIXED_SOFT_BINS and not _letter(grade)


# ----------------------------------------------------------------------------------- adapter
def software_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("thermal-cal-station")
    except PackageNotFoundError:
        return ""


def load_report(db: Any, *, batch_id: int | None = None, run_id: int | None = None) -> ExportReport:
    """The report of a batch (every run) or of one run, read from the database. ExportNotFound for
    an unknown id; ExportNotReady while the batch is still running (its verdicts are not final) or
    the run has no verdict yet and is still running."""
    from db import repository as repo

    if (batch_id is None) == (run_id is None):
        raise ValueError("give a batch id or a run id")
    if batch_id is not None:
        batch = repo.batch_detail(db, batch_id)
        if batch is None:
            raise ExportNotFound(f"no batch {batch_id}")
        if batch.get("state") in BATCH_ACTIVE_STATES:
            raise ExportNotReady(f"batch {batch_id} is {batch['state']}: its verdicts are not final yet")
        runs = [repo.run_detail(db, int(r["id"])) for r in batch.get("runs") or []]
        return build_report(batch, [r for r in runs if r is not None], "batch", software_version())
    run = repo.run_detail(db, int(run_id))
    if run is None:
        raise ExportNotFound(f"no run {run_id}")
    batch = repo.batch_detail(db, int(run["batch_id"])) or {"id": run["batch_id"]}
    if run.get("verdict") is None and (run.get("state") in RUN_ACTIVE_STATES
                                       or batch.get("state") in BATCH_ACTIVE_STATES):
        raise ExportNotReady(f"run {run_id} is {run.get('state')}: not judged yet")
    return build_report(batch, [run], "run", software_version())


__all__ = ["ExportTest", "ExportPart", "ExportReport", "BinCount", "ExportNotFound", "ExportNotReady", "build_report",
           "load_report", "part_verdict", "measurement_test_number", "HARD_BINS", "TEST_NUMBERS"]
