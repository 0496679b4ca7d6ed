"""Failure Pareto of judged runs: which check fails most, and why runs do not pass. Pure.

Two tables, each sorted by count (descending; ties by name) with its own percent and cumulative
percent, because the engineer's question is "fix what first": the first rows that reach ~80 %
are the work.

- checks: per judged parameter (`measurement:axis`, in words), the checks whose outcome was
  `fail` or `error` (an error check is a required measurement that was not measured). Each check
  counted once per run; a run failing on three axes counts on three rows, so the percentages are
  of failing checks, not of runs.
- causes: one per run judged `fail` or `error`, by name (station/records/causes.py): an error by
  the station's words for it ("label mismatch", "plate never arrived", "link lost", "no samples",
  "analysis", "cannot do it (operator)", "results not stored", "not measured", ...), a fail by the
  measurement that failed it ("limit: TDB"). The `fail` and `error` columns count the runs of each
  verdict; `example` is one reason as the station wrote it.

Marginal checks and runs are not failures and are not counted.
"""

from __future__ import annotations

import csv
import io
from dataclasses import asdict, dataclass, field
from typing import Iterable

from station.records.causes import run_cause
from station.records.csv_cells import safe_row
from station.records.parameter_names import words

CHECKS = "checks"
CAUSES = "causes"
CSV_COLUMNS = ("table", "rank", "what", "fail", "error", "count", "%", "cumulative %")


@dataclass(frozen=True)
class ParetoRow:
    table: str  # CHECKS or CAUSES
    rank: int  # 1 = most frequent
    key: str  # parameter ("tdb_mg_per_c:x") or cause
    what: str  # in words ("TDB x", "label mismatch")
    fail: int
    error: int
    count: int  # fail + error
    pct: float  # of the table's total, rounded to 0.1 (the page and the CSV show this number)
    cum_pct: float
    example: str = ""  # one reason as the station wrote it (causes)


@dataclass
class Pareto:
    runs: int  # judged runs looked at
    runs_failed: int
    runs_error: int
    checks: list[ParetoRow] = field(default_factory=list)
    causes: list[ParetoRow] = field(default_factory=list)

    def rows(self) -> list[ParetoRow]:
        return self.checks + self.causes

    def to_json(self) -> dict:
        return {"runs": self.runs, "runs_failed": self.runs_failed, "runs_error": self.runs_error,
                "checks": [asdict(r) for r in self.checks], "causes": [asdict(r) for r in self.causes]}


def _param(c: dict) -> str:
    m = str(c.get("measurement") or "")
    return f"{m}:{c['axis']}" if c.get("axis") else m


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
        n_error += verdict == "error"
        if verdict in ("fail", "error"):
            cause, example = run_cause(r)
            causes.setdefault(cause, [0, 0])[0 if verdict == "fail" else 1] += 1
            examples.setdefault(cause, example)
    return Pareto(n, n_fail, n_error, _ranked(CHECKS, checks, names, {}),
                  _ranked(CAUSES, causes, {k: k for k in causes}, examples))


def csv_text(p: Pareto) -> str:
    """The rows the Records view shows, in its columns (checks first, then causes); text a
    spreadsheet would take for a formula is quoted (station/records/csv_cells.py)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for r in p.rows():
        w.writerow(safe_row([r.table, r.rank, r.what, r.fail, r.error, r.count, f"{r.pct:.1f}", f"{r.cum_pct:.1f}"]))
    return buf.getvalue()


__all__ = ["ParetoRow", "Pareto", "pareto", "run_cause", "csv_text", "CSV_COLUMNS", "CHECKS", "CAUSES"]
