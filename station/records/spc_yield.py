"""Yield of judged DUT runs per batch, day, product, limits set and station. Pure.

Pass / judged runs: every judged attempt counts (a retest is a second run), as the station tested
it. A run stopped for a label mismatch (attempt 0: the board in the slot was not the labelled part,
no data was taken) tested nothing and is no yield point; the failure Pareto still counts its cause.
Beside it, per group, first-pass and final yield per DUT, by the rule of `GET /api/yield`
(db.repository.yields): the DUTs with a judged attempt in the group; first pass = the DUT's first
judged attempt passed, final = its latest valid (pass/marginal/fail) attempt passed, over the
attempts among the runs given (the filters'). Split from spc.py, which re-exports it, to keep that
module about the charts.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any, Iterable

from station.decisions.verdicts import VERDICTS  # re-exported

NO_ATTEMPT = 0  # a run's attempt when it never tested its part (db/models.py NO_ATTEMPT)
UNSPECIFIED = "unspecified product"  # runs whose batch carried no part number (a demo, or stored before batches carried a trace)


@dataclass
class YieldRow:
    key: str
    judged: int  # judged attempts (runs)
    passed: int
    marginal: int
    failed: int
    errors: int
    yield_pct: float | None  # 100 * passed / judged: of the attempts
    duts: int = 0  # DUTs with a judged attempt in the group
    first_pass: int = 0  # of them, first judged attempt passed
    final_pass: int = 0  # of them, latest valid attempt passed
    first_pass_pct: float | None = None  # 100 * first_pass / duts
    final_pct: float | None = None  # 100 * final_pass / duts


def utc_text(iso: Any) -> str | None:
    """ISO 8601 -> 'YYYY-MM-DDTHH:MM:SSZ' in UTC (one spelling for the page, the CSV and the ticks)."""
    if not iso:
        return None
    try:
        t = datetime.fromisoformat(str(iso).replace("Z", "+00:00"))
    except ValueError:
        return str(iso)
    t = t.replace(tzinfo=timezone.utc) if t.tzinfo is None else t.astimezone(timezone.utc)
    return t.strftime("%Y-%m-%dT%H:%M:%SZ")


def _day(iso: str | None) -> str:
    return (iso or "")[:10] or "unknown"


YIELD_BY = ("batch", "day", "product", "limits", "station")


def yields(runs: Iterable[dict], by: str) -> list[YieldRow]:
    """Yield per `batch`, `day` (UTC, of judging), `product` (part number + revision), `limits`
    (limits set and version) or `station`: pass / judged runs. Every judged attempt counts (a retest
    is a second run), as the station tested it; a run that never tested its part (attempt 0, a
    label mismatch) is none."""
    key_of = {
        "batch": lambda r: str(r.get("batch_id")),
        "day": lambda r: _day(utc_text(r.get("judged_at"))),
        "product": lambda r: str(r.get("product") or UNSPECIFIED),
        "limits": lambda r: f"{r.get('limits_name') or 'no limits set'} v{r.get('limits_version') or '?'}",
        "station": lambda r: str(r.get("station") or "unknown"),
    }[by]
    groups_: dict[str, dict[str, int]] = {}
    duts_of: dict[str, set] = {}
    tested = [r for r in runs if r.get("verdict") in VERDICTS and r.get("attempt") != NO_ATTEMPT]
    for r in tested:
        key = key_of(r)
        g = groups_.setdefault(key, {k: 0 for k in VERDICTS})
        g[r["verdict"]] += 1
        duts_of.setdefault(key, set()).add(_dut(r))
    first, final = dut_outcomes(tested)
    out = []
    for key, g in groups_.items():
        judged = sum(g.values())
        duts = duts_of[key]
        n_first = sum(first[d] for d in duts)
        n_final = sum(final[d] for d in duts)
        out.append(YieldRow(key, judged, g["pass"], g["marginal"], g["fail"], g["error"],
                            100.0 * g["pass"] / judged if judged else None, len(duts), n_first, n_final,
                            100.0 * n_first / len(duts), 100.0 * n_final / len(duts)))
    return out


def _dut(r: dict) -> str:
    return str(r.get("serial") or f"run {r.get('run_id')}")


def dut_outcomes(runs: Iterable[dict]) -> tuple[dict[str, bool], dict[str, bool]]:
    """Per DUT (serial): (first judged attempt passed, latest valid attempt passed), attempts in
    run order: the rule of GET /api/yield (db.repository.yields). Errors never make a final result
    (a retest that faulted does not hide the attempt before it); a DUT with errors only has none."""
    per: dict[str, list[tuple[int, str]]] = {}
    for r in runs:
        per.setdefault(_dut(r), []).append((int(r.get("run_id") or 0), str(r.get("verdict"))))
    first: dict[str, bool] = {}
    final: dict[str, bool] = {}
    for dut, vs in per.items():
        vs.sort()
        first[dut] = vs[0][1] == "pass"
        valid = [v for _i, v in vs if v in ("pass", "marginal", "fail")]
        final[dut] = bool(valid) and valid[-1] == "pass"
    return first, final


__all__ = ["VERDICTS", "NO_ATTEMPT", "UNSPECIFIED", "YIELD_BY", "YieldRow", "utc_text", "yields", "dut_outcomes"]
