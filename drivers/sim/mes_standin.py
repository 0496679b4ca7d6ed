"""A small MES stand-in for the demo and the tests: it answers the station's route check.

A real line's MES answers "may this serial be tested at this operation now?" (design 5.4). This
stand-in answers it the way the station's default [mes.route_check] expects, over real HTTP on
127.0.0.1 (the station's httpx client talks to it as to a real MES):

    GET  /route?serial=S&operation=O&station=N&slot=X ...   (or POST /route with the same as JSON)
    200  {"allowed": true,  "reason": ""}
    200  {"allowed": false, "reason": "on quality hold: NCR-2291 (voids under U3)"}   a held serial

It is the world, not the station: it keeps its own list of held serials (compared trimmed and
case-insensitive, as a line's MES compares labels) and of every call it received, so a test checks
what the station asked against what this MES saw. `mode` makes it misbehave like real MESes do:
'slow' answers after `slow_s`, 'error' answers 500, 'garbage' answers 200 with a body that is not
JSON; a stopped stand-in refuses connections.

The standard library's threaded HTTP server, in its own thread: independent of the station's
event loop and of its HTTP stack.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Literal
from urllib.parse import parse_qs, urlparse

Mode = Literal["up", "slow", "error", "garbage"]


@dataclass
class RouteCall:
    """One route check as the MES received it."""

    method: str
    fields: dict[str, str]
    at: float = field(default_factory=time.time)


class MesStandIn:
    """The route check's MES on 127.0.0.1 (port 0: a free one). Use as a context manager or
    start()/stop()."""

    def __init__(self, holds: dict[str, str] | None = None, *, host: str = "127.0.0.1", port: int = 0,
                 slow_s: float = 30.0) -> None:
        self.holds: dict[str, str] = dict(holds or {})  # serial -> the MES's reason
        self.mode: Mode = "up"
        self.slow_s = slow_s
        self.calls: list[RouteCall] = []
        self._lock = threading.Lock()
        self._server = ThreadingHTTPServer((host, port), self._handler())
        self._server.daemon_threads = True
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        return int(self._server.server_address[1])

    @property
    def url(self) -> str:
        """The route check URL a station's config names ([mes.route_check] url)."""
        return (f"http://127.0.0.1:{self.port}/route?serial={{serial}}&operation={{operation}}&station={{station}}"
                f"&slot={{slot}}&label={{label_serial}}&work_order={{work_order}}")

    def hold(self, serial: str, reason: str) -> None:
        with self._lock:
            self.holds[serial] = reason

    def answer_for(self, serial: str) -> dict[str, object]:
        """What this MES says of `serial` (its own rule: held or not)."""
        key = serial.strip().lower()
        with self._lock:
            reason = next((why for held, why in self.holds.items() if held.strip().lower() == key), None)
        return {"allowed": reason is None, "reason": reason or ""}

    def start(self) -> "MesStandIn":
        self._thread = threading.Thread(target=self._server.serve_forever, name="mes-standin", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop answering: the port is closed (a call then gets a refused connection)."""
        if self._thread is not None:  # shutdown() waits for serve_forever: only once it runs
            self._server.shutdown()
            self._thread.join(5)
            self._thread = None
        self._server.server_close()

    def __enter__(self) -> "MesStandIn":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _handler(self) -> type[BaseHTTPRequestHandler]:
        mes = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, format: str, *args: object) -> None:  # noqa: A002 - the stdlib's name
                pass

            def _route(self, fields: dict[str, str]) -> None:
                with mes._lock:
                    mes.calls.append(RouteCall(self.command, fields))
                    mode = mes.mode
                if mode == "slow":
                    time.sleep(mes.slow_s)
                if mode == "error":
                    self._send(500, b'{"error": "database unavailable"}')
                    return
                if mode == "garbage":
                    self._send(200, b"<html>maintenance</html>", "text/html")
                    return
                self._send(200, json.dumps(mes.answer_for(fields.get("serial", ""))).encode())

            def _send(self, status: int, body: bytes, ctype: str = "application/json") -> None:
                try:
                    self.send_response(status)
                    self.send_header("Content-Type", ctype)
                    self.send_header("Content-Length", str(len(body)))
                    self.end_headers()
                    self.wfile.write(body)
                except OSError:  # the station gave up waiting (its timeout): nothing to answer
                    pass

            def do_GET(self) -> None:  # noqa: N802 - the stdlib's name
                url = urlparse(self.path)
                if url.path != "/route":
                    self._send(404, b'{"error": "not found"}')
                    return
                self._route({k: v[0] for k, v in parse_qs(url.query, keep_blank_values=True).items()})

            def do_POST(self) -> None:  # noqa: N802
                if urlparse(self.path).path != "/route":
                    self._send(404, b'{"error": "not found"}')
                    return
                n = int(self.headers.get("Content-Length") or 0)
                try:
                    data = json.loads(self.rfile.read(n) or b"{}")
                except ValueError:
                    self._send(400, b'{"error": "body is not JSON"}')
                    return
                self._route({str(k): str(v) for k, v in dict(data).items()})

        return Handler
