"""Batches: start, status, abort, operator prompts (design 5.3)."""

from __future__ import annotations

import time

from fastapi import APIRouter, Depends, HTTPException, Path, Query, Request, Response
from fastapi.concurrency import run_in_threadpool

from web import audit
from web.auth import require_control, require_read
from web.schemas import Ack, BatchCreate, BatchCreated, BatchStatus, Prompt, PromptAnswer, error_responses
from web.views import batch_view, call, prompt_view

router = APIRouter(prefix="/api/batches", tags=["batches"], responses=error_responses(401, 403, 404, 409))
FINAL_STATES = frozenset({"finished", "aborted", "failed", "interrupted"})
BatchId = Path(ge=1, le=2**62, description="batch id")


@router.post("", status_code=201, response_model=BatchCreated, dependencies=[Depends(require_control)])
async def start_batch(body: BatchCreate, request: Request, response: Response):
    station = request.app.state.station
    for other in await call(station.batch_ids):  # one plate, one lamp: 409 while a batch runs
        st = await call(station.batch_status, other)
        if st.get("state") not in FINAL_STATES:
            raise HTTPException(status_code=409, detail=f"batch {other} is already running on this station "
                                "(one plate, one lamp): wait for it to end or abort it")
    batch_id = await call(station.start_batch, body.profile, body.slots, body.operator)
    await audit.record(request, audit.BATCH_START, f"batch {int(batch_id)}",
                       {"profile": body.profile, "slots": body.slots, "operator": body.operator})
    response.headers["Location"] = f"/api/batches/{batch_id}"
    return {"id": int(batch_id)}


@router.get("", response_model=list[BatchStatus], dependencies=[Depends(require_read)])
async def list_batches(request: Request, limit: int = Query(default=20, ge=1, le=200)):
    """Batches the daemon holds (this process), newest first: the page finds the running one here."""
    station = request.app.state.station
    ids = sorted((await call(station.batch_ids)), reverse=True)[:limit]
    return [batch_view(await call(station.batch_status, i), i) for i in ids]


# Many clients poll the status of the running batch (every page, the MES): the answer of a batch
# (64 slots, ~25 KiB) is rendered at most once per STATUS_TTL_S and served as bytes meanwhile. Any
# change made through the API (abort, prompt answer) drops it at once; the live page gets its
# events by SSE anyway.
STATUS_TTL_S = 0.1


def _status_cache(request: Request) -> dict[int, tuple[float, bytes]]:
    cache = getattr(request.app.state, "batch_status_cache", None)
    if cache is None:
        cache = request.app.state.batch_status_cache = {}
    return cache


@router.get("/{batch_id}", response_model=BatchStatus, dependencies=[Depends(require_read)])
async def get_batch(request: Request, batch_id: int = BatchId):
    """Live status from the daemon; a batch it no longer holds (ended before a restart) from the db."""
    cache = _status_cache(request)
    now = time.monotonic()
    marker_fn = getattr(request.app.state.station, "batch_marker", None)
    try:
        marker = marker_fn(batch_id) if marker_fn is not None else None
    except KeyError:
        marker = None
    hit = cache.get(batch_id)
    # Served from the cache only while the batch has not changed state (a stale 'paused' after an
    # abort would otherwise stick on a page that got its last event inside the TTL).
    if hit is not None and now - hit[0] < STATUS_TTL_S and hit[2] == marker and marker is not None:
        return Response(hit[1], media_type="application/json")
    try:
        view = batch_view(await call(request.app.state.station.batch_status, batch_id), batch_id)
    except HTTPException as exc:
        if exc.status_code != 404:
            raise
        stored = await run_in_threadpool(request.app.state.repo.batch, batch_id)
        if stored is None:
            raise
        view = batch_view(stored, batch_id)
    body = BatchStatus.model_validate(view).model_dump_json().encode()
    if len(cache) > 64:
        cache.clear()
    cache[batch_id] = (now, body, marker)
    return Response(body, media_type="application/json")


@router.post("/{batch_id}/abort", response_model=Ack)
async def abort_batch(request: Request, batch_id: int = BatchId, principal=Depends(require_control)):
    """The batch records who aborted it (the token's name) and when: ended_by, ended_at, error."""
    await call(request.app.state.station.abort, batch_id, by=principal.name, conflict=True)
    await audit.record(request, audit.BATCH_ABORT, f"batch {batch_id}", {"reason": "operator"})
    _status_cache(request).pop(batch_id, None)
    return {"ok": True, "detail": f"batch {batch_id} aborted"}


@router.get("/{batch_id}/prompt", response_model=Prompt | None, dependencies=[Depends(require_read)])
async def get_prompt(request: Request, batch_id: int = BatchId):
    """The open operator prompt of the batch, or null when none is waiting."""
    return prompt_view(await call(request.app.state.station.prompt, batch_id))


@router.post("/{batch_id}/prompt", response_model=Ack)
async def answer_prompt(body: PromptAnswer, request: Request, batch_id: int = BatchId,
                        principal=Depends(require_control)):
    await call(request.app.state.station.answer_prompt, batch_id, body.prompt_id, body.answer, by=principal.name,
               conflict=True)
    await audit.record(request, audit.PROMPT_ANSWER, f"batch {batch_id}",
                       {"prompt_id": body.prompt_id, "answer": body.answer})
    _status_cache(request).pop(batch_id, None)
    return {"ok": True, "detail": f"prompt {body.prompt_id} answered"}


@router.post("/{batch_id}/resume", response_model=BatchCreated, dependencies=[Depends(require_control)])
async def resume_batch(request: Request, batch_id: int = BatchId):
    """Resume a batch that a crash or restart interrupted, at the step after its last completed
    one: the same DUT runs go on (their stored samples and segments are kept). 409 when the batch
    is not interrupted or another batch is running."""
    bid = await call(request.app.state.station.resume_batch, batch_id, "operator (resume)", conflict=True)
    await audit.record(request, audit.BATCH_RESUME, f"batch {batch_id}", {"resumed_as": int(bid)})
    _status_cache(request).pop(batch_id, None)
    return {"id": int(bid)}
