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

_DIGIT_BOUNDS = np.array([10 ** k for k in range(1, 20)], dtype=np.uint64)  # ndigits(m) = 1 + #bounds <= m
_DIGITS4 = np.frombuffer(b"".join(b"%04d" % k for k in range(10000)), dtype=np.uint8).reshape(10000, 4)
_HEX = np.frombuffer(b"0123456789ABCDEF", dtype=np.uint8)


def _decimal_columns(values: np.ndarray) -> np.ndarray:
    """(n, width) uint8: each int64 value in decimal ASCII, right-aligned, NUL-padded on the left.
    NUL is the padding because it is neutral in the frame checksum (XOR) and never part of a frame,
    so a whole block of frames is one matrix, its checksums one reduce and its bytes one mask."""
    v = np.asarray(values, dtype=np.int64)
    neg = v < 0
    mag = np.where(neg, (~v).astype(np.uint64) + np.uint64(1), v.astype(np.uint64))  # |INT64_MIN| too
    ndig = np.searchsorted(_DIGIT_BOUNDS, mag, side="right") + 1
    maxd = int(ndig.max(initial=1))
    groups = -(-maxd // 4)
    sign = int(neg.any())
    out = np.empty((len(v), sign + 4 * groups), dtype=np.uint8)
    rest = mag
    for g in range(groups - 1, -1, -1):  # four digits per division: a quarter of the divisions
        rest, r = np.divmod(rest, np.uint64(10000))
        out[:, sign + 4 * g: sign + 4 * g + 4] = _DIGITS4[r]
    out = out[:, 4 * groups - maxd:]
    lead = out.shape[1] - ndig
    out[np.arange(out.shape[1])[None, :] < lead[:, None]] = 0
    if sign:
        rows = np.flatnonzero(neg)
        out[rows, lead[rows] - 1] = ord("-")
    return out


def render_sample_frames(seq: np.ndarray, t_us: np.ndarray, acc: np.ndarray,
                         temp: np.ndarray) -> tuple[bytes, np.ndarray]:
    """The design-3.1 `D` frames of n samples as one byte string, and the (n + 1,) offsets of each
    frame in it (frame k = data[off[k]:off[k + 1]]): byte for byte what `sf.SampleFrame.encode`
    gives sample by sample, computed for the whole block with a few numpy operations. A board that
    sends thousands of samples per plant tick (a replay at x2000) must not cost the host a Python
    loop per sample: the boards it stands for cost the daemon's machine nothing."""
    n = len(t_us)
    if n == 0:
        return b"", np.zeros(1, dtype=np.int64)
    acc = np.asarray(acc, dtype=np.int64).reshape(n, 3)
    fields = (seq, t_us, acc[:, 0], acc[:, 1], acc[:, 2], temp)
    comma = np.full((n, 1), ord(","), dtype=np.uint8)
    cols: list[np.ndarray] = [np.broadcast_to(np.frombuffer(b"$D", dtype=np.uint8), (n, 2))]
    for f in fields:
        cols += [comma, _decimal_columns(np.asarray(f, dtype=np.int64))]
    mat = np.concatenate(cols, axis=1)
    cs = np.bitwise_xor.reduce(mat[:, 1:], axis=1)  # the body: after '$', NULs change nothing
    tail = np.empty((n, 4), dtype=np.uint8)
    tail[:, 0], tail[:, 1], tail[:, 2], tail[:, 3] = ord("*"), _HEX[cs >> 4], _HEX[cs & 15], ord("\n")
    mat = np.concatenate([mat, tail], axis=1)
    keep = mat != 0
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(keep.sum(axis=1), out=offsets[1:])
    return mat[keep].tobytes(), offsets


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
        self.max_out_bytes = OUT_BUFFER_MAX_BYTES  # this device's transmit buffer
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
            if len(self._out) + len(data) > self.max_out_bytes:
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
        # what the board reports of its starts (docs/design.md 3.1 `reset=`, `boots=`): 1
        # after a power-on, +1 per reset that is not one (reset_streaming: its watchdog)
        self.boots = 1
        self.reset_cause = "power"
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
        self.boots, self.reset_cause = 1, "power"

    def reset_streaming(self, boot_s: float = 0.05) -> None:
        """The board resets (a brown-out, its watchdog) and, as some firmware does, streams again
        by itself: seq from 0, its clock from `boot_s` after power-up (design 3.1: t_us is time
        since power-up). Takes effect at the next sample fed."""
        self._restart_at_s = float(boot_s)
        self.seq = 0
        self.power_cycles += 1
        self.boots += 1
        self.reset_cause = "watchdog"

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
            self._send(sf.IdentityFrame(dataclasses.replace(self.identity, reset_cause=self.reset_cause,
                                                            boots=self.boots)).encode())
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
        acc_arr = np.asarray(acc_counts)[sel].astype(np.int64) + self._offset_counts
        tc_arr = np.asarray(temp_counts)[sel].astype(np.int64)
        if self.cal.nvm.comp and self.compensates:  # on-board compensation with the board's own temperature
            acc_arr = self.cal.compensate_counts(acc_arr, self.identity.temp_c(tc_arr), self.identity.ug_per_lsb)
            acc_arr = np.clip(acc_arr, -(1 << 31), (1 << 31) - 1)
        seq = (self.seq + np.arange(len(sel), dtype=np.int64)) & 0xFFFFFFFF
        data, offsets = render_sample_frames(seq, t_us_arr, acc_arr, tc_arr)
        self.seq = (int(seq[-1]) + 1) & 0xFFFFFFFF
        if self._corrupt:
            for k in range(len(sel)):
                self._send(data[offsets[k]:offsets[k + 1]])
        else:
            self.port.write(data)
            self.frames_sent += len(sel)

    def sends_counts_as_given(self) -> bool:
        """True when feed() would put each sample's counts, sample clock and the given seq on the wire
        unchanged (no decimation, clock offset or wrap, injected fault, other board's offsets or
        on-board compensation): then a stream rendered ahead (render_sample_frames) may go out with
        send_rendered() in place of feed(), byte for byte the same."""
        return (self._decim == 1 and self.t0_us == 0 and self.clock_mask is None and self._restart_at_s is None
                and not self._corrupt and not self._offset_counts.any()
                and not (self.cal.nvm.comp and self.compensates))

    def send_rendered(self, frames: bytes, n: int, last_time_s: float, next_seq: int) -> None:
        """Put n frames rendered ahead on the wire (only while sends_counts_as_given()), as feed()
        would have: while streaming, not muted, connected; `next_seq` is the seq after the last."""
        if n == 0 or not self.streaming or self.muted or self.port.closed:
            return
        self.sent_until_s = float(last_time_s)
        self.seq = int(next_seq) & 0xFFFFFFFF
        self.port.write(frames)
        self.frames_sent += int(n)
