"""CAN board driver (design 3.2) over python-can: many boards on one bus, told apart by node id.

`CanBus` (drivers/can_bus.py, re-exported here) owns the one `can.Bus` and a reader thread (python-can's
blocking `recv`, so any interface works: socketcan, slcan on a serial port, virtual, ...). The thread
only queues raw frames; the event loop drains the queue in one callback per burst and dispatches by
node id to the registered `CanBoard`s. A bus failure faults every board on that bus (they all share it).
"""

from __future__ import annotations

import asyncio
import dataclasses

import numpy as np

from drivers.base import BoardDriver, CalibrationError, CalReadback, DriverError, LinkStats
from drivers.can_bus import MAX_UNREADABLE_IN_A_ROW as MAX_UNREADABLE_IN_A_ROW  # re-exported: callers import them here
from drivers.can_bus import CanBus as CanBus
from drivers.protocol import can_frames as cf
from drivers.protocol.stream_timeline import SeqTracker
from drivers.sample_buffer import MAX_PENDING_SAMPLES as MAX_PENDING_SAMPLES, Row, SampleBuffer
from contracts.types import Identity, SampleBlock

# A reply whose frames 0 and 1 hold a full 14-character serial may go on in frames 12/13 (issue 42):
# they are given this long after the base frames (a board sends them in the same burst; an old
# board with exactly 14 characters pays it once per identify, every other board nothing)
IDENT_EXT_GRACE_S = 0.1


def _columns(rows: list[Row]) -> tuple[np.ndarray, np.ndarray]:
    """A CAN row's time is already in seconds (the extended sample index / ODR)."""
    arr = np.array(rows, dtype=np.float64)
    return arr[:, 0], arr[:, 1:]


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
        self._ident_grace: asyncio.TimerHandle | None = None  # waiting for frames 12/13 (IDENT_EXT_GRACE_S)
        self._sends_health = False  # this node has sent identity frame 11: wait for it in every reply
        self._grace_s = IDENT_EXT_GRACE_S  # at most half of identify()'s time per try
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
            if data[0] == cf.IDENT_HEALTH_INDEX:
                self._sends_health = True
                self._late_health()
            if done and self._ident_fut is not None and not self._ident_fut.done():
                asm = self._ident
                if asm.waits_for_more or (self._sends_health and asm.health is None):
                    if self._ident_grace is None:
                        self._ident_grace = self._ident_fut.get_loop().call_later(self._grace_s, self._resolve_ident)
                else:
                    self._resolve_ident()
        elif func == cf.CMD_BASE:
            pass  # our own command echoed back by an interface
        else:
            self.stats.frames_malformed += 1

    def _resolve_ident(self) -> None:
        """The identity reply is in (or its grace for frames 11/12/13 is over): hand it to identify()."""
        if self._ident_grace is not None:
            self._ident_grace.cancel()
            self._ident_grace = None
        fut, asm = self._ident_fut, self._ident
        if fut is None or fut.done() or asm is None:
            return
        if asm.extension_incomplete:  # frame 12 without 13 (or 13 without 12): the serial is unknown
            self.stats.frames_malformed += 1
            self._ident = cf.IdentityAssembler()
            return
        try:
            ident = asm.identity(self.sensor)
        except ValueError:  # NaN/zero sensitivity or ODR: refuse, identify() asks again
            self.stats.frames_malformed += 1
            self._ident = cf.IdentityAssembler()
            return
        fut.set_result(ident)

    def _with_health(self, ident: Identity) -> Identity:
        """`ident` with frame 11's reset cause and record when the reply's frame 11 is in by now."""
        asm = self._ident
        if ident.reset_cause is None and asm is not None and asm.health is not None and asm.serial == ident.serial:
            cause, record = asm.health
            return dataclasses.replace(ident, reset_cause=cause, record=record)
        return ident

    def _late_health(self) -> None:
        """Frame 11 after identify() took the reply (a short serial's reply is taken at its base
        frames, so an old board waits for nothing): the driver's identity gets it."""
        if self._ident_fut is None and self.identity is not None:
            self.identity = self._with_health(self.identity)

    def _flush(self) -> None:
        self._held.flush()

    def _on_bus_error(self, error: DriverError) -> None:
        self._error = error
        if self._ident_grace is not None:
            self._ident_grace.cancel()
            self._ident_grace = None
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
        self._grace_s = min(IDENT_EXT_GRACE_S, per_try / 2)
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
                if self._ident_grace is not None:
                    self._ident_grace.cancel()
                    self._ident_grace = None
            ident = self._with_health(ident)  # frame 11 may have come while identify() resumed
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
