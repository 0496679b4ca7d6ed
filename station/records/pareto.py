"""Failure Pareto of judged runs: which check fails most, and why runs end in error. Pure.

Two tables, each sorted by count (descending; ties by name) with its own percent and cumulative
percent, because the engineer's question is "fix what first": the first rows that reach ~80 %
are the work.

- checks: per judged parameter (`measurement:axis`, in words), the checks whose outcome was
  `fail` or `error` (an error check is a required measurement that was not measured). Each check
  counted once per run; a run failing on three axes counts on three rows, so the percentages are
  of failing checks, not of runs.
- error causes: one per run whose verdict is `error`, in the station's words: the run's end state
  when it did not finish (`faulted`, `aborted`, `interrupted`), `not measured` when it finished
  but a required measurement is missing, `no spec limits` when no limits set matched the part,
  else the verdict's first reason with its numbers masked (so "timeout after 10.2 s" and "after
  12 s" are one cause).

Marginal checks are not failures and are not counted.
"""

from __future__ import annotations

import csv
import io
import re
from dataclasses import asdict, dataclass, field
from typing import Iterable

from station.records.parameter_names import words

CHECKS = "checks"
ERRORS = "error causes"
CSV_COLUMNS = ("table", "rank", "what", "fail", "error", "count", "%", "cumulative %")


@dataclass(frozen=True)
class ParetoRow:
    table: str  # CHECKS or ERRORS
    rank: int  # 1 = most frequent
    key: str  # parameter ("tdb_mg_per_c:x") or cause
    what: str  # in words ("TDB x", "faulted")
    fail: int
    error: int
    count: int  # fail + error
    pct: float  # of the table's total, rounded to 0.1 (the page and the CSV show this number)
    cum_pct: float
    example: str = ""  # one reason as the station wrote it (error causes)


@dataclass
class Pareto:
    runs: int  # judged runs looked at
    runs_failed: int
    runs_error: int
    checks: list[ParetoRow] = field(default_factory=list)
    errors: list[ParetoRow] = field(default_factory=list)

    def rows(self) -> list[ParetoRow]:
        return self.checks + self.errors

    def to_json(self) -> dict:
        return {"runs": self.runs, "runs_failed": self.runs_failed, "runs_error": self.runs_error,
                "checks": [asdict(r) for r in self.checks], "errors": [asdict(r) for r in self.errors]}


def _param(c: dict) -> str:
    m = str(c.get("measurement") or "")
    return f"{m}:{c['axis']}" if c.get("axis") else m


_NUM = re.compile(r"[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


def error_cause(run: dict) -> tuple[str, str]:
    """(cause, example reason) of a run judged `error` (see the module doc)."""
    reasons = [str(r) for r in (run.get("reasons") or []) if r]
    example = reasons[0] if reasons else ""
    state = str(run.get("state") or "")
    if state and state != "done":
        return state, example
    checks = [c for c in run.get("checks") or [] if isinstance(c, dict)]
    if any(c.get("outcome") == "error" for c in checks):
        missing = next(c for c in checks if c.get("outcome") == "error")
        return "not measured", str(missing.get("reason") or example)
    if any("no spec limits" in r for r in reasons):
        return "no spec limits", example
    return (_NUM.sub("N", example)[:80] or "unknown"), example


def _ranked(table: str, counts: dict[str, list[int]], names: dict[str, str], examples: dict[str, str]) -> list[ParetoRow]:
    total = sum(f + e for f, e in counts.values())
    order = sorted(counts.items(), key=lambda kv: (-(kv[1][0] + kv[1][1]), names[kv[0]].casefold(), kv[0]))
    rows, cum = [], 0
    for rank, (key, (f, e)) in enumerate(order, start=1):
        cum += f + e
        rows.append(ParetoRow(table, rank, key, names[key], f, e, f + e, round(100.0 * (f + e) / total, 1),
                              round(100.0 * cum / total, 1), examples.get(key, "")))
    return rows


def pareto(runs: Iterable[dict]) -> Pareto:
    checks: dict[str, list[int]] = {}
    names: dict[str, str] = {}
    causes: dict[str, list[int]] = {}
    examples: dict[str, str] = {}
    n = n_fail = n_error = 0
    for r in runs:
        verdict = r.get("verdict")
        if verdict is None:
            continue
        n += 1
        n_fail += verdict == "fail"
        for c in r.get("checks") or []:
            if isinstance(c, dict) and c.get("outcome") in ("fail", "error"):
                p = _param(c)
                names.setdefault(p, words(p))
                checks.setdefault(p, [0, 0])[0 if c["outcome"] == "fail" else 1] += 1
        if verdict == "error":
            n_error += 1
            cause, example = error_cause(r)
            causes.setdefault(cause, [0, 0])[1] += 1
            examples.setdefault(cause, example)
    return Pareto(n, n_fail, n_error, _ranked(CHECKS, checks, names, {}),
                  _ranked(ERRORS, causes, {k: k for k in causes}, examples))


def csv_text(p: Pareto) -> str:
    """The rows the Records view shows, in its columns (checks first, then error causes)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for r in p.rows():
        w.writerow([r.table, r.rank, r.what, r.fail, r.error, r.count, f"{r.pct:.1f}", f"{r.cum_pct:.1f}"])
    return buf.getvalue()


__all__ = ["ParetoRow", "Pareto", "pareto", "error_cause", "csv_text", "CSV_COLUMNS", "CHECKS", "ERRORS"]
