"""Simulated serial boards on real pseudo-terminals (design 3.1 spoken from the pty master).

The driver opens the slave path (`/dev/pts/N`) with pyserial exactly like a USB CDC port; the
simulated firmware reads commands and writes frames on the master fd from the event loop. What
the board sends comes from `feed()` (the SimStation clock hands it the world's samples); the
board only turns counts into frames, it knows no physics.
"""

from __future__ import annotations

import asyncio
import dataclasses
import errno
import os
import tty
from collections.abc import Callable

import numpy as np

from drivers.protocol import serial_frames as sf
from drivers.sim.board_nvm import CalFirmware
from contracts.types import Identity

OUT_BUFFER_MAX_BYTES = 1 << 20  # a board's USB buffer: beyond this, frames are dropped (seq gap)


class PtyEndpoint:
    """The device end of a pseudo-terminal: non-blocking, loop-driven, with an output queue.

    on_data(bytes) gets whatever the host wrote. The slave fd stays open here too so the
    master never reads EIO while no host has the port open; `close()` closes both, and a host
    holding the slave then sees the port vanish (EOF/EIO), like a pulled USB cable.
    """

    def __init__(self, on_data: Callable[[bytes], None] | None = None) -> None:
        self.master_fd, self._slave_fd = os.openpty()
        tty.setraw(self._slave_fd)
        os.set_blocking(self.master_fd, False)
        self.path = os.ttyname(self._slave_fd)
        self.on_data = on_data
        self._out = bytearray()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._writer_on = False
        self.closed = False
        self.bytes_dropped = 0
        self.last_drain = 0.0  # loop time the host last took bytes (a live reader)

    def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._loop.add_reader(self.master_fd, self._on_readable)

    def _on_readable(self) -> None:
        try:
            data = os.read(self.master_fd, 65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:  # EIO: nobody on the slave side right now; nothing to do
            return
        if self.on_data is not None:
            self.on_data(data)

    def write(self, data: bytes) -> None:
        if self.closed:
            return
        if self._out:
            if len(self._out) + len(data) > OUT_BUFFER_MAX_BYTES:
                self.bytes_dropped += len(data)
                return
            self._out += data
            return
        try:
            n = os.write(self.master_fd, data)
        except BlockingIOError:
            n = 0
        except OSError:
            return
        if n and self._loop is not None:
            self.last_drain = self._loop.time()
        if n < len(data):
            self._out += data[n:]
            self._arm_writer()

    def backlog_bytes(self, now: float, live_within_s: float = 1.0) -> int:
        """Bytes waiting for a host that is reading (one that took bytes lately); 0 for a dead
        or absent reader, whose backlog must not hold the plant."""
        if self.closed or now - self.last_drain > live_within_s:
            return 0
        return len(self._out)

    def _arm_writer(self) -> None:
        if not self._writer_on and self._loop is not None and not self.closed:
            self._loop.add_writer(self.master_fd, self._on_writable)
            self._writer_on = True

    def _on_writable(self) -> None:
        try:
            n = os.write(self.master_fd, self._out)
        except BlockingIOError:
            return
        except OSError:
            n = len(self._out)
        del self._out[:n]
        if n and self._loop is not None:
            self.last_drain = self._loop.time()
        if not self._out and self._loop is not None:
            self._loop.remove_writer(self.master_fd)
            self._writer_on = False

    def unplug(self) -> None:
        """The cable is pulled: the master closes, so a host holding the port reads EOF and the
        path is gone (opening it again fails). This end keeps its slave fd until close(), which
        keeps the pts number taken: the kernel hands a freed number to the next pty opened on the
        machine, and a station that tries its vanished port again (the next batch's connect) would
        open another process's board (parallel tests did, and read a second board's serial)."""
        if self.closed:
            return
        self.closed = True
        if self._loop is not None:
            self._loop.remove_reader(self.master_fd)
            if self._writer_on:
                self._loop.remove_writer(self.master_fd)
        self._close_fd(self.master_fd)
        self._out.clear()

    def close(self) -> None:
        """Unplug (if not yet) and give the pts number back."""
        self.unplug()
        if self._slave_fd >= 0:
            self._close_fd(self._slave_fd)
            self._slave_fd = -1

    @staticmethod
    def _close_fd(fd: int) -> None:
        try:
            os.close(fd)
        except OSError as exc:  # pragma: no cover
            if exc.errno != errno.EBADF:
                raise


def _ratio(src_hz: float, dst_hz: float) -> int | None:
    """Decimation factor src->dst if dst divides src, else None."""
    if dst_hz <= 0 or dst_hz > src_hz * (1 + 1e-9):
        return None
    k = src_hz / dst_hz
    return int(round(k)) if abs(k - round(k)) < 1e-6 else None


class SimSerialBoard:
    """Board firmware for one DUT: answers ID/START/STOP/ODR, streams `D` frames while started.

    `identity` gives the counts' scaling and the source sample rate (identity.odr_hz); ODR
    commands are honoured when they divide the source rate (decimation), else answered `E`.
    Faults: inject_garbage, corrupt_next, stop_streaming, disconnect, reset_streaming (a reset
    that streams again by itself), jump_clock, swap_to (another board behind the same open
    port); on the calibration write
    path `cal.flip_next_write`, `cal.refuse_writes`, `cal.drop_replies` (drivers.sim.board_nvm).
    Calibration ($CALW/$SFEW/$CALR/$SFER/$COMP) lives in `cal.nvm`, which `power_cycle()` keeps.
    """

    def __init__(self, identity: Identity, *, t0_us: int = 0, clock_bits: int | None = 32) -> None:
        self.identity = identity
        self.source_odr_hz = identity.odr_hz
        self.port = PtyEndpoint(self._on_data)
        self.path = self.port.path
        self.parser = sf.FrameParser(board_side=True)
        self.streaming = False
        self.muted = False  # stop_streaming(): alive, answers commands, sends no samples
        # False: the counts fed are already what the board sent (a replay of recorded output, which
        # is compensated or raw exactly as recorded), so $COMP changes the NVM flag only
        self.compensates = True
        self.seq = 0
        self._decim = 1
        self._phase = 0
        self._corrupt = 0
        self.t0_us = t0_us
        self.clock_mask = (1 << clock_bits) - 1 if clock_bits else None  # firmware uint32 clock wraps
        self.commands: list[bytes] = []  # every command frame received, raw (tests read it)
        self.frames_sent = 0
        self.sent_until_s: float | None = None  # plant time of the newest sample sent (the lead a reader has to catch up)
        self.cal = CalFirmware()
        self.power_cycles = 0
        self._restart_at_s: float | None = None  # reset_streaming(): the clock restarts at the next sample
        self._offset_counts = np.zeros(3, dtype=np.int64)  # swap_to(): another board's offsets
        # called as STOP takes effect, before its ack: what was already on its way goes out first
        # (a replay sends the recorded samples up to the recorded stop, drivers/sim/replay.py)
        self.on_stop: Callable[[], None] | None = None

    # ---- lifecycle ------------------------------------------------------------------------
    def start(self) -> None:
        self.port.start()

    def close(self) -> None:
        self.port.close()

    # ---- fault injection ------------------------------------------------------------------
    def inject_garbage(self, data: bytes) -> None:
        self.port.write(bytes(data))

    def corrupt_next(self, n: int = 1) -> None:
        """The next n frames go out with a wrong checksum."""
        self._corrupt += int(n)

    def stop_streaming(self) -> None:
        self.muted = True

    def disconnect(self) -> None:
        """Pull the cable: the host's port vanishes (PtyEndpoint.unplug)."""
        self.port.unplug()

    def power_cycle(self) -> None:
        """The board restarts: RAM state (streaming, seq, ODR, parser) is lost, the NVM is kept."""
        self.streaming = False
        self.seq = 0
        self._decim, self._phase = 1, 0
        self.identity = dataclasses.replace(self.identity, odr_hz=self.source_odr_hz)
        self.parser = sf.FrameParser(board_side=True)
        self.power_cycles += 1

    def reset_streaming(self, boot_s: float = 0.05) -> None:
        """The board resets (a brown-out, its watchdog) and, as some firmware does, streams again
        by itself: seq from 0, its clock from `boot_s` after power-up (design 3.1: t_us is time
        since power-up). Takes effect at the next sample fed."""
        self._restart_at_s = float(boot_s)
        self.seq = 0
        self.power_cycles += 1

    def jump_clock(self, seconds: float) -> None:
        """The board's clock jumps by `seconds` (back when negative) while its seq runs on."""
        self.t0_us += int(round(seconds * 1e6))

    def swap_to(self, identity: Identity, offset_counts: tuple[int, int, int] = (0, 0, 0)) -> None:
        """Another board now answers behind the same open port (its serial, its physics: here a
        different offset per axis), its stream going on as if nothing happened."""
        self.identity = dataclasses.replace(identity, odr_hz=self.identity.odr_hz)
        self._offset_counts = np.asarray(offset_counts, dtype=np.int64)

    @property
    def connected(self) -> bool:
        return not self.port.closed

    # ---- host commands --------------------------------------------------------------------
    def _on_data(self, data: bytes) -> None:
        start = 0
        while True:
            nl = data.find(b"\n", start)
            if nl < 0:
                break
            self.commands.append(data[start : nl + 1])
            start = nl + 1
        for frame in self.parser.feed(data):
            assert isinstance(frame, sf.CommandFrame)
            self._command(frame)

    def _send(self, raw: bytes) -> None:
        if self._corrupt:
            self._corrupt -= 1
            raw = raw[:-3] + (b"%02X" % (int(raw[-3:-1], 16) ^ 0x5A)) + b"\n"
        self.port.write(raw)
        self.frames_sent += 1

    def _command(self, frame: sf.CommandFrame) -> None:
        cmd = frame.command
        if cmd == "ID":
            self._send(sf.IdentityFrame(self.identity).encode())
        elif cmd == "START":
            self.streaming = True
            self._send(sf.AckFrame("START").encode())
        elif cmd == "STOP":
            self.streaming = False
            if self.on_stop is not None:
                self.on_stop()
            self._send(sf.AckFrame("STOP").encode())
        elif cmd == "ODR":
            hz = float(frame.args[0])
            k = _ratio(self.source_odr_hz, hz)
            if k is None:
                self._send(sf.ErrorFrame("ODR", f"unsupported rate {frame.args[0]}").encode())
                return
            self._decim, self._phase = k, 0
            self.identity = dataclasses.replace(self.identity, odr_hz=self.source_odr_hz / k)
            self._send(sf.AckFrame("ODR", (frame.args[0],)).encode())
        elif cmd in ("CALW", "SFEW", "CALR", "SFER", "COMP"):
            self._calibration(cmd, frame.args)

    def _cal_reply(self, raw: bytes) -> None:
        if not self.cal.take_drop():
            self._send(raw)

    def _calibration(self, cmd: str, args: tuple[str, ...]) -> None:
        cal = self.cal
        if cmd in ("CALW", "SFEW"):
            values = cal.on_the_way([float(a) for a in args])
            if cal.take_refuse():
                self._cal_reply(sf.ErrorFrame(cmd, "flash write failed").encode())
                return
            if cmd == "CALW":
                cal.store_thermal(values)
                crc = cal.nvm.thermal_crc
            else:
                cal.store_sfem(values)
                crc = cal.nvm.sfem_crc
            self._cal_reply(sf.AckFrame(cmd, (sf.fmt_crc(crc),)).encode())
        elif cmd == "CALR":
            self._cal_reply(sf.CalReadFrame(cal.nvm.thermal, cal.readback_crc(), cal.nvm.comp).encode())
        elif cmd == "SFER":
            if cal.nvm.sfem is None:
                self._cal_reply(sf.ErrorFrame("SFER", "no SFEM stored").encode())
            else:
                self._cal_reply(sf.SfemReadFrame(cal.nvm.sfem, cal.nvm.sfem_crc).encode())
        elif cmd == "COMP":
            cal.nvm.comp = args[0] == "1"
            self._cal_reply(sf.AckFrame("COMP").encode())

    # ---- samples from the world -----------------------------------------------------------
    def feed(self, time_s: np.ndarray, acc_counts: np.ndarray, temp_counts: np.ndarray) -> None:
        """Samples the sensor produced (n,), (n, 3), (n,); sent as `D` frames while started."""
        n = len(time_s)
        if n == 0 or not self.streaming or self.muted or self.port.closed:
            return
        sel = np.arange(n)
        if self._decim > 1:
            sel = sel[(sel + self._phase) % self._decim == 0]
            self._phase = (self._phase + n) % self._decim
        if len(sel) == 0:
            return
        self.sent_until_s = float(np.asarray(time_s)[sel[-1]])
        if self._restart_at_s is not None:  # reset_streaming(): the clock starts again at power-up
            self.t0_us = int(round((self._restart_at_s - float(np.asarray(time_s)[sel[0]])) * 1e6))
            self._restart_at_s = None
        t_us_arr = np.round(np.asarray(time_s)[sel] * 1e6).astype(np.int64) + self.t0_us
        if self.clock_mask is not None:
            t_us_arr &= self.clock_mask
        t_us = t_us_arr.tolist()
        acc_arr = np.asarray(acc_counts)[sel].astype(np.int64) + self._offset_counts
        tc_arr = np.asarray(temp_counts)[sel].astype(np.int64)
        if self.cal.nvm.comp and self.compensates:  # on-board compensation with the board's own temperature
            acc_arr = self.cal.compensate_counts(acc_arr, self.identity.temp_c(tc_arr), self.identity.ug_per_lsb)
            acc_arr = np.clip(acc_arr, -(1 << 31), (1 << 31) - 1)
        acc = acc_arr.tolist()
        tc = tc_arr.tolist()
        parts = []
        seq = self.seq
        for k in range(len(t_us)):
            a = acc[k]
            body = b"D,%d,%d,%d,%d,%d,%d" % (seq, t_us[k], a[0], a[1], a[2], tc[k])
            parts.append(b"$%s*%02X\n" % (body, sf.checksum(body)))
            seq = (seq + 1) & 0xFFFFFFFF
        self.seq = seq
        if self._corrupt:
            for raw in parts:
                self._send(raw)
        else:
            self.port.write(b"".join(parts))
            self.frames_sent += len(parts)
