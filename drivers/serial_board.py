"""Serial board driver (design 3.1) over pyserial: any port name or pyserial URL.

Reading never blocks the event loop: when the port has a file descriptor (real tty, USB CDC,
pty) the loop watches it (`add_reader`) and reads what is there, so 64 boards cost 64 fds and no
threads; ports without one (pyserial URLs such as `loop://`, `socket://`) get one small reader
thread that hands bytes to the loop. Bytes go through the incremental frame parser; samples
queue until `read_block()` takes them, already in g / C with the board's identity.
"""

from __future__ import annotations

import asyncio
import dataclasses
import fcntl
import os
import struct
import termios
import threading
import time

import numpy as np
import serial

from drivers.base import DriverError, LinkStats, StreamBreak
from drivers.protocol import serial_frames as sf
from drivers.protocol.selfcal_frames import SegmentReportFrame, SelfCalResultFrame
from drivers.serial_board_commands import BoardErrorReply as BoardErrorReply  # re-exported: callers import it here
from drivers.serial_board_commands import SerialBoardCommands, reply_key
from drivers.protocol.sample_lines import SampleLines
from drivers.protocol.stream_timeline import ClockUnwrapper, SeqTracker, StreamTimeline
from drivers.sample_buffer import MAX_PENDING_SAMPLES as MAX_PENDING_SAMPLES, Row, SampleBuffer
from contracts.types import Identity, SampleBlock


RAW_PARSE_BYTES = 1 << 18  # unparsed bytes beyond this are parsed at once (nobody reads: a bound)
MAX_HELD_SEGMENTS = 4096  # G frames nobody took: the oldest go (a calibrator saves a few per hour)
CLEAN_BAND = 0.2  # of the period: a clock step this close to it is "ok" for every per-frame check (see _take_clean)


def _columns(rows: list[Row]) -> tuple[np.ndarray, np.ndarray]:
    """A serial row's time is the board's clock in microseconds (unwrapped)."""
    try:
        arr = np.array(rows, dtype=np.int64)
        t_us, counts = arr[:, 0], arr[:, 1:]
    except OverflowError:
        # a 64-bit board clock past 2**63 us (in range for the protocol's uint64): the time goes
        # through float64 instead of int64; the counts (int32 by the frame checks) stay exact
        t_us = np.array([r[0] for r in rows], dtype=np.float64)
        counts = np.array([r[1:] for r in rows], dtype=np.int64)
    return t_us / 1e6, counts


class SerialBoard(SerialBoardCommands):
    """One serial board.

    url_or_port: "/dev/ttyACM0", "/dev/pts/7", "socket://host:port", "loop://", ...
    ack_timeout_s/retries: a command without `A` reply is re-sent this many times, then
    DriverError. An `E` reply to a command raises DriverError with the board's text.
    speed: plant time per wall second (config timing.speed; 1 on real hardware): how long a silence
    on the wire explains a forward step of the board's clock (StreamTimeline).
    """

    def __init__(
        self,
        url_or_port: str,
        baudrate: int = 115200,
        *,
        ack_timeout_s: float = 0.5,
        retries: int = 3,
        speed: float = 1.0,
    ) -> None:
        self.port = url_or_port
        self.baudrate = baudrate
        self.ack_timeout_s = ack_timeout_s
        self.retries = max(1, int(retries))
        self.stats = LinkStats()
        self.identity: Identity | None = None
        self._parser = sf.FrameParser(self.stats)
        self._seq = SeqTracker(32)
        self._clock = ClockUnwrapper()
        self._timeline = StreamTimeline(speed)  # one board, one timeline: resets and clock jumps
        self._ser: serial.SerialBase | None = None
        self._fd: int | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._running = False
        self._held = SampleBuffer(self.stats, _columns)  # rows: t_us, ax, ay, az, t
        self._raw = bytearray()  # taken off the port, not parsed yet (_on_readable)
        self._bytes_parsed = 0  # bytes parsed so far: with frames_ok, the bytes of a frame
        self._broken = False  # a StreamBreak was seen: samples are not taken until the next START
        self._breaks: list[StreamBreak] = []
        self._error: DriverError | None = None
        self._ident_fut: asyncio.Future[Identity] | None = None
        self._ack_waiters: dict[str, asyncio.Future] = {}
        self._cmd_lock = asyncio.Lock()
        self._segments: list[SegmentReportFrame] = []  # G frames not taken yet (take_selfcal_segments)
        self.segments_dropped = 0  # G frames dropped because nobody took them (MAX_HELD_SEGMENTS)

    def __repr__(self) -> str:
        return f"SerialBoard({self.port!r})"

    # ---- link ------------------------------------------------------------------------------
    async def open(self) -> None:
        if self._ser is not None:
            return
        self._loop = asyncio.get_running_loop()
        self._held.renew()
        self._cmd_lock = asyncio.Lock()
        try:
            self._ser = await asyncio.to_thread(
                serial.serial_for_url, self.port, baudrate=self.baudrate, timeout=0.1, write_timeout=1.0,
                exclusive=True,  # posix: flock on the tty; a second process opening this board is refused
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DriverError(f"cannot open serial port {self.port}: {exc}") from exc
        self._error = None
        self._running = True
        try:
            fd = self._ser.fileno()
        except Exception:  # URL handlers without a descriptor
            fd = None
        if fd is not None:
            self._fd = fd
            os.set_blocking(fd, False)
            self._loop.add_reader(fd, self._on_readable)
        else:
            self._thread = threading.Thread(target=self._reader_thread, name=f"serial-{self.port}", daemon=True)
            self._thread.start()

    def _on_readable(self) -> None:
        try:
            data = os.read(self._fd, 65536)  # type: ignore[arg-type]
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._fail(f"serial port {self.port} vanished: {exc}")
            return
        if not data:
            self._fail(f"serial port {self.port} vanished (EOF)")
            return
        # The bytes are taken off the port at once (its buffer never overruns while the loop turns);
        # they are parsed in bulk when the pump reads (read_block, every read period), or at once
        # while a command waits for its reply (the reply, and the samples before it, in order).
        self.last_rx_wall = time.monotonic()
        self._raw += data
        if self._ack_waiters or (self._ident_fut is not None and not self._ident_fut.done()) \
                or len(self._raw) >= RAW_PARSE_BYTES:
            self._drain()
        else:
            self._held.wake()

    def backlog_samples(self) -> int:
        pending = len(self._raw) + len(self._parser._buf)
        if self._fd is not None:
            try:
                pending += struct.unpack("i", fcntl.ioctl(self._fd, termios.FIONREAD, b"\0\0\0\0"))[0]
            except OSError:
                pass
        per_frame = max(16, self._bytes_parsed // max(1, self.stats.frames_ok))
        return len(self._held) + pending // per_frame

    def _drain(self) -> None:
        """Parse the bytes taken off the port and not parsed yet."""
        if self._raw:
            data, self._raw = bytes(self._raw), bytearray()
            self._parse(data)

    def _reader_thread(self) -> None:
        ser = self._ser
        loop = self._loop
        assert ser is not None and loop is not None
        while self._running:
            try:
                data = ser.read(max(1, ser.in_waiting))
            except Exception as exc:  # noqa: BLE001 - any failure means the port is gone
                if self._running:
                    loop.call_soon_threadsafe(self._fail, f"serial port {self.port} vanished: {exc}")
                return
            if data:
                loop.call_soon_threadsafe(self._feed, data)

    def _fail(self, message: str) -> None:
        if self._error is None:
            self._error = DriverError(message)
        self._stop_reading()
        for fut in [self._ident_fut, *self._ack_waiters.values()]:
            if fut is not None and not fut.done():
                fut.set_exception(self._error)
        self._held.wake()

    def _stop_reading(self) -> None:
        if self._fd is not None and self._loop is not None:
            self._loop.remove_reader(self._fd)
        self._fd = None
        self._running = False

    # ---- frames ----------------------------------------------------------------------------
    def _feed(self, data: bytes) -> None:
        self.last_rx_wall = time.monotonic()
        self._parse(data)

    def _parse(self, data: bytes) -> None:
        self._bytes_parsed += len(data)
        lines = self._parser.feed_samples(data)
        if lines is not None:  # a read of nothing but sample frames (the usual one)
            if not self._take_clean(lines):
                for seq, t_us, (ax, ay, az, tc) in zip(lines.seq.tolist(), lines.t_us.tolist(),
                                                        lines.counts.tolist()):
                    self._frame(sf.SampleFrame(seq, t_us, ax, ay, az, tc))
        else:
            for frame in self._parser.feed(b""):
                self._frame(frame)
        self._held.flush()

    def _take_clean(self, lines: SampleLines) -> bool:
        """Take a run of sample frames at once when it simply goes on the stream's one timeline:
        every seq one more than the one before, every clock step within CLEAN_BAND of the learned
        period (so each frame's own check would say "ok": StreamTimeline, ClockUnwrapper), no wrap,
        no break. Else False, and each frame goes through `_frame` (the one definition)."""
        tl, clock, seqt = self._timeline, self._clock, self._seq
        if (self._broken or tl.last is None or tl.period_us is None or tl._n_on_line < tl.CONFIRM_FRAMES
                or tl._cand or clock.last is None or clock.period_us is None or clock._candidate is not None
                or clock._skipped_steps or seqt.last is None or clock.last != tl.last[1]
                or seqt.last != tl.last[0]):
            return False
        seq, t_us = lines.seq, lines.t_us
        last_t = clock.last
        if last_t >= clock.WRAP or int(t_us.max()) >= clock.WRAP:
            return False
        p0 = tl.period_us
        dt = np.diff(t_us, prepend=last_t)
        dseq = np.diff(seq, prepend=seqt.last)
        if not ((dseq == 1).all() and (np.abs(dt - p0) <= CLEAN_BAND * p0).all()
                and abs(int(dt[0]) - clock.period_us) <= clock.TOLERANCE * clock.period_us):
            return False
        # the state each frame's own check would leave (the timeline's period, smoothed per frame)
        p = p0
        for step in dt.tolist():
            p += 0.05 * (step - p)
        n = len(lines)
        last_seq, last_tus = int(seq[-1]), int(t_us[-1])
        tl.period_us, tl.last, tl.last_wall_s = p, (last_seq, last_tus), self.last_rx_wall
        tl._n_on_line += n
        clock.period_us, clock.last = float(dt[-1]), last_tus
        seqt.last, seqt.index = last_seq, seqt.index + n
        self._held.add_columns((t_us + clock.offset) / 1e6, lines.counts)
        self.last_sample_t = (last_tus + clock.offset) / 1e6
        return True

    def _frame(self, frame: sf.Frame) -> None:
        """One frame from the board, in order: a sample onto its timeline, a reply to its waiter."""
        if type(frame) is sf.SampleFrame:
            if self._broken:  # after a break: not this run's timeline (until the next START)
                self.stats.frames_after_break += 1
                return
            line = self._timeline.check(frame.seq, frame.t_us, self.last_rx_wall)
            if line == "skip":  # off its timeline, not confirmed: garbage that passed the checksum
                self._malformed()
                return
            if line in ("reset", "clock_jump"):
                self._stream_break(line)
                return
            lost = self._seq.update(frame.seq)
            if lost:
                self._held.count_lost(lost)
            t_us = self._clock.update(frame.t_us, lost + 1)
            if t_us is None:  # a time that follows nothing: a corrupt frame, not a clock wrap
                self._malformed()
                return
            self._held.add((t_us, frame.ax, frame.ay, frame.az, frame.t))
            self.last_sample_t = t_us / 1e6
        elif isinstance(frame, sf.IdentityFrame):
            if self._ident_fut is not None and not self._ident_fut.done():
                self._ident_fut.set_result(frame.identity)
        elif isinstance(frame, SegmentReportFrame):
            # the on-board calibrator saved a segment: held for take_selfcal_segments, never a sample
            self._segments.append(frame)
            if len(self._segments) > MAX_HELD_SEGMENTS:
                del self._segments[0]
                self.segments_dropped += 1
        elif isinstance(frame, (sf.AckFrame, sf.CalReadFrame, sf.SfemReadFrame, SelfCalResultFrame,
                                sf.SfemCubicHeadFrame, sf.SfemCubicRowFrame)):
            fut = self._ack_waiters.get(reply_key(frame))
            if fut is not None and not fut.done():
                fut.set_result(frame)
        elif isinstance(frame, sf.ErrorFrame):
            if frame.code in sf.UNSOLICITED_ERRORS:
                # the board's own report (a sensor it re-initialised, a damaged NVM slot): counted by
                # the parser, kept for the run's notes, never the answer to a command in flight
                self.last_board_error = f"{frame.code}: {frame.text}"
                return
            for fut in self._ack_waiters.values():
                if not fut.done():
                    fut.set_exception(BoardErrorReply(self.port, frame.code, frame.text))

    def _malformed(self) -> None:
        """A frame the parser counted ok that is no sample after all: counted malformed instead."""
        self.stats.frames_ok -= 1
        self.stats.frames_malformed += 1

    def _break_words(self, kind: str) -> str:
        """The break in words: what the board's seq and clock did (StreamTimeline.broke)."""
        if self._timeline.broke is None:
            return "its stream broke"
        (seq0, t0), (seq1, t1), off_us = self._timeline.broke
        if kind == "reset":
            return (f"the board restarted while streaming (seq {seq0} -> {seq1}, clock {t0 / 1e6:.1f} s -> "
                    f"{t1 / 1e6:.1f} s): a reset (power, brown-out, watchdog)?")
        return (f"its clock jumped {abs(off_us) / 1e6:.1f} s {'back' if off_us < 0 else 'forward'} while its seq "
                f"ran on (seq {seq0} -> {seq1}): a clock fault?")

    def _stream_break(self, kind: str) -> None:
        """Stop taking samples of this stream (until the next START; the frame that confirmed the
        break is the first not taken) and report the break once."""
        self._broken = True
        self.stats.frames_after_break += 1
        if kind == "reset":
            self.stats.resets += 1
        else:
            self.stats.clock_jumps += 1
        words = self._break_words(kind)
        at = self.last_sample_t
        where = f" after {at:.1f} s board time" if at is not None else ""
        self._breaks.append(StreamBreak(kind, at, f"{self.port}: {words}{where}; one run is one board's "
                                                  "one timeline: its run ends here"))
        self._held.wake()

    def take_breaks(self) -> list[StreamBreak]:
        out, self._breaks = self._breaks, []
        return out

    def _write(self, raw: bytes) -> None:
        if self._error is not None:
            raise self._error
        if self._ser is None:
            raise DriverError(f"serial port {self.port} is not open")
        try:
            if self._fd is not None:
                view = memoryview(raw)
                while view:
                    try:
                        n = os.write(self._fd, view)
                    except BlockingIOError:
                        n = 0
                        self._ser.flush()  # tiny frames: only blocks if the driver buffer is full
                    view = view[n:]
            else:
                self._ser.write(raw)
        except (OSError, serial.SerialException) as exc:
            self._fail(f"serial port {self.port} vanished: {exc}")
            raise self._error from exc  # type: ignore[misc]

    def _check(self) -> None:
        if self._error is not None:
            raise self._error
        if self._ser is None:
            raise DriverError(f"serial port {self.port} is not open")

    # ---- commands --------------------------------------------------------------------------
    async def identify(self, timeout_s: float = 2.0) -> Identity:
        self._check()
        assert self._loop is not None
        async with self._cmd_lock:
            per_try = timeout_s / self.retries
            for _ in range(self.retries):
                self._ident_fut = self._loop.create_future()
                self._write(sf.cmd_id())
                try:
                    ident = await asyncio.wait_for(asyncio.shield(self._ident_fut), per_try)
                except asyncio.TimeoutError:
                    continue
                finally:
                    self._ident_fut = None
                self._note_restart(ident)
                self.identity = ident
                return ident
        self._check()
        raise DriverError(f"no identity reply from {self.port} within {timeout_s:g} s")

    def _note_restart(self, ident: Identity) -> None:
        """Count a restart of the board between the previous identity reply and this one: its
        `boots` moved (both reported). A power cycle is not seen here (boots is 1 after every
        power-on); a stream that broke on a reset is counted as `resets` as well."""
        before = self.identity
        if before is not None and before.boots is not None and ident.boots is not None and before.boots != ident.boots:
            self.stats.board_restarts += 1

    async def _command(self, raw: bytes, key: str) -> None:
        self._check()
        assert self._loop is not None
        async with self._cmd_lock:
            for _ in range(self.retries):
                fut = self._loop.create_future()
                self._ack_waiters[key] = fut
                self._write(raw)
                try:
                    await asyncio.wait_for(asyncio.shield(fut), self.ack_timeout_s)
                    return
                except asyncio.TimeoutError:
                    continue
                finally:
                    self._ack_waiters.pop(key, None)
        self._check()
        raise DriverError(f"board {self.port} did not acknowledge {key} ({self.retries} tries)")

    async def start(self) -> None:
        if self.identity is None:
            await self.identify()
        self._seq.reset()
        # a new stream: the board may have been stopped for a while (no period to hold to; its
        # 32-bit clock may have wrapped meanwhile, which the unwrapper still joins) or restarted
        # (programming, a power cycle between runs): breaks count within one stream only
        self._clock.reset_period()
        self._timeline.restart()
        self._broken = False
        await self._command(sf.cmd_start(), "START")

    def discard_held(self) -> int:
        self._drain()
        return self._held.discard()

    async def stop(self) -> None:
        await self._command(sf.cmd_stop(), "STOP")

    async def set_odr(self, odr_hz: float) -> None:
        await self._command(sf.cmd_odr(odr_hz), "ODR")
        self._clock.reset_period()
        self._timeline.restart()
        if self.identity is not None:
            self.identity = dataclasses.replace(self.identity, odr_hz=float(odr_hz))

    # ---- samples ---------------------------------------------------------------------------
    async def read_block(self, timeout_s: float = 1.0) -> SampleBlock:
        self._drain()
        await self._held.wait(timeout_s, self._check, lambda: self._error)
        self._drain()
        if self.identity is None and len(self._held):
            await self.identify()
        return self._held.take_block(self.identity)

    async def close(self) -> None:
        self._stop_reading()
        ser, self._ser = self._ser, None
        if self._thread is not None:
            await asyncio.to_thread(self._thread.join, 1.0)
            self._thread = None
        if ser is not None:
            try:
                ser.close()
            except Exception:  # noqa: BLE001 - closing a vanished port
                pass
