"""Request guard (pure ASGI middleware): authentication before the body, a cap on its size, and
JSON bodies that are not UTF-8 answered like any other bad JSON.

Why here and not in the routes: FastAPI reads and parses a request body *before* it runs the
route's dependencies, so a client without a token could make the daemon buffer and parse any
amount of data (four 50 MB POSTs took it from 459 MB to 902 MB). This middleware runs first:

- a request that carries a body (Content-Length > 0 or Transfer-Encoding) must have a valid
  bearer token, checked from the headers alone: 401 without reading a byte of the body (uvicorn
  then closes the connection instead of draining it);
- a declared Content-Length above `max_body_bytes` is 413 at once; a chunked body is counted as
  it arrives and answered 413 as soon as it passes the limit;
- a body sent as JSON that is not UTF-8 (RFC 8259 JSON is UTF-8) is 422 with the byte offset,
  like every other invalid JSON body (FastAPI would answer a bare 400).
"""

from __future__ import annotations

import json

from fastapi import HTTPException

from web.auth import authenticate

DEFAULT_MAX_BODY_BYTES = 1 << 20  # the largest real body (a batch start) is < 100 KiB


def _json_response(status: int, detail: str, extra_headers: list[tuple[bytes, bytes]] = (), **more) -> tuple[dict, dict]:
    body = json.dumps({"detail": detail, **more}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()), *extra_headers]
    return ({"type": "http.response.start", "status": status, "headers": headers},
            {"type": "http.response.body", "body": body})


def too_large(limit: int) -> str:
    return f"request body larger than {limit} bytes (the station's http.max_body_bytes)"


class RequestGuard:
    """See the module doc. Added inside SecurityHeaders (web/app.py), so its answers carry the
    same headers as the app's; requests without a body pass straight through."""

    def __init__(self, app, max_body_bytes: int = DEFAULT_MAX_BODY_BYTES) -> None:
        self.app = app
        self.max_body_bytes = int(max_body_bytes)

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = {}
        for k, v in scope.get("headers") or ():
            headers.setdefault(k.lower(), v)
        length_raw = headers.get(b"content-length")
        chunked = b"transfer-encoding" in headers
        try:
            length = int(length_raw) if length_raw is not None else 0
        except ValueError:  # uvicorn rejects these itself; be safe anyway
            length = 0
        if length <= 0 and not chunked:
            await self.app(scope, receive, send)
            return

        # 1. who is asking, from the headers only (the body stays unread in the socket)
        from starlette.requests import Request

        try:
            authenticate(Request(scope))
        except HTTPException as exc:
            await self._answer(send, exc.status_code, str(exc.detail), [(b"www-authenticate", b"Bearer")])
            return
        # 2. how much, when declared
        limit = self.max_body_bytes
        if length > limit:
            await self._answer(send, 413, too_large(limit))
            return
        # 3. read it (bounded), check JSON encoding, then hand it to the app in one message
        body = bytearray()
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            body += message.get("body", b"")
            if len(body) > limit:
                await self._answer(send, 413, too_large(limit))
                return
            if not message.get("more_body", False):
                break
        ctype = headers.get(b"content-type", b"").split(b";")[0].strip().lower()
        if ctype == b"application/json" or ctype.endswith(b"+json"):
            try:
                bytes(body).decode("utf-8")
            except UnicodeDecodeError as exc:
                detail = f"body: not valid JSON: not UTF-8 at byte {exc.start}"
                await self._answer(send, 422, detail, errors=[
                    {"loc": ["body", str(exc.start)], "msg": "not UTF-8", "type": "json_invalid"}])
                return
        sent = False

        async def replay():
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": bytes(body), "more_body": False}
            return await receive()  # after the body: wait for the disconnect as usual

        await self.app(scope, replay, send)

    @staticmethod
    async def _answer(send, status: int, detail: str, extra_headers=(), **more) -> None:
        start, body = _json_response(status, detail, list(extra_headers), **more)
        await send(start)
        await send(body)
