"""What makes GET /api/batches/{id} cheap for pollers (web/routes/batches.py `get_batch`): the
rendered answer kept for a moment, a strong ETag of its bytes, the If-None-Match test, and the
compact view (what the operator page polls: bounded, a few KiB at 64 DUTs; the rest of a slot and
the step list it fetches when they change, from the same kept render).

Why: every open page and the MES poll the running batch's status; at 64 DUTs the full answer is
~40 KiB and rendering it (daemon status -> view -> schema -> JSON, 3-5 ms) costs the daemon's
event loop, which also ingests the samples. A render is therefore shared by every poller for a
short TTL (and dropped at once when the batch's change marker moves), requests that come while it
runs wait for that one render, its parts run in separate turns of the loop (no single turn holds
the loop for the whole render), and a client that already holds the bytes gets 304 with no body.

The helpers are pure (dicts and bytes in, bytes and booleans out); `Rendered.start` (the render
task) is the one adapter, run by the route.
"""

from __future__ import annotations

import asyncio
import hashlib
from dataclasses import dataclass, field
from typing import Any, Awaitable, Callable, Hashable, Literal

import pydantic_core
from pydantic import BaseModel

from web.schemas import BatchStatus
from web.views import batch_view

View = Literal["full", "compact"]  # GET /api/batches/{id}?view=

# What the operator page polls (web/static/status.js pollBatch, every 2 s and on its live events),
# bounded whatever the batch's length and at most a few KiB at 64 DUTs (tests/test_web_compact.py
# holds every polled answer under 8 KiB): the batch's header, the running step's row (not the step
# list: GET /api/batches/{id}/steps, fetched when the running step changes), the verdict counts, and
# per slot only its name in `slots` and its live figures as columns in `slot_live` (state, samples,
# segments, steps done, waiting for, and `rev`, which tells the page to fetch that slot's other
# fields once: GET /api/batches/{id}/slots). Not here: transitions (they grow with the batch),
# results, program and verify records, verdict texts and the sorting list (the page builds it from
# the slots' verdicts), link statistics, lamp on-time, windows. Each name is a declared field of
# web/schemas.py BatchStatus / SlotStatus (tests/test_web_etag.py checks it), so the compact answer
# still matches the document. `overload`: its alarm is a banner on the page.
COMPACT_BATCH_FIELDS = ("id", "profile", "state", "step", "current_step", "progress", "error", "prompt", "lamp_on",
                        "lamp_state", "decision", "time_left", "elapsed_s", "waiting_for", "note", "counts",
                        "work_order", "part_number", "part_revision", "lot", "created_at", "ended_at", "slots",
                        "slot_live", "overload")
# Per slot only its name: the rest of what the page polls per slot is in `slot_live`, as columns.
COMPACT_SLOT_FIELDS = ("slot",)
# Of the step and the time left, the page shows "2 / 4 · P hot" and the two wall clocks.
COMPACT_STEP_FIELDS = ("index", "name", "count")
COMPACT_TIME_LEFT_FIELDS = ("step_wall_s", "batch_wall_s")
_COMPACT_INCLUDE: dict[str, Any] = {k: True for k in COMPACT_BATCH_FIELDS}
_COMPACT_INCLUDE.update(slots={"__all__": set(COMPACT_SLOT_FIELDS)}, step=set(COMPACT_STEP_FIELDS),
                        time_left=set(COMPACT_TIME_LEFT_FIELDS))


def compact_body(model: BaseModel) -> bytes:
    """The compact view's bytes from the validated full status."""
    out = model.model_dump(mode="json", include=_COMPACT_INCLUDE)
    out["slots"] = [{k: v for k, v in s.items() if v is not None} for s in out.get("slots") or []]
    return pydantic_core.to_json(out)


def full_body(model: BaseModel) -> bytes:
    return model.model_dump_json().encode()


def etag_of(batch_id: int, view: str, body: bytes) -> str:
    """Strong ETag (quoted) of exactly these bytes: blake2b, 96 bits, so a client holding an old
    tag never matches a different answer by chance; the batch and view are spelled out so that
    two batches (or views) never share a tag even if their bytes did."""
    return f'"b{int(batch_id)}-{view}-{hashlib.blake2b(body, digest_size=12).hexdigest()}"'


def none_match(header: str | None, etag: str) -> bool:
    """Does an If-None-Match header match this ETag (RFC 9110 13.1.2: weak comparison, a list of
    tags, or `*`)? Then the answer is 304 Not Modified."""
    if not header:
        return False
    opaque = etag.removeprefix("W/")
    for tag in header.split(","):
        tag = tag.strip()
        if tag == "*" or tag.removeprefix("W/") == opaque:
            return True
    return False


@dataclass
class Rendered:
    """One render of a batch's status: when it was asked for (monotonic s), the batch's change
    marker then, the validated full status once made, and the bytes and ETag of each view asked for
    since (dumped on demand)."""

    t_s: float
    marker: Hashable | None
    model: BatchStatus | None = None
    views: dict[str, tuple[bytes, str]] = field(default_factory=dict)
    task: asyncio.Task[BatchStatus] | None = None

    def fresh(self, now_s: float, marker: Hashable | None, ttl_s: float) -> bool:
        """Still the answer: the daemon knows the batch (marker), its marker has not moved (a state,
        step or DUT state change) and the render is younger than the TTL (sample counts, times)."""
        return marker is not None and self.marker == marker and now_s - self.t_s < ttl_s

    def start(self, fetch: Callable[[], Awaitable[dict]], batch_id: int) -> None:
        """Render in a task of its own: every request that finds this render fresh awaits the same
        one, and a request that goes away (its client hung up) does not cancel it for the others."""
        self.task = asyncio.ensure_future(self._render(fetch, batch_id))

    async def ready(self) -> BatchStatus:
        """The validated status (at once once rendered); raises what the render raised (a 404)."""
        assert self.task is not None
        return await asyncio.shield(self.task)

    @property
    def status(self) -> BatchStatus:
        """The validated status of a render that is ready (see `ready`)."""
        assert self.model is not None
        return self.model

    async def _render(self, fetch: Callable[[], Awaitable[dict]], batch_id: int) -> BatchStatus:
        raw = await fetch()  # the daemon's status: a snapshot, in one go
        await asyncio.sleep(0)  # then the view and the schema, each in its own turn of the loop
        shaped = batch_view(raw, batch_id)
        await asyncio.sleep(0)
        self.model = BatchStatus.model_validate(shaped)
        return self.model

    def answer(self, batch_id: int, view: str) -> tuple[bytes, str]:
        """(body, ETag) of one view of the rendered status, dumped once per render."""
        assert self.model is not None
        got = self.views.get(view)
        if got is None:
            body = compact_body(self.model) if view == "compact" else full_body(self.model)
            got = self.views[view] = (body, etag_of(batch_id, view, body))
        return got


__all__ = ["View", "Rendered", "compact_body", "full_body", "etag_of", "none_match", "COMPACT_BATCH_FIELDS",
           "COMPACT_SLOT_FIELDS"]
