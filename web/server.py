"""The web server's one start-up: `station serve`, `station demo` and the tests all go through
`serve_web` (so a test talks to the server the daemon runs, slow-client limits included).

It runs uvicorn in the caller's event loop (the daemon's: the Station facade is not thread-safe,
so routes call it directly) and needs nothing but the web app and a Station-like object: `.config`
for the `[http]` limits and whatever web/app.create_app reads. Every web import happens inside
serve_web, so an installation whose web app cannot be imported fails there in one line
(StationError), never at import time of the command line.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
from collections.abc import Iterator
from typing import Any

from contracts.types import StationError

# Open SSE streams never end by themselves: a stop waits this long for requests in flight, then
# uvicorn cancels them.
GRACEFUL_SHUTDOWN_S = 2


LISTEN_QUEUE = 1024  # connections the kernel holds before the station accepts them (capped by net.core.somaxconn)


async def serve_web(station: Any, host: str, port: int, *, app: Any = None, sock: socket.socket | None = None,
                    header_timeout_s: float | None = None, keep_alive_s: float | None = None,
                    max_connections: int | None = None, access_log: bool = False) -> tuple[Any, asyncio.Task[None]]:
    """Serve the web app of `station` on host:port in this event loop; returns (server, task).

    app: the FastAPI app (default create_app(station); a test passes its own repository or tokens).
    sock: an already bound socket to serve on (default: bind host:port here; a taken port is one
    clear line, not uvicorn's exit(3)).
    header_timeout_s / keep_alive_s / max_connections: default from station.config [http]
    (web/http_guard.py). access_log: log every request at INFO (token-redacted; the daemon logs
    warnings only). `server.http_guard` holds the guard's counters. Stop with `stop_web`.
    """
    try:
        import uvicorn

        from web.app import create_app
        from web.auth import install_log_redaction
        from web.http_guard import (ACCEPT_BATCH, DEFAULT_HEADER_TIMEOUT_S, DEFAULT_KEEP_ALIVE_S,
                                    DEFAULT_MAX_CONNECTIONS, HttpGuard, install_accept_error_filter)
    except ImportError as exc:
        # A web app that cannot be imported is a hard error, never a warning: a daemon without
        # its page looks alive to an operator who cannot reach it.
        raise StationError(f"the operator page cannot be served: {exc} "
                           "(the installation is incomplete: run `pip install .` or ./scripts/setup.sh)") from exc

    class _Server(uvicorn.Server):
        @contextlib.contextmanager
        def capture_signals(self) -> Iterator[None]:  # the daemon owns SIGINT/SIGTERM (lamp off first)
            yield

    http_cfg = getattr(getattr(station, "config", None), "http", None)
    if header_timeout_s is None:
        header_timeout_s = getattr(http_cfg, "header_timeout_s", DEFAULT_HEADER_TIMEOUT_S)
    if keep_alive_s is None:
        keep_alive_s = getattr(http_cfg, "keep_alive_s", DEFAULT_KEEP_ALIVE_S)
    if max_connections is None:
        max_connections = getattr(http_cfg, "max_connections", DEFAULT_MAX_CONNECTIONS)
    install_log_redaction()  # the access log never shows a ?token=
    install_accept_error_filter()  # a full file table: one line per 10 s, not a traceback per accept()
    own_sock = sock is None
    listen = _listen_socket(host, port) if sock is None else sock
    if app is None:
        app = create_app(station)
    guard = HttpGuard(header_timeout_s=header_timeout_s, max_connections=max_connections, accept_batch=ACCEPT_BATCH)
    # Slow clients (web/http_guard.py: one slow client must not hold the API): a request head within header_timeout_s, idle
    # keep-alive closed after keep_alive_s, at most max_connections open (the oldest waiting for a
    # head is evicted), and at most ACCEPT_BATCH sockets accepted per loop tick (the listen backlog).
    config = uvicorn.Config(app, host=host, port=port, log_level="info" if access_log else "warning",
                            access_log=access_log, lifespan="on", http=guard.protocol_class(),
                            timeout_keep_alive=keep_alive_s,  # type: ignore[arg-type]  # seconds, a float works
                            backlog=ACCEPT_BATCH,
                            # the client's address is the TCP peer's: uvicorn would otherwise take it from
                            # X-Forwarded-For on a connection from 127.0.0.1, so any local process could
                            # claim another address (the /metrics allow list, the audit's addresses)
                            proxy_headers=False,
                            timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_S)
    server = _Server(config)
    task = asyncio.get_running_loop().create_task(server.serve(sockets=[listen]), name="http")
    for _ in range(200):
        if server.started or task.done():
            break
        await asyncio.sleep(0.02)
    if task.done():
        err = task.exception() if not task.cancelled() else None
        if own_sock:
            listen.close()
        raise StationError(f"cannot serve HTTP on {host}:{port}: {err or 'server exited'}")
    # The kernel's queue of connections not yet accepted is deeper than one accept batch: asyncio set
    # it to the batch when it started serving, and a flood of half-open connections (a slowloris, a
    # misbehaving client) then fills it whenever the loop is busy, so the kernel drops the next SYN
    # and a health probe or the kiosk waits for TCP's 1 s retransmission. Queued connections hold no
    # file of ours: the open sockets stay bounded by the cap plus one batch (web/http_guard.py).
    with contextlib.suppress(OSError):
        listen.listen(LISTEN_QUEUE)
    server.http_guard = guard  # type: ignore[attr-defined]  # its counters, for tests and diagnostics
    return server, task


def _listen_socket(host: str, port: int) -> socket.socket:
    try:
        family, kind, proto, _, addr = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
        sock = socket.socket(family, kind, proto)
    except (OSError, UnicodeError) as exc:
        raise StationError(f"cannot serve HTTP on {host}:{port}: {exc}") from None
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
        sock.listen(128)
    except OSError as exc:
        sock.close()
        raise StationError(f"cannot serve HTTP on {host}:{port}: {exc.strerror or exc} (is another station "
                           "or program using this port? choose another with --port)") from None
    sock.setblocking(False)
    return sock


async def stop_web(server: Any, task: asyncio.Task[None] | None, timeout_s: float = 5.0) -> None:
    """Stop what serve_web started (None: nothing was served): ask, wait up to timeout_s, cancel."""
    if server is None or task is None:
        return
    server.should_exit = True
    try:
        await asyncio.wait_for(task, timeout_s)
    except (asyncio.TimeoutError, Exception):
        task.cancel()


__all__ = ["GRACEFUL_SHUTDOWN_S", "serve_web", "stop_web"]
