"""Why a run did not pass, by name: the cause the failure Pareto counts (station/records/pareto.py).

A run judged `error` carries the station's own words: its fault reason (station/daemon: a slot's
link, the stall watchdog, the label check, the plate watch, the prompt's "Cannot do it", program and
verify, the analysis, the storage) or the verdict's reason (the same words after the run's end,
"faulted: ..." or "batch aborted: ..., DUT incomplete"; a required measurement not measured, no
spec limits). `cause_of` reads those words and names the cause ("label mismatch", "plate never
arrived", "link lost", ...), so that the Pareto counts causes, not end states ("faulted" said
nothing: a wrong label and a lost cable were one bar). A run judged `fail` is counted by the
measurement that failed it ("limit: TDB").

Pure; the patterns follow the texts the daemon writes (tests/test_records_causes.py holds one of
each, made by the daemon's own functions where they are pure). Words it does not know keep their
own text with the link and the numbers masked ("board answered N", not "other"), so a new fault
reason is still its own row until it gets a name here.
"""

from __future__ import annotations

import re
from typing import Any

from station.records.parameter_names import words

# (cause, pattern searched in the reason, case-insensitive), first match wins: the specific before
# the general ("could not turn the plate" quotes a prompt that may name a plate's position; a
# programming link loss is a link loss, said before "program").
_RULES: tuple[tuple[str, str], ...] = (
    # the MES's route check (station/decisions/route_check.py fault_words), first: before anything the
    # MES's own words may contain
    ("route refused (MES)", r"\bMES route check: the MES refused\b"),
    ("MES did not answer", r"\bMES route check: the MES did not answer\b"),
    ("station overloaded", r"\bstation overloaded\b"),
    ("cannot do it (operator)", r"\bcould not (?:.*: )?turn the plate to \S+: "),
    ("label mismatch", r"\blabel serial '.*' does not match the board's own serial"),
    ("board swapped (resume)", r"\bthe interrupted run was \S+ \(board swapped\?\)"),
    # one board, one record (design 3.1): the identity read again, a reset, a clock jump; said
    # before "programming" ("program: not written: s01 answers ... before programming")
    ("board swapped mid-run", r"\ba board swapped mid-run\?|'s board changed\b|\bidentity could not be read again\b"),
    ("board reset mid-run", r"\bthe board restarted (?:while streaming|during the run)\b"),
    ("board clock jumped", r"\bits clock jumped \d"),
    ("board clock slow", r"\bthe station's clock ran \d+ s since Done, this board's own clock\b"),
    # the board's own calibrator as a second opinion (issue 42, station/science/selfcal_compare.py
    # opinion_words, the check board_selfcal_agrees): anchored, as they are verdict reasons, so that
    # a line whose worst reason is another (a limit, a missing measurement) keeps that one's name
    ("board calibrator disagrees", r"^board's own calibrator disagrees: "),
    ("board calibrator not read", r"^board's own calibrator: no comparison: "),
    # the cubic SFEM verified on the board (station/decisions/board_checks.py sfem_verify_findings, a
    # told mark beside the contract's verify_failed_axes that decides): the line of a run failed by
    # it alone; its write and read-back failures are "programming" ("program: crc_mismatch: ...")
    ("SFEM verification failed", r"^(?:axes failing the verification [^;]*; )*[xyz] SFEM on the board: "
                                 r"residual (?:rms|max) [^;]* over its limit\b"),
    ("temperature sensor", r"\btemperature sensor (?:stuck|implausible)\b"),
    ("plate never arrived", r"\bplate never arrived at \S+"),
    ("plate at wrong position", r"\bfaces? \S+, not \S+"),
    ("DUT never faced the position", r"\boutput never faced \S+ within"),
    ("step timed out", r"\bstep '.*' timed out after"),
    ("results not stored", r"\bresults not stored\b"),
    ("safety trip", r"\bsafety trip\b"),
    ("lamp relay", r"\blamp relay\b"),
    ("fixture", r"\bfixture (?:failed|did not reach)\b"),
    ("thermal chamber", r"\bthermal chamber failed\b"),
    ("link lost", r"\blink lost\b|^program: link\b"),
    ("no samples", r"\bno samples for \d"),
    ("garbage on the link", r"\bonly garbage for \d"),
    ("board data unreadable", r"\bboard data could not be (?:read|processed)\b"),
    ("board did not answer", r"\bno identity reply from\b|\bcannot open (?:serial port|CAN bus)\b|\bstart failed\b"
                             r"|\bdid not acknowledge\b"),
    ("programming", r"^program: |^not programmed: "),
    ("verification", r"^not verified: "),
    ("analysis", r"^analysis: "),
    ("aborted", r"\baborted\b"),
    ("interrupted", r"\bstation restarted\b|^batch interrupted\b|^run interrupted\b"),
    ("no DUT left", r"\bno DUT left\b"),
    ("no spec limits", r"\bno spec limits\b"),
)
_COMPILED = tuple((name, re.compile(pat, re.IGNORECASE)) for name, pat in _RULES)
CAUSES = tuple(name for name, _ in _RULES) + ("not measured",)

_LINK = re.compile(r"^(?:serial \S+|can \S+ node \d+): ")
# the verdict's reason of a run that did not finish starts with its end (station/decisions/moment.py
# end_of): "faulted: <the fault reason>", "interrupted: station restarted during the batch, ..."
_END = re.compile(r"^(?:faulted|interrupted|aborted): ")
_NUM = re.compile(r"[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


def unnamed(reason: str) -> str:
    """A reason no rule names, as its own cause: without the link it came from, numbers masked
    (so "after 10.2 s" and "after 12 s" are one cause), at most 80 characters."""
    return _NUM.sub("N", _LINK.sub("", _END.sub("", reason.strip())))[:80] or "unknown"


def cause_of(reason: str) -> str | None:
    """The named cause of one reason (a fault reason or a verdict reason); None when no rule knows
    the words."""
    text = _END.sub("", str(reason or "").strip())
    for name, rx in _COMPILED:
        if rx.search(text):
            return name
    return None


def code_of(cause: str) -> str:
    """A cause's stable machine code, for a page that says the cause in the reader's language
    (web/static/i18n/*.json `reason.<code>`): the name in lower case, every run of other characters
    one "_" ("route refused (MES)" -> "route_refused_mes"). Derived, not listed, so that a cause
    named here has its code at once; tests/test_i18n_catalogs.py fails until every catalog says it."""
    return re.sub(r"[^a-z0-9]+", "_", cause.lower()).strip("_")


# The verdict's own reasons that are no fault (station/decisions/judging.py, verdicts.py): a limit
# check's words. Not causes of the Pareto (that counts a fail by its measurement), but the page says
# them in the operator's language too; code -> pattern on the first reason of the line.
_VERDICT_WORDS: tuple[tuple[str, str], ...] = (
    ("all_limits_met", r"^all limits met$"),
    ("limit_crossed", r" crosses limit \S+$"),
    ("limit_near", r", within \S+ of limit \S+$"),
    ("limit_exceeded", r", limit \S+$"),
    ("not_measured", r" not measured$"),
    ("no_grade_met", r"^meets no grade"),
)
_VERDICT_RX = tuple((code, re.compile(pat)) for code, pat in _VERDICT_WORDS)
# every code reason_code can give: what the message catalogs must translate
CODES = tuple(dict.fromkeys([*(code_of(c) for c in CAUSES), *(code for code, _ in _VERDICT_WORDS)]))


def reason_code(reason: str | None) -> str | None:
    """The machine code of a reason the station shows (a fault reason, a verdict's or a batch's
    reason), so that the page translates the cause while the record keeps the station's English
    words; None for words no rule names (the MES's free text, a new fault): the page then shows
    them as they are, marked untranslated, rather than guess."""
    text = str(reason or "").strip()
    if not text:
        return None
    cause = cause_of(text)
    if cause is not None:
        return code_of(cause)
    first = text.split("; ")[0]
    return next((code for code, rx in _VERDICT_RX if rx.search(first)), None)


def _failing_check(run: dict[str, Any]) -> dict[str, Any] | None:
    """The check that failed the run: the one its first (worst) reason names, else the first failing."""
    checks = [c for c in run.get("checks") or [] if isinstance(c, dict) and c.get("outcome") == "fail"]
    first = next(iter(run.get("reasons") or []), None)
    return next((c for c in checks if first and c.get("reason") == first), checks[0] if checks else None)


def run_cause(run: dict[str, Any]) -> tuple[str, str]:
    """(cause, example reason) of a run judged `fail` or `error`: an error by its reason (the fault
    reason of a run that did not finish, else the verdict's), "not measured" when it finished
    without a required measurement; a fail by the measurement that failed it, "limit: TDB"."""
    reasons = [str(r) for r in (run.get("reasons") or []) if r]
    fault = str(run.get("fault_reason") or "")
    example = fault or (reasons[0] if reasons else "")
    if run.get("verdict") == "fail":
        c = _failing_check(run)
        if c is not None:
            return f"limit: {words(str(c.get('measurement') or ''))}", str(c.get("reason") or example)
        return ("no grade met" if any(r.startswith("meets no grade") for r in reasons) else "limit"), example
    for text in [fault, *reasons]:
        name = cause_of(text)
        if name is not None:
            return name, text
    checks = [c for c in run.get("checks") or [] if isinstance(c, dict)]
    missing = next((c for c in checks if c.get("outcome") == "error"), None)
    if missing is not None:
        return "not measured", str(missing.get("reason") or example)
    if example:
        return unnamed(example), example
    return str(run.get("state") or "unknown"), example


__all__ = ["CAUSES", "CODES", "cause_of", "code_of", "reason_code", "run_cause", "unnamed"]
