"""HTTP connection limits of the station's web server: slow clients cannot hold it.

uvicorn closes an idle keep-alive connection (`timeout_keep_alive`) but has no timeout for a
request head that never ends, and no cap on open connections: 1,100 half-sent requests held a
station at a 1,024 open-file limit for as long as the sender liked, and asyncio logged the failed
accept() with a traceback per attempt (hundreds of MB in seconds). Here:

- `GuardedH11Protocol` (uvicorn's h11 protocol, handed over as `uvicorn.Config(http=...)`): a
  connection waiting for a request head (a new one, or a keep-alive one between requests) must
  complete it within `header_timeout_s` from the moment it started waiting, whatever it trickles
  in the meantime; otherwise it is answered 408 (if it sent part of a head) and closed. A complete
  head stops the clock; a request being served is never timed out here.
- `HttpGuard.max_connections`: a new connection beyond the cap evicts the connection that has been
  waiting longest for a request head (a slowloris, or an idle keep-alive one), so a health probe
  or the operator page still gets in; when every connection is busy with a request, the new one
  is answered 503 and closed. The open sockets of HTTP stay below the cap plus one accept batch
  (`uvicorn.Config(backlog=...)`), well inside the process's file limit: the cap is lowered to fit
  RLIMIT_NOFILE minus `reserve_fds` (boards, database, log files).
- `AcceptErrorFilter` on the "asyncio" logger: "socket.accept() out of system resource" (EMFILE,
  ENFILE, ...) is one line per `interval_s` with the number of repeats it stood for, not one
  traceback per attempt.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

log = logging.getLogger(__name__)

DEFAULT_HEADER_TIMEOUT_S = 10.0
DEFAULT_KEEP_ALIVE_S = 5
DEFAULT_MAX_CONNECTIONS = 512
DEFAULT_RESERVE_FDS = 256  # boards, Modbus, database, logs, subprocess pipes: never HTTP's
ACCEPT_BATCH = 128  # listen backlog = most sockets one loop tick accepts before a protocol sees them

_TIMEOUT_408 = (b"HTTP/1.1 408 Request Timeout\r\ncontent-type: text/plain; charset=utf-8\r\n"
                b"connection: close\r\ncontent-length: 37\r\n\r\nrequest head not complete in time\r\n\r\n")
_FULL_503 = (b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: text/plain; charset=utf-8\r\n"
             b"connection: close\r\nretry-after: 1\r\ncontent-length: 30\r\n\r\ntoo many open HTTP connections")
assert int(_TIMEOUT_408.split(b"content-length: ")[1].split(b"\r\n")[0]) == len(_TIMEOUT_408.split(b"\r\n\r\n", 1)[1])
assert int(_FULL_503.split(b"content-length: ")[1].split(b"\r\n")[0]) == len(_FULL_503.split(b"\r\n\r\n", 1)[1])


def fd_limit() -> int | None:
    """The soft RLIMIT_NOFILE of this process (None where unknown)."""
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    except (ImportError, OSError, ValueError):
        return None
    return None if soft == resource.RLIM_INFINITY else int(soft)


class HttpGuard:
    """The limits and the open connections of one server (shared by its protocol instances)."""

    def __init__(self, *, header_timeout_s: float = DEFAULT_HEADER_TIMEOUT_S,
                 max_connections: int = DEFAULT_MAX_CONNECTIONS, reserve_fds: int = DEFAULT_RESERVE_FDS,
                 accept_batch: int = ACCEPT_BATCH) -> None:
        self.header_timeout_s = float(header_timeout_s)
        self.max_connections = int(max_connections)
        limit = fd_limit()
        if limit is not None:
            fits = max(8, limit - int(reserve_fds) - int(accept_batch))
            if fits < self.max_connections:
                log.warning("HTTP: at most %d open connections (open-file limit %d minus %d reserved; "
                            "http.max_connections is %d)", fits, limit, reserve_fds + accept_batch,
                            self.max_connections)
                self.max_connections = fits
        self.open: set[GuardedH11Protocol] = set()
        # connections waiting for a request head -> when they started waiting; oldest first
        self.waiting: dict[GuardedH11Protocol, float] = {}
        self.evicted = 0
        self.timed_out = 0
        self.refused = 0

    def protocol_class(self) -> type[GuardedH11Protocol]:
        """A protocol class bound to this guard, for `uvicorn.Config(http=...)`."""
        return type("GuardedH11Protocol", (GuardedH11Protocol,), {"guard": self})

    def stats(self) -> dict[str, int]:
        return {"open": len(self.open), "waiting_for_head": len(self.waiting), "max_connections": self.max_connections,
                "evicted": self.evicted, "timed_out": self.timed_out, "refused": self.refused}

    def admit(self, proto: GuardedH11Protocol) -> bool:
        """Room for a new connection: evict the one waiting longest for its head if full; False if
        every open connection is busy with a request (the new one is refused)."""
        while len(self.open) >= self.max_connections:
            if not self.waiting:
                self.refused += 1
                return False
            oldest = next(iter(self.waiting))
            self.evicted += 1
            oldest.drop()
        self.open.add(proto)
        return True


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with a request-head timeout and the connection cap of its `guard`."""

    guard: HttpGuard

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._head_timer: asyncio.TimerHandle | None = None

    # -- asyncio.Protocol ------------------------------------------------------------------------
    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        if not self.guard.admit(self):
            self.transport = transport
            transport.write(_FULL_503)
            transport.close()
            if transport.get_write_buffer_size():
                transport.abort()
            return  # uvicorn never sees it: no state, no timers
        super().connection_made(transport)
        self._sync()

    def connection_lost(self, exc: Exception | None) -> None:
        if self not in self.guard.open and self.flow is None:  # refused in connection_made
            return
        self._stop_waiting()
        self.guard.open.discard(self)
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self not in self.guard.open:  # dropped, closing: nothing more is read
            return
        super().data_received(data)

    # -- uvicorn's hooks: after each, is the connection waiting for a request head? ----------------
    def handle_events(self) -> None:
        super().handle_events()
        self._sync()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._sync()

    def _sync(self) -> None:
        if self.transport is None or self.transport.is_closing():
            self._stop_waiting()
            return
        # h11's client state is IDLE until a request head is complete; once our answer is sent the
        # connection serves nobody until the client's next head (or the rest of an unread body).
        waiting = self.conn.their_state is h11.IDLE or self.conn.our_state in (h11.DONE, h11.MUST_CLOSE)
        if waiting and self._head_timer is None:
            self.guard.waiting[self] = time.monotonic()
            self._head_timer = self.loop.call_later(self.guard.header_timeout_s, self._head_timeout)
        elif not waiting and self._head_timer is not None:
            self._stop_waiting()

    def _stop_waiting(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None
        self.guard.waiting.pop(self, None)

    def _head_timeout(self) -> None:
        self._head_timer = None
        self.guard.timed_out += 1
        partial = bool(self.conn.trailing_data[0]) and self.conn.their_state is h11.IDLE
        self.drop(_TIMEOUT_408 if partial else b"")

    def drop(self, last_words: bytes = b"") -> None:
        """Close now (eviction, head timeout): the socket is freed even if the peer reads nothing."""
        self._stop_waiting()
        self.guard.open.discard(self)
        self._unset_keepalive_if_required()
        if self.transport.is_closing():
            return
        if last_words:
            self.transport.write(last_words)
        if self.transport.get_write_buffer_size():
            self.transport.abort()
        else:
            self.transport.close()


class AcceptErrorFilter(logging.Filter):
    """asyncio's "socket.accept() out of system resource" at most once per `interval_s`, one line
    with the number of repeats it stands for; other records pass untouched."""

    MESSAGE = "socket.accept() out of system resource"

    def __init__(self, interval_s: float = 10.0) -> None:
        super().__init__("asyncio")
        self.interval_s = float(interval_s)
        self._last = -float("inf")
        self.suppressed = 0

    def filter(self, record: logging.LogRecord) -> bool:
        if not (isinstance(record.msg, str) and record.msg.startswith(self.MESSAGE)):
            return True
        now = time.monotonic()
        if now - self._last < self.interval_s:
            self.suppressed += 1
            return False
        exc = record.exc_info[1] if record.exc_info else None
        text = f"{self.MESSAGE}: {exc}" if exc is not None else self.MESSAGE
        if self.suppressed:
            text += f" ({self.suppressed} more in the last {now - self._last:.0f} s not logged)"
        text += f"; logged at most once per {self.interval_s:g} s"
        record.msg, record.args, record.exc_info, record.exc_text = text, None, None, None
        self._last, self.suppressed = now, 0
        return True


def install_accept_error_filter(interval_s: float = 10.0) -> AcceptErrorFilter:
    """Put the filter on the "asyncio" logger once per process (idempotent); returns it."""
    logger = logging.getLogger("asyncio")
    for f in logger.filters:
        if isinstance(f, AcceptErrorFilter):
            return f
    f = AcceptErrorFilter(interval_s)
    logger.addFilter(f)
    return f


__all__ = ["HttpGuard", "GuardedH11Protocol", "AcceptErrorFilter", "install_accept_error_filter", "fd_limit",
           "DEFAULT_HEADER_TIMEOUT_S", "DEFAULT_KEEP_ALIVE_S", "DEFAULT_MAX_CONNECTIONS", "ACCEPT_BATCH"]
