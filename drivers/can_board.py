"""CAN board driver (design 3.2) over python-can: many boards on one bus, told apart by node id.

`CanBus` owns the one `can.Bus` and a reader thread (python-can's blocking `recv`, so any
interface works: socketcan, slcan on a serial port, virtual, ...). The thread only queues raw
frames; the event loop drains the queue in one callback per burst and dispatches by node id to
the registered `CanBoard`s. A bus failure faults every board on that bus (they all share it).
"""

from __future__ import annotations

import asyncio
import collections
import dataclasses
import threading
import time
from typing import Any

import can
import numpy as np

from drivers.base import BoardDriver, CalibrationError, CalReadback, DriverError, LinkStats
from drivers.protocol import can_frames as cf
from drivers.protocol.slcan_lines import FrameRun, drop_partial_line, is_line_noise, pop_merged
from drivers.protocol.slcan_lines import split_frame_runs, split_frames
from drivers.protocol.stream_timeline import SeqTracker
from drivers.sample_buffer import MAX_PENDING_SAMPLES as MAX_PENDING_SAMPLES, Row, SampleBuffer
from contracts.types import Identity, SampleBlock

MAX_UNREADABLE_IN_A_ROW = 1000  # then it is not noise but a broken adapter: fail the bus


def _columns(rows: list[Row]) -> tuple[np.ndarray, np.ndarray]:
    """A CAN row's time is already in seconds (the extended sample index / ODR)."""
    arr = np.array(rows, dtype=np.float64)
    return arr[:, 0], arr[:, 1:]


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
        self._boards: dict[int, CanBoard] = {}
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
        touched: set[CanBoard] = set()
        while self._inbox:  # runs (FrameRun) and single frames, in arrival order
            item = pop_merged(self._inbox)
            if isinstance(item, FrameRun):
                self._dispatch_run(item, touched)
            else:
                self._dispatch(item[0], item[1], touched)
        for board in touched:
            board._flush()

    def _dispatch(self, arb_id: int, data: bytes, touched: set["CanBoard"]) -> None:
        """One frame to its board by node id (the one definition; the bulk path's fallback)."""
        self.frames_rx += 1
        board = self._boards.get(arb_id & 0x7F)
        if board is None:
            self.frames_foreign += 1
            return
        board._on_frame(arb_id & 0x780, data)
        touched.add(board)

    def _dispatch_run(self, run: FrameRun, touched: set["CanBoard"]) -> None:
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

    def register(self, board: "CanBoard") -> None:
        if board.node_id in self._boards and self._boards[board.node_id] is not board:
            raise DriverError(f"CAN node {board.node_id} already has a driver on {self.channel}")
        self._boards[board.node_id] = board

    def unregister(self, board: "CanBoard") -> None:
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


class CanBoard(BoardDriver):
    """One CAN board by node id. Time is the extended sample index / ODR (the frame has no clock).

    The board sends no acknowledgements: START/STOP/SET_ODR are fire-and-forget; identify()
    retries until the four identity frames are in or timeout_s ends. `sensor` names the sensor
    when known from configuration (the CAN identity has no sensor field; otherwise guessed from
    ug_per_lsb).
    """

    def __init__(self, bus: CanBus, node_id: int, *, sensor: str | None = None, retries: int = 3,
                 cal_timeout_s: float = 2.0) -> None:
        self.bus = bus
        self.node_id = cf.check_node(node_id)
        self.sensor = sensor
        self.retries = max(1, int(retries))
        self.stats = LinkStats()
        self.identity: Identity | None = None
        self._seq = SeqTracker(8)
        self._odr_hz: float | None = None
        self._time_base_s = 0.0
        self._index_base = 0
        self._held = SampleBuffer(self.stats, _columns)  # time: seconds from the sample index
        self._ident: cf.IdentityAssembler | None = None
        self._ident_fut: asyncio.Future[Identity] | None = None
        self._error: DriverError | None = None
        self._opened = False
        self.cal_timeout_s = cal_timeout_s
        self._cal_fut: asyncio.Future[cf.CalStatus] | None = None
        self._cal_fields: list[float | None] = [None] * cf.N_CAL_FIELDS
        self._cal_lock = asyncio.Lock()

    @property  # type: ignore[override]
    def last_rx_wall(self) -> float:
        """The whole bus: a reply waits behind every node's frames, not only this node's."""
        return self.bus.last_rx_wall

    @last_rx_wall.setter
    def last_rx_wall(self, value: float) -> None:
        pass

    def __repr__(self) -> str:
        return f"CanBoard({self.bus.channel!r}, node={self.node_id})"

    async def open(self) -> None:
        self._held.renew()
        await self.bus.open()
        self.bus.register(self)
        self._opened = True
        self._error = None

    # ---- frames (called in the loop by CanBus._drain) --------------------------------------
    def _on_samples(self, data: np.ndarray, counts: np.ndarray, seq: np.ndarray) -> None:
        """Sample frames (n, 8) uint8 (cf.decode_samples) in order as `_on_frame` takes them, a stretch that
        goes on (cf.seq_stretches; ODR known) at once with numpy, the rest through `_on_frame` (the one definition)."""
        for a, b, clean in cf.seq_stretches(seq, self._seq.last):  # each _on_frame sets _seq.last
            odr = self._odr_hz or (self.identity.odr_hz if self.identity else 0.0)
            if not (clean and odr and self.bus.bulk):
                for k in range(a, b):
                    self._on_frame(cf.SAMPLE_BASE, data[k].tobytes())
                continue
            index = self._seq.index + np.arange(1, b - a + 1, dtype=np.int64)
            t = self._time_base_s + (index - self._index_base) / odr  # as _on_frame, to the bit
            self._seq.index, self._seq.last = int(index[-1]), int(seq[b - 1])
            self.stats.frames_ok += b - a
            self._held.add_columns(t, counts[a:b])
            self.last_sample_t = float(t[-1])

    def _on_frame(self, func: int, data: bytes) -> None:
        if func == cf.SAMPLE_BASE:
            try:
                s = cf.decode_sample(data)
            except ValueError:
                self.stats.frames_malformed += 1
                return
            self.stats.frames_ok += 1
            lost = self._seq.update(s.seq)
            if lost:
                self._held.count_lost(lost)
            odr = self._odr_hz or (self.identity.odr_hz if self.identity else 0.0)
            if not odr:
                self.stats.frames_malformed += 1  # cannot time a sample without an ODR
                return
            t = self._time_base_s + (self._seq.index - self._index_base) / odr
            self._held.add((t, s.ax, s.ay, s.az, s.t))
            self.last_sample_t = t
        elif func == cf.IDENT_BASE and cf.is_cal_reply(data):
            try:
                idx, value = cf.decode_cal_reply(data)
            except ValueError:
                self.stats.frames_malformed += 1
                return
            self.stats.frames_ok += 1
            if idx == cf.CAL_STATUS_INDEX:
                if self._cal_fut is not None and not self._cal_fut.done():
                    self._cal_fut.set_result(value)  # type: ignore[arg-type]
            else:
                self._cal_fields[idx - cf.CAL_FIELD_INDEX0] = value  # type: ignore[assignment]
        elif func == cf.IDENT_BASE:
            if self._ident is None:
                self._ident = cf.IdentityAssembler()
            try:
                done = self._ident.feed(data)
            except ValueError:
                self.stats.frames_malformed += 1
                return
            self.stats.frames_ok += 1
            if done and self._ident_fut is not None and not self._ident_fut.done():
                try:
                    ident = self._ident.identity(self.sensor)
                except ValueError:  # NaN/zero sensitivity or ODR: refuse, identify() asks again
                    self.stats.frames_malformed += 1
                    self._ident = cf.IdentityAssembler()
                    return
                self._ident_fut.set_result(ident)
        elif func == cf.CMD_BASE:
            pass  # our own command echoed back by an interface
        else:
            self.stats.frames_malformed += 1

    def _flush(self) -> None:
        self._held.flush()

    def _on_bus_error(self, error: DriverError) -> None:
        self._error = error
        for fut in (self._ident_fut, self._cal_fut):
            if fut is not None and not fut.done():
                fut.set_exception(error)
        self._held.wake()

    def _check(self) -> None:
        if self._error is not None:
            raise self._error
        if not self._opened:
            raise DriverError(f"CAN node {self.node_id} is not open")

    async def _send(self, data: bytes) -> None:
        self._check()
        await self.bus.send(cf.CMD_BASE + self.node_id, data)

    # ---- commands --------------------------------------------------------------------------
    async def identify(self, timeout_s: float = 2.0) -> Identity:
        self._check()
        loop = asyncio.get_running_loop()
        per_try = timeout_s / self.retries
        for _ in range(self.retries):
            self._ident = cf.IdentityAssembler()
            self._ident_fut = loop.create_future()
            await self._send(cf.encode_command(cf.CMD_IDENTIFY))
            try:
                ident = await asyncio.wait_for(asyncio.shield(self._ident_fut), per_try)
            except asyncio.TimeoutError:
                continue
            finally:
                self._ident_fut = None
            self._rebase(ident.odr_hz)
            self.identity = ident
            return ident
        self._check()
        raise DriverError(f"no identity reply from CAN node {self.node_id} on {self.bus.channel} within {timeout_s:g} s")

    def _rebase(self, odr_hz: float) -> None:
        """Keep time continuous when the sample rate changes: new samples count from here."""
        if self._odr_hz and self._odr_hz != odr_hz:
            self._time_base_s += (self._seq.index - self._index_base) / self._odr_hz
            self._index_base = self._seq.index
        self._odr_hz = odr_hz

    async def start(self) -> None:
        if self.identity is None:
            await self.identify()
        await self._send(cf.encode_command(cf.CMD_START))

    def backlog_samples(self) -> int:
        """Its queue, and its share of the frames the bus's reader took in and the loop has not
        dispatched yet (one adapter's inbox for every board on it)."""
        boards = max(1, len(self.bus._boards))
        return len(self._held) + max(0, self.bus._frames_queued - self.bus.frames_rx) // boards

    def discard_held(self) -> int:
        return self._held.discard()

    async def stop(self) -> None:
        await self._send(cf.encode_command(cf.CMD_STOP))

    async def set_odr(self, odr_hz: float) -> None:
        await self._send(cf.encode_command(cf.CMD_SET_ODR, odr_hz))
        self._rebase(float(odr_hz))
        if self.identity is not None:
            self.identity = dataclasses.replace(self.identity, odr_hz=float(odr_hz))

    # ---- calibration write-back (one attempt each; BoardDriver.program_thermal retries) ------
    async def _cal_status(self, frames: list[bytes], what: str) -> cf.CalStatus:
        """Send frames, wait for the index-4 status reply; one attempt."""
        self._check()
        loop = asyncio.get_running_loop()
        self._cal_fut = loop.create_future()
        try:
            for data in frames:
                await self._send(data)
            return await asyncio.wait_for(asyncio.shield(self._cal_fut), self.cal_timeout_s)
        except asyncio.TimeoutError:
            self._check()
            raise CalibrationError("no_reply", f"no {what} status from CAN node {self.node_id} within "
                                   f"{self.cal_timeout_s:g} s") from None
        finally:
            self._cal_fut = None

    async def write_thermal(self, tdb_mg_per_c, tdsf_ppm_per_c) -> int:
        from drivers.protocol.cal_record import crc32_f32, to_f32

        vals = to_f32([*tdb_mg_per_c, *tdsf_ppm_per_c])
        frames = [cf.encode_cal_field(k, v) for k, v in enumerate(vals)] + [cf.encode_cal_commit(crc32_f32(vals))]
        async with self._cal_lock:
            st = await self._cal_status(frames, "CAL_COMMIT")
        refusal = cf.commit_refusal(st.status)
        if refusal is not None:
            raise CalibrationError(refusal[0], f"CAN node {self.node_id}: {refusal[1]}")
        return st.crc

    async def read_thermal(self) -> CalReadback:
        async with self._cal_lock:
            self._cal_fields = [None] * cf.N_CAL_FIELDS
            st = await self._cal_status([cf.encode_cal_read()], "CAL_READ")
            fields = list(self._cal_fields)
        if any(v is None for v in fields):
            missing = [k for k, v in enumerate(fields) if v is None]
            raise CalibrationError("no_reply", f"CAN node {self.node_id}: stored field(s) {missing} missing in the read-back")
        return CalReadback(tuple(float(v) for v in fields), st.crc, st.comp)  # type: ignore[arg-type]

    async def set_compensation(self, on: bool) -> None:
        """COMP has no reply in 3.2: program_thermal confirms it with CAL_READ (comp byte)."""
        await self._send(cf.encode_comp(on))

    # ---- samples ---------------------------------------------------------------------------
    async def read_block(self, timeout_s: float = 1.0) -> SampleBlock:
        await self._held.wait(timeout_s, self._check, lambda: self._error)
        return self._held.take_block(self.identity)

    async def close(self) -> None:
        self.bus.unregister(self)
        self._opened = False
