"""A TCP proxy between a station and the real PostgreSQL on 127.0.0.1:5432 that the test can make
blink as a line's network and server do (issue 37), without touching the machine's server (other
tests use it in parallel):

- `restart(down_s)`: every connection is cut (RST) and new ones are refused for `down_s`: what a
  station sees of a PostgreSQL restart or a network cut;
- `hang()` / `resume()`: connections stay open and new ones are accepted, but no byte moves either
  way until resume(), when the held bytes go through in order: what a station sees of a stopped
  server (SIGSTOP, a hung host): the kernel keeps the connection, nobody answers.

Threads, blocking sockets: the proxy must keep its own time whatever the test's event loop does.
"""

from __future__ import annotations

import socket
import struct
import threading
import time


class PgProxy:
    def __init__(self, target: tuple[str, int] = ("127.0.0.1", 5432)) -> None:
        self.target = target
        self._srv = socket.create_server(("127.0.0.1", 0))
        self.port = int(self._srv.getsockname()[1])
        self._lock = threading.Lock()
        self._conns: list[tuple[socket.socket, socket.socket]] = []
        self._down_until = 0.0
        self._flowing = threading.Event()
        self._flowing.set()
        self._stop = threading.Event()
        self.accepted = 0
        threading.Thread(target=self._accept, name="pg-proxy", daemon=True).start()

    def url(self, database: str) -> str:
        return f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/{database}"

    # ---- faults -------------------------------------------------------------------------------
    def restart(self, down_s: float) -> None:
        with self._lock:
            self._down_until = time.monotonic() + down_s
            conns, self._conns = self._conns, []
        for a, b in conns:
            for s in (a, b):
                _reset(s)

    def hang(self) -> None:
        self._flowing.clear()

    def resume(self) -> None:
        self._flowing.set()

    def close(self) -> None:
        self._stop.set()
        self._flowing.set()
        self._srv.close()
        self.restart(0)

    # ---- relaying -----------------------------------------------------------------------------
    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self._srv.accept()
            except OSError:
                return
            if time.monotonic() < self._down_until:
                _reset(client)  # refused while "restarting"
                continue
            try:
                server = socket.create_connection(self.target, timeout=5)
                server.settimeout(None)
            except OSError:
                _reset(client)
                continue
            with self._lock:
                self._conns.append((client, server))
                self.accepted += 1
            for src, dst in ((client, server), (server, client)):
                threading.Thread(target=self._pipe, args=(src, dst), daemon=True).start()

    def _pipe(self, src: socket.socket, dst: socket.socket) -> None:
        try:
            while True:
                self._flowing.wait()
                data = src.recv(65536)
                if not data:
                    break
                self._flowing.wait()  # bytes read just before a hang are held too
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for s in (src, dst):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass


def _reset(s: socket.socket) -> None:
    """Cut a connection now: shutdown() first, since close() alone does not wake (nor close the
    connection of) a relay thread blocked in recv() on the same socket."""
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        s.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    try:
        s.close()
    except OSError:
        pass
