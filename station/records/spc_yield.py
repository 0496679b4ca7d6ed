"""Yield of judged DUT runs per batch, day, product, limits set and station (issue 13). Pure.

Pass / judged runs: every judged attempt counts (a retest is a second run), as the station tested
it. (`GET /api/yield` keeps first-pass and final yield per DUT.) Split from spc.py, which
re-exports it, to keep that module about the charts.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any, Iterable

VERDICTS = ("pass", "marginal", "fail", "error")
UNSPECIFIED = "unspecified product"  # runs whose batch carried no part number (before issue 24)


@dataclass
class YieldRow:
    key: str
    judged: int
    passed: int
    marginal: int
    failed: int
    errors: int
    yield_pct: float | None


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
    is a second run), as the station tested it."""
    key_of = {
        "batch": lambda r: str(r.get("batch_id")),
        "day": lambda r: _day(utc_text(r.get("judged_at"))),
        "product": lambda r: str(r.get("product") or UNSPECIFIED),
        "limits": lambda r: f"{r.get('limits_name') or 'no limits set'} v{r.get('limits_version') or '?'}",
        "station": lambda r: str(r.get("station") or "unknown"),
    }[by]
    groups_: dict[str, dict[str, int]] = {}
    for r in runs:
        v = r.get("verdict")
        if v not in VERDICTS:
            continue
        g = groups_.setdefault(key_of(r), {k: 0 for k in VERDICTS})
        g[v] += 1
    out = []
    for key, g in groups_.items():
        judged = sum(g.values())
        out.append(YieldRow(key, judged, g["pass"], g["marginal"], g["fail"], g["error"],
                            100.0 * g["pass"] / judged if judged else None))
    return out


__all__ = ["VERDICTS", "UNSPECIFIED", "YIELD_BY", "YieldRow", "utc_text", "yields"]
