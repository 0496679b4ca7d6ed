"""GET /api/events: server-sent events (token in ?token= because EventSource cannot send headers;
the access log redacts it)."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request
from fastapi.responses import StreamingResponse

from web.auth import require_read_sse
from web.schemas import error_responses
from web.sse import event_stream

router = APIRouter(prefix="/api", tags=["events"], responses=error_responses(401, 403))


@router.get(
    "/events",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}, "description": "live events, JSON per `data:` line"}},
    dependencies=[Depends(require_read_sse)],
)
async def events(request: Request):
    interval = getattr(request.app.state, "sse_interval_s", 0.5)
    return StreamingResponse(
        event_stream(request.app.state.station, request, interval_s=interval),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )
