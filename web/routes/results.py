"""MES: results feed with cursor paging, and the webhook outbox state (admin)."""

from __future__ import annotations

from datetime import datetime

from fastapi import APIRouter, Depends, HTTPException, Query, Request
from fastapi.concurrency import run_in_threadpool

from web.auth import require_admin, require_results
from web.schemas import OutboxEntry, ResultsPage, error_responses
from web.views import clean, dut_view

router = APIRouter(prefix="/api", tags=["mes"], responses=error_responses(401, 403, 503))


def parse_since(since: str | None) -> tuple[int, float | None]:
    """since = a cursor from a previous page (`next`), or an ISO 8601 time (first page)."""
    if since is None or since == "":
        return 0, None
    if since.isdigit():
        return int(since), None
    try:
        ts = datetime.fromisoformat(since.replace("Z", "+00:00"))
    except ValueError:
        raise HTTPException(
            status_code=422,
            detail="since: expected a cursor (the 'next' of a previous page) or an ISO 8601 time like 2026-01-31T08:00:00Z",
        ) from None
    return 0, ts.timestamp()


@router.get("/results", response_model=ResultsPage, dependencies=[Depends(require_results)])
async def results(
    request: Request,
    since: str | None = Query(default=None, max_length=64, description="cursor or ISO 8601 time"),
    limit: int = Query(default=100, ge=1, le=1000),
):
    after_id, since_time = parse_since(since)
    rows = await run_in_threadpool(request.app.state.repo.results_since, after_id, since_time, limit + 1)
    more = len(rows) > limit
    rows = rows[:limit]
    out = []
    for r in rows:
        v = dut_view(r)
        v["thermal"] = r.get("thermal")
        out.append(clean(v))
    nxt = str(rows[-1]["id"]) if more and rows else None
    return {"results": out, "next": nxt}


@router.get("/outbox", response_model=list[OutboxEntry], dependencies=[Depends(require_admin)])
async def outbox(request: Request, limit: int = Query(default=100, ge=1, le=1000)):
    return clean(await run_in_threadpool(request.app.state.repo.outbox_list, limit))
