"""Simulated CAN boards behind a simulated slcan (Lawicel) adapter on a pseudo-terminal.

The station side is python-can unmodified: `can.Bus(interface="slcan", channel=<pty path>)`.
Here is the device side of the adapter (ASCII commands ending in CR: S0..S8, O, L, C, V, N, F,
Z, t/T/r/R frames) and the firmware of the boards on the simulated bus (design 3.2).
`VirtualCanBridge` puts the same boards on a python-can `virtual` channel instead.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable

import can
import numpy as np

from drivers.protocol import can_frames as cf
from drivers.protocol.cal_record import crc32_f32
from drivers.sim.board_nvm import CalFirmware, flip_bit
from drivers.sim.serial_pty import PtyEndpoint, _ratio
from contracts.types import Identity

SendFn = Callable[[int, bytes], None]


def can_scale(identity: Identity) -> tuple[int, float]:
    """(right shift, CAN ug/LSB): a sensor wider than int16 is shifted down to fit +-1.9 g."""
    shift = 0
    ug = identity.ug_per_lsb
    while ug * (1 << shift) * 32767 < 1.9e6:
        shift += 1
    return shift, ug * (1 << shift)


class SimCanBoard:
    """Firmware of one CAN board: commands in, identity and sample frames out via `send`.

    Calibration (design 3.2, 0x05-0x08): CAL_FIELD fills RAM, CAL_COMMIT stores the six fields
    in `cal.nvm` only if the board's own CRC of what it received matches the commit CRC; the
    NVM survives `power_cycle()`. Write-path faults: `cal.flip_next_write` (a field arrives with
    a bit flipped: CRC mismatch), `cal.refuse_writes` (write failed), `cal.drop_replies`.
    """

    def __init__(self, node_id: int, identity: Identity, send: SendFn | None = None) -> None:
        self.node_id = cf.check_node(node_id)
        self.identity = identity
        self.send = send
        self.source_odr_hz = identity.odr_hz
        self.odr_hz = identity.odr_hz
        self.shift, self.ug_per_lsb = can_scale(identity)
        self.streaming = False
        self.muted = False
        self.compensates = True  # False: fed counts are the board's recorded output (see SimSerialBoard)
        self.seq = 0
        self._decim = 1
        self._phase = 0
        self._corrupt = 0
        self.connected = True
        self.commands: list[bytes] = []
        self.on_stop: Callable[[], None] | None = None  # as SimSerialBoard.on_stop
        self.frames_sent = 0
        self.cal = CalFirmware()
        self._fields: list[float | None] = [None] * cf.N_CAL_FIELDS
        self.power_cycles = 0

    def power_cycle(self) -> None:
        """The board restarts: RAM state (streaming, seq, ODR, received fields) lost, NVM kept."""
        self.streaming = False
        self.seq = 0
        self._decim, self._phase = 1, 0
        self.odr_hz = self.source_odr_hz
        self._fields = [None] * cf.N_CAL_FIELDS
        self.power_cycles += 1

    # ---- faults ----------------------------------------------------------------------------
    def inject_garbage(self, data: bytes) -> None:
        """A frame with this node's sample id but a wrong length (counted malformed)."""
        if self.send is not None and self.connected:
            self.send(cf.SAMPLE_BASE + self.node_id, bytes(data)[:7] or b"\0")

    def corrupt_next(self, n: int = 1) -> None:
        """CAN has a CRC: a corrupted frame never arrives. The next n sample frames are lost."""
        self._corrupt += int(n)

    def stop_streaming(self) -> None:
        self.muted = True

    def disconnect(self) -> None:
        """Board unplugged from the bus: silent from now on."""
        self.connected = False

    # ---- bus side --------------------------------------------------------------------------
    def on_frame(self, arb_id: int, data: bytes) -> None:
        if arb_id != cf.CMD_BASE + self.node_id or not self.connected:
            return
        self.commands.append(bytes(data))
        if data and cf.CMD_CAL_FIELD <= data[0] <= cf.CMD_COMP:
            self._calibration(bytes(data))
            return
        try:
            cmd, odr = cf.decode_command(data)
        except ValueError:
            return
        if cmd == cf.CMD_START:
            self.streaming = True
        elif cmd == cf.CMD_STOP:
            self.streaming = False
            if self.on_stop is not None:
                self.on_stop()
        elif cmd == cf.CMD_IDENTIFY:
            for payload in cf.encode_identity(self.identity.serial, self.ug_per_lsb, self.odr_hz):
                self._out(cf.IDENT_BASE + self.node_id, payload)
        elif cmd == cf.CMD_SET_ODR and odr is not None:
            k = _ratio(self.source_odr_hz, odr)
            if k is not None:
                self._decim, self._phase = k, 0
                self.odr_hz = self.source_odr_hz / k

    def _calibration(self, data: bytes) -> None:
        try:
            c = cf.decode_cal_command(data)
        except ValueError:
            return
        cal = self.cal
        reply = cf.IDENT_BASE + self.node_id
        if c.cmd == cf.CMD_CAL_FIELD:
            assert c.field is not None and c.value is not None
            value = c.value
            if cal.flip and cal.flip[0][0] % cf.N_CAL_FIELDS == c.field:  # flipped on the way in
                _, bit = cal.flip.pop(0)
                value = flip_bit(value, bit)
                cal.flips_done += 1
            self._fields[c.field] = value
        elif c.cmd == cf.CMD_CAL_COMMIT:
            got = self._fields
            if any(v is None for v in got) or crc32_f32(got) != c.crc:
                status = cf.CAL_CRC_MISMATCH
            elif cal.take_refuse():
                status = cf.CAL_WRITE_FAILED
            else:
                cal.store_thermal(got)
                status = cf.CAL_STORED
            self._fields = [None] * cf.N_CAL_FIELDS
            if not cal.take_drop():
                self._out(reply, cf.encode_cal_status(status, cal.nvm.comp, cal.nvm.thermal_crc))
        elif c.cmd == cf.CMD_CAL_READ:
            if cal.take_drop():
                return
            for k, v in enumerate(cal.nvm.thermal):
                self._out(reply, cf.encode_cal_stored_field(k, v))
            self._out(reply, cf.encode_cal_status(cf.CAL_STORED, cal.nvm.comp, cal.readback_crc()))
        elif c.cmd == cf.CMD_COMP:
            cal.nvm.comp = bool(c.on)  # no reply in 3.2: the station confirms with CAL_READ

    def _out(self, arb_id: int, payload: bytes) -> None:
        if self.send is not None:
            self.send(arb_id, payload)
            self.frames_sent += 1

    def feed(self, time_s: np.ndarray, acc_counts: np.ndarray, temp_counts: np.ndarray) -> None:
        n = len(time_s)
        if n == 0 or not self.streaming or self.muted or not self.connected:
            return
        sel = np.arange(n)
        if self._decim > 1:
            sel = sel[(sel + self._phase) % self._decim == 0]
            self._phase = (self._phase + n) % self._decim
        if len(sel) == 0:
            return
        acc = np.asarray(acc_counts)[sel].astype(np.int64)
        if self.cal.nvm.comp and self.compensates:  # on-board compensation, board's own temperature
            acc = self.cal.compensate_counts(acc, self.identity.temp_c(np.asarray(temp_counts)[sel]),
                                             self.identity.ug_per_lsb)
        if self.shift:
            acc = np.floor_divide(acc + (1 << (self.shift - 1)), 1 << self.shift)
        acc = np.clip(acc, -32768, 32767).tolist()
        temp_c = self.identity.temp_c(np.asarray(temp_counts)[sel])
        t8 = np.clip(np.round(temp_c - cf.TEMP_C_AT_ZERO), -128, 127).astype(np.int64).tolist()
        arb = cf.SAMPLE_BASE + self.node_id
        seq = self.seq
        for k in range(len(t8)):
            a = acc[k]
            if self._corrupt:
                self._corrupt -= 1
            else:
                self._out(arb, cf.encode_sample(a[0], a[1], a[2], t8[k], seq))
            seq = (seq + 1) & 0xFF
        self.seq = seq


class SimCanHub:
    """The simulated bus: boards hear the host's frames, the host hears the boards'."""

    def __init__(self) -> None:
        self.boards: list[SimCanBoard] = []
        self.to_host: SendFn | None = None

    def add(self, board: SimCanBoard) -> SimCanBoard:
        board.send = self._from_board
        self.boards.append(board)
        return board

    def _from_board(self, arb_id: int, data: bytes) -> None:
        if self.to_host is not None:
            self.to_host(arb_id, data)

    def from_host(self, arb_id: int, data: bytes) -> None:
        for b in self.boards:
            b.on_frame(arb_id, data)


class SlcanPtyAdapter:
    """Device side of an slcan adapter on a pty; `path` is the channel for python-can."""

    VERSION = b"V1013\r"
    SERIAL = b"NSIM1\r"

    def __init__(self, hub: SimCanHub) -> None:
        self.hub = hub
        hub.to_host = self._to_host
        self.port = PtyEndpoint(self._on_data)
        self.path = self.port.path
        self.is_open = False
        self.bitrate_cmd = ""
        self._buf = bytearray()
        self.frames_to_host = 0
        self.frames_from_host = 0
        self.bad_commands = 0

    def start(self) -> None:
        self.port.start()

    def close(self) -> None:
        self.port.close()

    def _reply(self, data: bytes) -> None:
        self.port.write(data)

    def _on_data(self, data: bytes) -> None:
        self._buf += data
        while True:
            cr = self._buf.find(b"\r")
            if cr < 0:
                if len(self._buf) > 64:
                    self._buf.clear()
                    self.bad_commands += 1
                    self._reply(b"\a")
                return
            line = bytes(self._buf[:cr])
            del self._buf[: cr + 1]
            self._command(line.lstrip(b"\n"))

    def _command(self, line: bytes) -> None:
        if not line:
            self._reply(b"\r")
            return
        c = line[:1]
        try:
            if c in (b"S", b"s"):
                if self.is_open:
                    raise ValueError("bitrate change while open")
                self.bitrate_cmd = line.decode()
                self._reply(b"\r")
            elif c in (b"O", b"L"):
                self.is_open = True
                self._reply(b"\r")
            elif c == b"C":
                self.is_open = False
                self._reply(b"\r")
            elif c == b"V":
                self._reply(self.VERSION)
            elif c == b"N":
                self._reply(self.SERIAL)
            elif c == b"F":
                self._reply(b"F00\r")
            elif c in (b"Z", b"M", b"m", b"X", b"W", b"Q"):
                self._reply(b"\r")
            elif c in (b"t", b"T"):
                ext = c == b"T"
                nid = 8 if ext else 3
                arb = int(line[1 : 1 + nid], 16)
                dlc = int(line[1 + nid : 2 + nid])
                data = bytes.fromhex(line[2 + nid : 2 + nid + 2 * dlc].decode())
                if len(data) != dlc or not self.is_open:
                    raise ValueError("bad frame or channel closed")
                self.frames_from_host += 1
                self._reply(b"Z\r" if ext else b"z\r")
                if not ext:
                    self.hub.from_host(arb, data)
            elif c in (b"r", b"R"):
                self._reply(b"Z\r" if c == b"R" else b"z\r")
            else:
                raise ValueError("unknown command")
        except ValueError:
            self.bad_commands += 1
            self._reply(b"\a")

    def _to_host(self, arb_id: int, data: bytes) -> None:
        if not self.is_open:
            return
        self.frames_to_host += 1
        self.port.write(b"t%03X%d%s\r" % (arb_id, len(data), data.hex().upper().encode()))


class VirtualCanBridge:
    """The same simulated boards on a python-can `virtual` channel (in-process bus)."""

    def __init__(self, hub: SimCanHub, channel: str) -> None:
        self.hub = hub
        self.channel = channel
        self.bus = can.Bus(interface="virtual", channel=channel)
        hub.to_host = self._to_host
        self._running = False
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._running = True
        self._thread = threading.Thread(target=self._reader, name=f"simcan-{self.channel}", daemon=True)
        self._thread.start()

    def _reader(self) -> None:
        loop = self._loop
        assert loop is not None
        while self._running:
            msg = self.bus.recv(0.1)
            if msg is None or msg.is_extended_id:
                continue
            try:
                loop.call_soon_threadsafe(self.hub.from_host, msg.arbitration_id, bytes(msg.data))
            except RuntimeError:
                return

    def _to_host(self, arb_id: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=arb_id, data=data, is_extended_id=False))

    def close(self) -> None:
        self._running = False
        if self._thread is not None:
            self._thread.join(1.0)
        self.bus.shutdown()

