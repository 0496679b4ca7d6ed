"""Batches: start, status, abort, operator prompts (design 5.3)."""

from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException, Path, Query, Request, Response
from fastapi.concurrency import run_in_threadpool

from web.auth import require_control, require_read
from web.schemas import Ack, BatchCreate, BatchCreated, BatchStatus, Prompt, PromptAnswer
from web.views import batch_view, call, prompt_view

router = APIRouter(prefix="/api/batches", tags=["batches"])
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
    response.headers["Location"] = f"/api/batches/{batch_id}"
    return {"id": int(batch_id)}


@router.get("", response_model=list[BatchStatus], dependencies=[Depends(require_read)])
async def list_batches(request: Request, limit: int = Query(default=20, ge=1, le=200)):
    """Batches the daemon holds (this process), newest first: the page finds the running one here."""
    station = request.app.state.station
    ids = sorted((await call(station.batch_ids)), reverse=True)[:limit]
    return [batch_view(await call(station.batch_status, i), i) for i in ids]


@router.get("/{batch_id}", response_model=BatchStatus, dependencies=[Depends(require_read)])
async def get_batch(request: Request, batch_id: int = BatchId):
    """Live status from the daemon; a batch it no longer holds (ended before a restart) from the db."""
    try:
        return batch_view(await call(request.app.state.station.batch_status, batch_id), batch_id)
    except HTTPException as exc:
        if exc.status_code != 404:
            raise
        stored = await run_in_threadpool(request.app.state.repo.batch, batch_id)
        if stored is None:
            raise
        return batch_view(stored, batch_id)


@router.post("/{batch_id}/abort", response_model=Ack, dependencies=[Depends(require_control)])
async def abort_batch(request: Request, batch_id: int = BatchId):
    await call(request.app.state.station.abort, batch_id, reason="operator", conflict=True)
    return {"ok": True, "detail": f"batch {batch_id} aborted"}


@router.get("/{batch_id}/prompt", response_model=Prompt | None, dependencies=[Depends(require_read)])
async def get_prompt(request: Request, batch_id: int = BatchId):
    """The open operator prompt of the batch, or null when none is waiting."""
    return prompt_view(await call(request.app.state.station.prompt, batch_id))


@router.post("/{batch_id}/prompt", response_model=Ack, dependencies=[Depends(require_control)])
async def answer_prompt(body: PromptAnswer, request: Request, batch_id: int = BatchId):
    await call(request.app.state.station.answer_prompt, batch_id, body.prompt_id, body.answer, conflict=True)
    return {"ok": True, "detail": f"prompt {body.prompt_id} answered"}
