"""Batches: start, status, abort, operator prompts (design 5.3)."""

from __future__ import annotations

import time

import pydantic_core
from fastapi import APIRouter, Depends, HTTPException, Path, Query, Request, Response

from web import audit
from web.auth import require_control, require_read
from web.db_gate import db_call
from contracts.trace import Trace
from web.schemas import (Ack, BatchCreate, BatchCreated, BatchStatus, Prompt, PromptAnswer, RetestCreate,
                         SlotStatus, StepRow, error_responses)
from web.status_etag import Rendered, compact_body, none_match
from web.views import batch_view, call, prompt_view

router = APIRouter(prefix="/api/batches", tags=["batches"], responses=error_responses(401, 403, 404, 409))
BatchId = Path(ge=1, le=2**62, description="batch id")


async def _no_batch_running(station) -> None:
    """One plate, one lamp: 409 while a batch runs (asked without rendering any batch's status)."""
    other = await call(station.running_batch)
    if other is not None:
        raise HTTPException(status_code=409, detail=f"batch {other} is already running on this station "
                                "(one plate, one lamp): wait for it to end or abort it")


@router.post("", status_code=201, response_model=BatchCreated, dependencies=[Depends(require_control)],
             responses=error_responses(422, what={422: "invalid input, also schema-valid ones: a profile or slot "
                                                       "this station does not have (GET /api/profiles, /api/slots)"}))
async def start_batch(body: BatchCreate, request: Request, response: Response):
    station = request.app.state.station
    await _no_batch_running(station)
    # The daemon records batch.start in the audit (every start: REST, demo, replay), naming the person.
    batch_id = await call(station.start_batch, body.profile, body.slots, body.operator, Trace.of(body.model_dump()),
                          by=f"REST: {audit.actor_of(request)}")
    response.headers["Location"] = f"/api/batches/{batch_id}"
    return {"id": int(batch_id)}


@router.post("/{batch_id}/retest", status_code=201, response_model=BatchCreated,
             dependencies=[Depends(require_control)])
async def retest_batch(body: RetestCreate, request: Request, response: Response, batch_id: int = BatchId):
    """Start a batch of only the slots that ended error, fail or marginal in this (ended) batch
    (or the `slots` given of those), with its profile, work order, part number, revision and lot,
    and the parts' labels scanned again (`labels`). Without `labels` the batch's own labels are
    kept, but a label that did not match its board is refused: scan it again. 409 while it runs,
    when it has no such slot, for a slot that is not one of them, for a refused label, or when
    another batch runs."""
    station = request.app.state.station
    await _no_batch_running(station)
    new_id = await call(station.retest_batch, batch_id, body.operator, by=f"REST: {audit.actor_of(request)}",
                        labels=body.labels, slots=body.slots, conflict=True)
    response.headers["Location"] = f"/api/batches/{new_id}"
    return {"id": int(new_id)}


@router.get("", response_model=list[BatchStatus], dependencies=[Depends(require_read)])
async def list_batches(request: Request, limit: int = Query(default=20, ge=1, le=200),
                       view: str = Query(default="full", pattern="^(full|compact)$",
                                         description="as GET /api/batches/{id}: compact is what the operator "
                                         "page needs to find its batch, without its transitions and results")):
    """Batches the daemon holds (this process), newest first: the page finds the running one here."""
    station = request.app.state.station
    ids = sorted((await call(station.batch_ids)), reverse=True)[:limit]
    shaped = [batch_view(await call(station.batch_status, i), i) for i in ids]
    if view == "full":
        return shaped
    return Response(b"[" + b",".join(compact_body(BatchStatus.model_validate(b)) for b in shaped) + b"]",
                    media_type="application/json")


# Many clients poll the status of the running batch (every page, the MES): the answer of a batch
# (64 slots, ~40 KiB) is rendered at most once per STATUS_TTL_S for all of them and served as bytes
# meanwhile, and rendered again at once when the batch's change marker moves (a state, step or DUT
# state change) or a change is made through the API (abort, prompt answer: their routes drop it).
# Within the TTL only sample counts and clocks can be older. A render costs the daemon's event
# loop 3-5 ms (benchmarks/web_load.py); 0.5 s, the page's SSE interval, keeps it at two a second
# whatever the number of pollers.
STATUS_TTL_S = 0.5


def _status_cache(request: Request) -> dict:
    """batch id -> web.status_etag.Rendered (the routes that change a batch pop its entry)."""
    cache = getattr(request.app.state, "batch_status_cache", None)
    if cache is None:
        cache = request.app.state.batch_status_cache = {}
    return cache


async def _rendered(request: Request, batch_id: int) -> Rendered:
    """The batch's kept render, rendered anew when it is stale (see STATUS_TTL_S), once ready: the
    status and the slot and step routes below share it, so the page's fetches of a slot's fields or
    of the step list cost no render of their own."""
    station = request.app.state.station
    cache = _status_cache(request)
    now = time.monotonic()
    marker_fn = getattr(station, "batch_marker", None)
    try:
        marker = marker_fn(batch_id) if marker_fn is not None else None
    except KeyError:
        marker = None
    hit = cache.get(batch_id)
    # Served from the kept render only while the batch has not changed state (a stale 'paused' after
    # an abort would otherwise stick on a page that got its last event inside the TTL, and a client
    # holding the running batch's ETag would get 304 for a batch that ended).
    if not (isinstance(hit, Rendered) and hit.fresh(now, marker, STATUS_TTL_S)):

        async def fetch() -> dict:
            try:
                return await call(station.batch_status, batch_id)
            except HTTPException as exc:
                if exc.status_code != 404:
                    raise
                stored = await db_call(request, request.app.state.repo.batch, batch_id)
                if stored is None:
                    raise
                return stored

        hit = Rendered(now, marker)
        if len(cache) > 64:
            cache.clear()
        cache[batch_id] = hit
        hit.start(fetch, batch_id)
    try:
        await hit.ready()
    except BaseException:
        if cache.get(batch_id) is hit:  # a failed render (404) is not kept
            cache.pop(batch_id, None)
        raise
    return hit


@router.get("/{batch_id}", response_model=BatchStatus, dependencies=[Depends(require_read)],
            responses={304: {"description": "Not Modified: the If-None-Match tag is the current answer's ETag "
                                            "(no body)"}})
async def get_batch(request: Request, batch_id: int = BatchId,
                    view: str = Query(default="full", pattern="^(full|compact)$",
                                      description="full: everything; compact: what the operator page polls "
                                      "(docs/design.md section 1, 'Batch status'): a few KiB whatever the batch's "
                                      "length")):
    """Live status from the daemon; a batch it no longer holds (ended before a restart) from the db.

    Pollers revalidate instead of downloading: the answer carries a strong `ETag` of its bytes and
    `Cache-Control: no-cache`; a request whose `If-None-Match` holds the current tag gets 304 with
    no body (decided from the kept render, without rendering, while it is fresh). `view=compact`
    carries what the operator page polls, bounded (no list that grows with the batch's length):
    state, step and the running step's row (`current_step`), progress, lamp, prompt, error, note,
    times left, counts, the verdict counts (`decision`), the trace (work order, part, revision, lot),
    and per slot its name in `slots` and its live figures as columns in `slot_live` (state, samples,
    segments, steps done, waiting for, and `rev`, which moves when the slot's other fields do: read
    them with GET /api/batches/{id}/slots). The step list is GET /api/batches/{id}/steps.
    """
    body, etag = (await _rendered(request, batch_id)).answer(batch_id, view)
    headers = {"ETag": etag, "Cache-Control": "no-cache"}
    if none_match(request.headers.get("if-none-match"), etag):
        return Response(status_code=304, headers=headers)
    return Response(body, media_type="application/json", headers=headers)


@router.get("/{batch_id}/slots", response_model=list[SlotStatus], dependencies=[Depends(require_read)])
async def get_batch_slots(request: Request, batch_id: int = BatchId,
                          slot: list[str] | None = Query(default=None, max_length=512, description="only these "
                                                         "slots (repeat the parameter); all when absent; a name the "
                                                         "batch does not have is left out"),
                          result: bool = Query(default=True, description="false: leave each slot's `result` out "
                                               "(the operator page reads it from GET /api/runs/{run_id})")):
    """The batch's slots as in the full status (GET /api/batches/{id}), in its order: what the
    operator page fetches of a slot once, and again only when the slot's `rev` in the compact view
    moves (serial, label, fault, program, verification, verdict), instead of polling it."""
    model = (await _rendered(request, batch_id)).status
    wanted = set(slot) if slot else None
    exclude = None if result else {"result"}
    picked = [s.model_dump(mode="json", exclude=exclude) for s in model.slots if wanted is None or s.slot in wanted]
    return Response(pydantic_core.to_json(picked), media_type="application/json")


@router.get("/{batch_id}/steps", response_model=list[StepRow], dependencies=[Depends(require_read)])
async def get_batch_steps(request: Request, batch_id: int = BatchId):
    """The batch's step list with each step's state and wall durations (`steps` of the full
    status; empty for a stored batch): the operator page fetches it when the running step changes
    and polls only the running row (`current_step` of the compact view)."""
    model = (await _rendered(request, batch_id)).status
    return Response(pydantic_core.to_json([r.model_dump(mode="json") for r in model.steps]),
                    media_type="application/json")


@router.post("/{batch_id}/abort", response_model=Ack)
async def abort_batch(request: Request, batch_id: int = BatchId, principal=Depends(require_control)):
    """The batch records who aborted it (the person in X-Operator with the token's name) and when:
    ended_by, ended_at, error."""
    await call(request.app.state.station.abort, batch_id, by=audit.actor_of(request), conflict=True)
    await audit.record(request, audit.BATCH_ABORT, f"batch {batch_id}", {"reason": "operator"})
    _status_cache(request).pop(batch_id, None)
    return {"ok": True, "detail": f"batch {batch_id} aborted"}


@router.get("/{batch_id}/prompt", response_model=Prompt | None, dependencies=[Depends(require_read)])
async def get_prompt(request: Request, batch_id: int = BatchId):
    """The open operator prompt of the batch, or null when none is waiting (an ended batch the
    daemon no longer holds waits for nobody: null, as long as the database knows the batch)."""
    try:
        return prompt_view(await call(request.app.state.station.prompt, batch_id))
    except HTTPException as exc:
        if exc.status_code != 404 or await db_call(request, request.app.state.repo.batch, batch_id) is None:
            raise
        return None


@router.post("/{batch_id}/prompt", response_model=Ack)
async def answer_prompt(body: PromptAnswer, request: Request, batch_id: int = BatchId,
                        principal=Depends(require_control)):
    """done: continue; cannot (with the operator's words in `note`): every DUT on the plate ends as
    error with the words and the batch ends failed; abort: abort the batch."""
    who = audit.actor_of(request)
    await call(request.app.state.station.answer_prompt, batch_id, body.prompt_id, body.answer, by=who,
               note=body.note, conflict=True)
    detail = {"prompt_id": body.prompt_id, "answer": body.answer}
    if body.note:
        detail["note"] = body.note
    await audit.record(request, audit.PROMPT_ANSWER, f"batch {batch_id}", detail)
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
