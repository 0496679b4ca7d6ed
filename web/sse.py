"""Server-sent events of the live station (GET /api/events).

Every bus event goes out as its `Event.to_json()`, except SamplesReceived: at 64 DUTs x ODR it is
far too heavy for a browser, so each client gets a throttled per-slot summary instead
(`kind: "LiveSummary"`: latest temperature, acceleration and sample count per slot), at most
every `interval_s`. A stalled client only loses its own oldest events (EventBus drop=True).
"""

from __future__ import annotations

import asyncio
import json
import time
from typing import Any, AsyncIterator

from starlette.responses import StreamingResponse

from contracts.events import SamplesReceived
from web.views import call, clean

DEFAULT_MAX_EVENT_STREAMS = 32  # a station has a few pages and an MES; each stream costs a bus queue
STREAM_RETRY_AFTER_S = 5


class StreamLimiter:
    """Open event streams of one app, capped: each holds a bus subscription (up to 20,000 queued
    events) and a task, so any read token could otherwise open them without end."""

    def __init__(self, limit: int) -> None:
        self.limit = int(limit)
        self.open = 0

    def try_acquire(self) -> bool:
        if self.open >= self.limit:
            return False
        self.open += 1
        return True

    def release(self) -> None:
        self.open = max(0, self.open - 1)


class LimitedStreamingResponse(StreamingResponse):
    """Releases its stream slot when the response ends however it ends (client gone before the
    first byte, cancelled, finished): the generator's own `finally` would not run if it never
    started."""

    def __init__(self, *args, limiter: StreamLimiter, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._limiter = limiter

    async def __call__(self, scope, receive, send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            self._limiter.release()


def format_sse(data: dict, event_id: int | None = None) -> bytes:
    text = json.dumps(clean(data), separators=(",", ":"), allow_nan=False)
    head = f"id: {event_id}\n" if event_id is not None else ""
    return f"{head}data: {text}\n\n".encode()


class LiveSummary:
    """Per-slot latest values from SamplesReceived, flushed as one small event."""

    def __init__(self) -> None:
        self.slots: dict[str, dict[str, Any]] = {}
        self.dirty = False

    def add(self, ev: SamplesReceived) -> None:
        n = len(ev.block)
        s = self.slots.setdefault(ev.slot, {"samples": 0})
        s["samples"] += n
        s.update(batch_id=ev.batch_id, serial=ev.serial, step_index=ev.step_index,
                 lamp_on=ev.lamp_on, position=ev.position)
        if n:
            s["temp_c"] = round(float(ev.block.temp_c[-1]), 3)
            s["acc_g"] = [round(float(v), 5) for v in ev.block.acc_g[-1]]
            s["time_s"] = round(float(ev.block.time_s[-1]), 3)
        self.dirty = True

    def flush(self) -> dict:
        self.dirty = False
        return {"kind": "LiveSummary", "wall_time": time.time(), "slots": self.slots}


async def event_stream(station, request, interval_s: float = 0.5, keepalive_s: float = 15.0) -> AsyncIterator[bytes]:
    bus = station.bus
    q = bus.subscribe(maxsize=20000, drop=True)
    seq = 0
    try:
        # A snapshot first, so a page that (re)connects shows the current slots at once.
        try:
            slots = await call(station.slots_status)
        except Exception:  # noqa: BLE001 - a snapshot is a convenience, never fatal
            slots = []
        seq += 1
        yield format_sse({"kind": "Snapshot", "wall_time": time.time(), "slots": slots}, seq)
        summary = LiveSummary()
        next_flush = time.monotonic() + interval_s
        last_sent = time.monotonic()
        yield b"retry: 2000\n\n"
        while True:
            timeout = max(0.0, next_flush - time.monotonic())
            try:
                ev = await asyncio.wait_for(q.get(), timeout=timeout)
            except (asyncio.TimeoutError, TimeoutError):
                ev = None
            if ev is not None:
                if isinstance(ev, SamplesReceived):
                    summary.add(ev)
                else:
                    seq += 1
                    yield format_sse(ev.to_json(), seq)
                    last_sent = time.monotonic()
                # drain what is already queued without yielding control for each one
                while not q.empty() and time.monotonic() < next_flush:
                    ev = q.get_nowait()
                    if isinstance(ev, SamplesReceived):
                        summary.add(ev)
                    else:
                        seq += 1
                        yield format_sse(ev.to_json(), seq)
                        last_sent = time.monotonic()
            now = time.monotonic()
            if now >= next_flush:
                next_flush = now + interval_s
                if summary.dirty:
                    seq += 1
                    yield format_sse(summary.flush(), seq)
                    last_sent = now
                elif now - last_sent >= keepalive_s:
                    yield b": keepalive\n\n"
                    last_sent = now
                if await request.is_disconnected():
                    break
    finally:
        bus.unsubscribe(q)
