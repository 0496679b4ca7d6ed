"""MES: results feed with cursor paging, and the webhook outbox state (admin)."""

from __future__ import annotations

import re
from datetime import datetime, timezone

from fastapi import APIRouter, Depends, HTTPException, Query, Request

from web.auth import require_admin, require_results
from web.db_gate import db_call
from web.schemas import MesResultPayload, OutboxEntry, ResultsPage, YieldOut, error_responses
from web.views import clean, dut_view

router = APIRouter(prefix="/api", tags=["mes"], responses=error_responses(401, 403, 422, 503))


CURSOR_MAX = (1 << 63) - 1  # result ids are SQLite/PostgreSQL signed 64-bit integers
SINCE_HELP = ("since: expected a cursor (the 'next' of a previous page), an ISO 8601 / RFC 3339 time with its offset "
              "like 2026-01-31T08:00:00Z, or a date like 2026-01-31")


# What `since` may be, for the OpenAPI document: a cursor (int64), or an ISO 8601 date or time.
SINCE_FORMS = [
    {"type": "string", "pattern": r"^([0-9]{1,18}|[0-8][0-9]{18})$", "description": "a cursor: the 'next' of a previous page"},
    {"type": "string", "format": "date-time", "description": "results stored at or after this time"},
    {"type": "string", "format": "date", "description": "results stored on or after this day (station local time)"},
    {"type": "string", "maxLength": 0, "description": "empty: the same as no since (from the first result)"},
]


_CURSOR = re.compile(r"^[0-9]{1,19}$")
_DATE = re.compile(r"^[0-9]{4}-[0-9]{2}-[0-9]{2}$")
_RFC3339 = re.compile(r"^([0-9]{4}-[0-9]{2}-[0-9]{2})[Tt ]([0-9]{2}:[0-9]{2}):([0-9]{2})(\.[0-9]+)?([Zz]|[+-][0-9]{2}:[0-9]{2})$")


def parse_since(since: str | None) -> tuple[int, float | None]:
    """since = a cursor from a previous page (`next`), or a time (first page): an RFC 3339 date-time
    with its offset (2026-01-31T08:00:00Z) or a date (local midnight), the forms the OpenAPI
    document gives (SINCE_FORMS), nothing looser.

    Anything else is a 422 naming the problem, never a 500: a cursor beyond int64, digits that are
    not ASCII ('²' is a digit to str.isdigit), a time no clock can hold (year 1 in local time)."""
    if since is None or since == "":
        return 0, None
    if _CURSOR.match(since):
        cursor = int(since)
        if cursor > CURSOR_MAX:
            raise HTTPException(status_code=422, detail=f"since: cursor {since} is out of range (max {CURSOR_MAX})")
        return cursor, None
    m = _RFC3339.match(since)
    try:
        if m is not None:
            day, hm, sec, frac, off = m.groups()
            sec = min(int(sec), 59)  # a leap second (:60) is taken as the second before it
            off = "+00:00" if off in ("Z", "z") else off
            ts = datetime.fromisoformat(f"{day}T{hm}:{sec:02d}{(frac or '')[:7]}{off}")
        elif _DATE.match(since):
            ts = datetime.fromisoformat(since)
        else:
            raise HTTPException(status_code=422, detail=SINCE_HELP)
    except ValueError:  # month 13, February 30, ...
        raise HTTPException(status_code=422, detail=f"since: {since!r} is not a valid date or time") from None
    try:
        stamp = ts.timestamp()
        datetime.fromtimestamp(stamp, tz=timezone.utc)  # the repository's conversion must not fail
        return 0, stamp
    except (ValueError, OverflowError, OSError):  # e.g. 0001-01-01 as local time is before year 1
        raise HTTPException(status_code=422, detail=f"since: time {since!r} is out of range") from None


RESULTS_DESCRIPTION = """The MES feed: one record per final verdict of a DUT run (design 8), with its results,
in increasing `id` (commit order, also with many stations on one database).

**Cursor.** Pass `since` = the `next` of the previous page. `next` is never null: it is the last `id`
of this page or, when the page is empty, the `since` given (`"0"` when none). A page with fewer than
`limit` records is the last for now: poll again later with its `next`. A client that always follows
`next` reads each record exactly once (it used to get `next: null` on the last page and start again
from the beginning).

**Supersession.** A later verdict of the same run (a batch interrupted, then resumed and judged
again; a re-judge) is a new record with its own `id` and `idempotency_key`, `revision` N + 1 and
`supersedes` = the key of the record it replaces. Keep the latest revision per `run_id`."""


def next_cursor(rows: list[dict], since: str | None) -> str:
    """Where the client goes on from: the last id returned, or the since given (never null)."""
    if rows:
        return str(rows[-1]["id"])
    return since or "0"


@router.get("/results", response_model=ResultsPage, dependencies=[Depends(require_results)],
            description=RESULTS_DESCRIPTION,
            responses=error_responses(422, what={422: "invalid input, also schema-valid ones: a since that is no "
                                                      "calendar day or time (0000-00-00), or a time out of range"}))
async def results(
    request: Request,
    since: str | None = Query(default=None, max_length=64, description="cursor, RFC 3339 time (with offset) or date",
                              json_schema_extra={"anyOf": SINCE_FORMS}),
    limit: int = Query(default=100, ge=1, le=1000),
    station: str | None = Query(default=None, max_length=64,
                                description="only this station's results (many stations may share one database)"),
):
    after_id, since_time = parse_since(since)
    by_station = {"station": station} if station else {}  # repositories without stations still serve the rest
    rows = await db_call(request, request.app.state.repo.results_since, after_id, since_time, limit, **by_station)
    rows = rows[:limit]
    out = []
    for r in rows:
        v = dut_view(r)
        v["thermal"] = r.get("thermal")
        out.append(clean(v))
    return {"results": out, "next": next_cursor(rows, since)}


@router.get("/outbox", response_model=list[OutboxEntry], dependencies=[Depends(require_admin)])
async def outbox(request: Request, limit: int = Query(default=100, ge=1, le=1000)):
    return clean(await db_call(request, request.app.state.repo.outbox_list, limit))


@router.get("/yield", response_model=YieldOut, dependencies=[Depends(require_results)])
async def yield_summary(request: Request, batch_id: int | None = Query(default=None, ge=1, le=2**62,
                                                                          description="only the DUTs of this batch")):
    """First-pass and final yield: every attempt of each DUT counts; the latest valid attempt is
    the DUT's result (db.repository.yields)."""
    return await db_call(request, request.app.state.repo.yields, batch_id)


def register_webhooks(app) -> None:
    """Document the MES webhook in the OpenAPI (`webhooks`): what the station POSTs to the
    configured webhook ([mes] webhook_url) for every final verdict."""

    @app.webhooks.post("mes-result")
    def mes_result(body: MesResultPayload) -> None:
        """One MES record: a DUT run's final verdict (grade, attempt, limits version) with its results;
        a later verdict of the same run is a new record (`revision` N + 1, `supersedes` = the key it
        replaces). Header
        `Idempotency-Key` = body.idempotency_key: a retry after a lost reply carries the same key.
        Reply 2xx once stored; anything else is retried with exponential backoff."""
