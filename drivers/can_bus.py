"""One CAN bus shared by many boards (design 3.2), over python-can: its reader thread and dispatch.

`CanBus` owns the one `can.Bus` and a reader thread (python-can's blocking `recv`, so any
interface works: socketcan, slcan on a serial port, virtual, ...; an slcan adapter's port is read
in bulk). The thread only queues raw frames; the event loop drains the queue in one callback per
burst and dispatches by node id to the registered boards (drivers/can_board.CanBoard, re-exported
there with this class). A bus failure faults every board on that bus (they all share it).
"""

from __future__ import annotations

import asyncio
import collections
import threading
import time
from typing import Any, Protocol

import can
import numpy as np

from drivers.base import DriverError
from drivers.protocol import can_frames as cf
from drivers.protocol.slcan_lines import FrameRun, drop_partial_line, is_line_noise, pop_merged
from drivers.protocol.slcan_lines import split_frame_runs, split_frames

MAX_UNREADABLE_IN_A_ROW = 1000  # then it is not noise but a broken adapter: fail the bus


class CanNode(Protocol):
    """What the bus needs of a board on it (drivers/can_board.CanBoard is one)."""

    node_id: int

    def _on_frame(self, func: int, data: bytes) -> None: ...

    def _on_samples(self, data: np.ndarray, counts: np.ndarray, seq: np.ndarray) -> None: ...

    def _flush(self) -> None: ...

    def _on_bus_error(self, error: DriverError) -> None: ...


class CanBus:
    """One CAN bus shared by many boards.

    interface/channel/bitrate go to `can.Bus`; extra keyword arguments too (e.g.
    `sleep_after_open=0` for slcan on a simulated adapter, `receive_own_messages`).
    """

    def __init__(self, interface: str, channel: str, bitrate: int | None = 500_000, **bus_kwargs: Any) -> None:
        self.interface = interface
        self.channel = channel
        self.bitrate = bitrate
        self.bus_kwargs = bus_kwargs
        self.bus: can.BusABC | None = None
        self._boards: dict[int, CanNode] = {}
        self._inbox: collections.deque[tuple[int, bytes] | FrameRun] = collections.deque()
        self._frames_queued = 0  # into the inbox (the reader thread); frames_rx: out of it (the loop)
        self.bulk = True  # runs of clean sample frames in bulk (numpy); False: frame by frame
        self._wake_pending = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._running = False
        self._open_lock: asyncio.Lock | None = None
        self.error: DriverError | None = None
        self.frames_rx = 0
        self.frames_foreign = 0  # ids no registered board claims
        self.frames_unreadable = 0  # garbled adapter lines (e.g. slcan noise), skipped
        self.last_rx_wall = 0.0  # time.monotonic() of the latest frames handed to the boards

    def __repr__(self) -> str:
        return f"CanBus({self.interface!r}, {self.channel!r})"

    async def open(self) -> None:
        """Idempotent: every board on the bus may call it."""
        if self._open_lock is None:
            self._open_lock = asyncio.Lock()
        async with self._open_lock:
            if self.bus is not None:
                return
            self._loop = asyncio.get_running_loop()
            kwargs = dict(self.bus_kwargs)
            if self.bitrate is not None:
                kwargs["bitrate"] = self.bitrate
            try:
                self.bus = await asyncio.to_thread(
                    can.Bus, interface=self.interface, channel=self.channel, **kwargs
                )
            except Exception as exc:  # python-can raises many kinds (CanError, OSError, ValueError)
                raise DriverError(f"cannot open CAN bus {self.interface}:{self.channel}: {exc}") from exc
            self.error = None
            self._running = True
            self._thread = threading.Thread(target=self._reader, name=f"can-{self.channel}", daemon=True)
            self._thread.start()

    def _reader(self) -> None:
        port = getattr(self.bus, "serialPortOrig", None) if self.interface == "slcan" else None
        if port is not None and hasattr(port, "in_waiting"):
            self._read_slcan_bulk(port)
        else:
            self._read_python_can()

    def _read_slcan_bulk(self, port: Any) -> None:
        """The slcan adapter's port read in bulk: whatever it holds in one call, lines split by
        drivers/protocol/slcan_lines.py (python-can reads it a byte per call: ~40 % of the daemon's
        CPU with 16 CAN boards). Writes still go through python-can (`bus.send`)."""
        loop = self._loop
        assert loop is not None
        buf = bytearray()
        noise_in_a_row = 0
        try:
            port.timeout = 0.1  # block for the first byte up to 0.1 s: no busy polling when idle
        except Exception:  # noqa: BLE001 - a port that cannot change it keeps python-can's
            pass
        while self._running:
            try:
                chunk = port.read(1)
                if chunk:
                    waiting = port.in_waiting
                    chunk += port.read(waiting) if waiting else b""
            except Exception as exc:  # noqa: BLE001 - the port is gone (pyserial raises OSError/SerialException)
                if self._running:
                    loop.call_soon_threadsafe(self._fail, f"CAN bus {self.channel} failed: {exc}")
                return
            if not chunk:
                continue
            buf += chunk
            frames, garbled = self._ingest(buf)
            noise_in_a_row = 0 if frames else noise_in_a_row + garbled
            if noise_in_a_row >= MAX_UNREADABLE_IN_A_ROW:
                loop.call_soon_threadsafe(self._fail, f"CAN bus {self.channel} failed: {noise_in_a_row} "
                                          "unreadable adapter lines in a row")
                return
            if frames and not self._wake(loop):
                return

    def _ingest(self, buf: bytearray) -> tuple[int, int]:
        """The complete slcan lines of `buf` into the inbox (clean runs as one FrameRun each in bulk)."""
        items, garbled = split_frame_runs(buf) if self.bulk else split_frames(buf)
        self.frames_unreadable += garbled
        n = sum(len(it) if isinstance(it, FrameRun) else 1 for it in items)
        self._inbox.extend(items)
        self._frames_queued += n
        return n, garbled

    def _read_python_can(self) -> None:
        bus, loop = self.bus, self._loop
        assert bus is not None and loop is not None
        noise_in_a_row = 0
        while self._running:
            try:
                msg = bus.recv(0.1)
            except Exception as exc:  # noqa: BLE001 - line noise (counted) or the bus is gone
                if self._running and is_line_noise(exc) and noise_in_a_row < MAX_UNREADABLE_IN_A_ROW:
                    noise_in_a_row += 1
                    self.frames_unreadable += 1
                    drop_partial_line(bus)
                    continue
                if self._running:
                    loop.call_soon_threadsafe(self._fail, f"CAN bus {self.channel} failed: {exc}")
                return
            noise_in_a_row = 0
            if msg is None or msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
                continue
            self._inbox.append((msg.arbitration_id, bytes(msg.data)))
            self._frames_queued += 1
            if not self._wake(loop):
                return

    def _wake(self, loop: asyncio.AbstractEventLoop) -> bool:
        """From the reader thread: have the loop drain the inbox (once per batch of frames).
        False when the loop is closed (the reader ends)."""
        if not self._wake_pending:
            self._wake_pending = True
            try:
                loop.call_soon_threadsafe(self._drain)
            except RuntimeError:  # loop closed
                return False
        return True

    def _drain(self) -> None:
        self._wake_pending = False
        self.last_rx_wall = time.monotonic()
        touched: set[CanNode] = set()
        while self._inbox:  # runs (FrameRun) and single frames, in arrival order
            item = pop_merged(self._inbox)
            if isinstance(item, FrameRun):
                self._dispatch_run(item, touched)
            else:
                self._dispatch(item[0], item[1], touched)
        for board in touched:
            board._flush()

    def _dispatch(self, arb_id: int, data: bytes, touched: set[CanNode]) -> None:
        """One frame to its board by node id (the one definition; the bulk path's fallback)."""
        self.frames_rx += 1
        board = self._boards.get(arb_id & 0x7F)
        if board is None:
            self.frames_foreign += 1
            return
        board._on_frame(arb_id & 0x780, data)
        touched.add(board)

    def _dispatch_run(self, run: FrameRun, touched: set[CanNode]) -> None:
        """A FrameRun as `_dispatch` would take it frame by frame, but each board's sample frames
        a run at a time (cf.route_run: the order that matters is kept)."""
        for step in cf.route_run(run.ids, run.data):
            if isinstance(step, int):
                self._dispatch(*run.frame(step), touched)
                continue
            self.frames_rx += len(step.seq)
            if (board := self._boards.get(step.node)) is None:
                self.frames_foreign += len(step.seq)
                continue
            board._on_samples(step.data, step.counts, step.seq)
            touched.add(board)

    def _fail(self, message: str) -> None:
        if self.error is None:
            self.error = DriverError(message)
        self._running = False
        for board in list(self._boards.values()):
            board._on_bus_error(self.error)

    def register(self, board: CanNode) -> None:
        if board.node_id in self._boards and self._boards[board.node_id] is not board:
            raise DriverError(f"CAN node {board.node_id} already has a driver on {self.channel}")
        self._boards[board.node_id] = board

    def unregister(self, board: CanNode) -> None:
        if self._boards.get(board.node_id) is board:
            del self._boards[board.node_id]

    async def send(self, arbitration_id: int, data: bytes) -> None:
        if self.error is not None:
            raise self.error
        if self.bus is None:
            raise DriverError(f"CAN bus {self.channel} is not open")
        msg = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False)
        try:
            await asyncio.to_thread(self.bus.send, msg, 1.0)
        except Exception as exc:  # noqa: BLE001
            raise DriverError(f"CAN send on {self.channel} failed: {exc}") from exc

    async def close(self) -> None:
        self._running = False
        if self._thread is not None:
            await asyncio.to_thread(self._thread.join, 2.0)
            self._thread = None
        bus, self.bus = self.bus, None
        if bus is not None:
            try:
                await asyncio.to_thread(bus.shutdown)
            except Exception:  # noqa: BLE001 - shutting down a failed bus
                pass

    async def __aenter__(self) -> "CanBus":
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()
