"""GET /api/events: server-sent events (token in ?token= because EventSource cannot send headers;
the access log redacts it)."""

from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException, Request
from fastapi.responses import StreamingResponse

from web.auth import require_read_sse
from web.schemas import error_responses
from web.sse import DEFAULT_MAX_EVENT_STREAMS, STREAM_RETRY_AFTER_S, LimitedStreamingResponse, StreamLimiter, event_stream

router = APIRouter(prefix="/api", tags=["events"], responses=error_responses(
    401, 403, 503, what={503: "too many open event streams on this station: retry after Retry-After seconds"}))


def _limiter(request: Request) -> StreamLimiter:
    lim = getattr(request.app.state, "event_streams", None)
    if lim is None:
        cap = getattr(request.app.state, "max_event_streams", DEFAULT_MAX_EVENT_STREAMS)
        lim = request.app.state.event_streams = StreamLimiter(cap)
    return lim


@router.get(
    "/events",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}, "description": "live events, JSON per `data:` line"}},
    dependencies=[Depends(require_read_sse)],
)
async def events(request: Request):
    interval = getattr(request.app.state, "sse_interval_s", 0.5)
    limiter = _limiter(request)
    if not limiter.try_acquire():
        raise HTTPException(status_code=503, headers={"Retry-After": str(STREAM_RETRY_AFTER_S)},
                            detail=f"{limiter.limit} event streams are already open on this station "
                            "(http.max_event_streams): close one or retry later")
    return LimitedStreamingResponse(
        event_stream(request.app.state.station, request, interval_s=interval),
        limiter=limiter,
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )
