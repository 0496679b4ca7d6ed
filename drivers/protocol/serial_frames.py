"""Serial board frames (design 3.1): `$BODY*HH\\n`, HH = XOR of the BODY bytes in upper-case hex.

Pure codec: bytes in, frame records out, no I/O. The parser is incremental (feed it whatever a
read returned: split frames, several frames, garbage) and counts everything it skips in a
LinkStats, so a noisy line is measurable but never fatal.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import reduce
from operator import xor

import numpy as np

from drivers.base import LinkStats
from drivers.protocol.cal_record import N_SFEM, N_THERMAL, to_f32
from drivers.protocol import selfcal_frames
from contracts.types import Identity

_U32_MAX = (1 << 32) - 1
_U64_MAX = (1 << 64) - 1
_I32_MIN, _I32_MAX = -(1 << 31), (1 << 31) - 1
MAX_LINE_BYTES = 512  # no valid frame is this long; longer runs without a newline are garbage


def checksum(body: bytes) -> int:
    """XOR of every byte of BODY."""
    return reduce(xor, body, 0)


def encode(body: str | bytes) -> bytes:
    """`$BODY*HH\\n` for one frame body (e.g. "ID", "ODR,50", "D,1,2,3,4,5,6")."""
    raw = body.encode("ascii") if isinstance(body, str) else bytes(body)
    return b"$%s*%02X\n" % (raw, checksum(raw))


def fmt_number(value: float) -> str:
    """Shortest decimal text for a float field ("60", "3.9", "3.125", "-9.05")."""
    if float(value).is_integer():
        return str(int(value))
    return f"{value:.10g}"


# ---- station to board ----------------------------------------------------------------------

def cmd_id() -> bytes:
    return encode("ID")


def cmd_start() -> bytes:
    return encode("START")


def cmd_stop() -> bytes:
    return encode("STOP")


def cmd_odr(odr_hz: float) -> bytes:
    return encode(f"ODR,{fmt_number(odr_hz)}")


# ---- calibration write-back (program and verify): the record is drivers/protocol/cal_record.py

def fmt_crc(crc: int) -> str:
    """8 hex digits, upper case like the frame checksum."""
    return f"{int(crc) & 0xFFFFFFFF:08X}"


def fmt_f32(value: float) -> str:
    """Shortest decimal text that parses back to the same float32 ("-0.35", "1.2e-05" never: positional)."""
    return np.format_float_positional(np.float32(value), unique=True, trim="-")


def _values_body(kind: str, values, n: int) -> str:
    vals = to_f32(values)
    if len(vals) != n:
        raise ValueError(f"{kind} needs {n} values, got {len(vals)}")
    if not all(np.isfinite(vals)):
        raise ValueError(f"{kind}: every value must be a finite float32")
    return ",".join((kind, *(fmt_f32(v) for v in vals)))


def cmd_calw(tdb_mg_per_c, tdsf_ppm_per_c) -> bytes:
    """`$CALW,<tdb_x>,<tdb_y>,<tdb_z>,<tdsf_x>,<tdsf_y>,<tdsf_z>*HH`."""
    return encode(_values_body("CALW", [*tdb_mg_per_c, *tdsf_ppm_per_c], N_THERMAL))


def cmd_sfew(a_3x3, b_g) -> bytes:
    """`$SFEW,<a11>,<a12>,...,<a33>,<b_x>,<b_y>,<b_z>*HH` (A row by row, b in g)."""
    a = np.asarray(a_3x3, dtype=np.float64).reshape(-1)
    return encode(_values_body("SFEW", [*a, *np.asarray(b_g, dtype=np.float64).reshape(-1)], N_SFEM))


def cmd_calr() -> bytes:
    return encode("CALR")


def cmd_sfer() -> bytes:
    return encode("SFER")


def cmd_comp(on: bool) -> bytes:
    return encode(f"COMP,{1 if on else 0}")


def cmd_scal(on: bool) -> bytes:
    """On-board streaming calibrator off/on (drivers/protocol/selfcal_frames.py)."""
    return encode(f"SCAL,{1 if on else 0}")


def cmd_scrr() -> bytes:
    return encode("SCRR")


# ---- frame records -------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class SampleFrame:
    seq: int
    t_us: int
    ax: int
    ay: int
    az: int
    t: int

    def encode(self) -> bytes:
        return encode(f"D,{self.seq},{self.t_us},{self.ax},{self.ay},{self.az},{self.t}")


@dataclass(frozen=True, slots=True)
class IdentityFrame:
    identity: Identity

    def encode(self) -> bytes:
        i = self.identity
        return encode(
            f"I,{i.serial},{i.sensor},{i.fw},{fmt_number(i.ug_per_lsb)},{fmt_number(i.t_lsb_per_c)},"
            f"{fmt_number(i.t_lsb_at_25c)},{fmt_number(i.odr_hz)}"
        )


@dataclass(frozen=True, slots=True)
class AckFrame:
    command: str  # first field of the acknowledged command body ("START", "ODR", ...)
    args: tuple[str, ...] = ()

    def encode(self) -> bytes:
        return encode(",".join(("A", self.command, *self.args)))


@dataclass(frozen=True, slots=True)
class ErrorFrame:
    code: str
    text: str = ""

    def encode(self) -> bytes:
        return encode(f"E,{self.code},{self.text}")


@dataclass(frozen=True, slots=True)
class CalReadFrame:
    """`C,<tdb_x>,...,<tdsf_z>,<crc>,<comp>`: the board's stored thermal coefficients (reply to CALR)."""

    values: tuple[float, ...]  # 6: tdb x y z (mg/C), tdsf x y z (ppm/C), as float32
    crc: int
    comp: bool

    def encode(self) -> bytes:
        return encode(",".join(("C", *(fmt_f32(v) for v in self.values), fmt_crc(self.crc), "1" if self.comp else "0")))


@dataclass(frozen=True, slots=True)
class SfemReadFrame:
    """`S,<a11>,...,<a33>,<b_x>,<b_y>,<b_z>,<crc>`: the board's stored SFEM (reply to SFER)."""

    values: tuple[float, ...]  # 12
    crc: int

    def encode(self) -> bytes:
        return encode(",".join(("S", *(fmt_f32(v) for v in self.values), fmt_crc(self.crc))))


@dataclass(frozen=True, slots=True)
class CommandFrame:
    """A station-to-board command as the board parses it (`ID`, `START`, `STOP`, `ODR,<hz>`,
    `CALW,<6 values>`, `SFEW,<12 values>`, `CALR`, `SFER`, `COMP,<0|1>`); args stay text."""

    command: str
    args: tuple[str, ...] = ()


Frame = (SampleFrame | IdentityFrame | AckFrame | ErrorFrame | CommandFrame | CalReadFrame | SfemReadFrame
         | selfcal_frames.SegmentReportFrame | selfcal_frames.SelfCalResultFrame)


def _crc_field(text: str) -> int:
    if len(text) != 8:
        raise ValueError("CRC field must be 8 hex digits")
    return int(text, 16)


def _finite_floats(fields: list[str]) -> tuple[float, ...]:
    """Decimal fields as the float32 values they denote (the board stores float32)."""
    vals = to_f32([float(f) for f in fields])
    if not all(np.isfinite(vals)):
        raise ValueError("non-finite value")
    return vals


def _decode_body(fields: list[str], board_side: bool) -> Frame | None:
    """One frame from its comma-separated fields, or None if malformed/unknown."""
    kind = fields[0]
    try:
        if board_side:  # the board parses commands
            if kind in ("ID", "START", "STOP", "CALR", "SFER", "SCRR") and len(fields) == 1:
                return CommandFrame(kind)
            if kind == "ODR" and len(fields) == 2:
                float(fields[1])
                return CommandFrame(kind, (fields[1],))
            if (kind == "CALW" and len(fields) == 1 + N_THERMAL) or (kind == "SFEW" and len(fields) == 1 + N_SFEM):
                _finite_floats(fields[1:])
                return CommandFrame(kind, tuple(fields[1:]))
            if kind in ("COMP", "SCAL") and len(fields) == 2 and fields[1] in ("0", "1"):
                return CommandFrame(kind, (fields[1],))
            return None
        if kind == "D":
            if len(fields) != 7:
                return None
            seq, t_us, ax, ay, az, t = (int(f) for f in fields[1:])
            # In range or malformed: seq uint32, t_us uint64 (a 32- or 64-bit board clock), counts
            # int32. A checksum-valid frame with a 20-digit number must be counted, not stored.
            if not (0 <= seq <= _U32_MAX and 0 <= t_us <= _U64_MAX):
                return None
            if not all(_I32_MIN <= v <= _I32_MAX for v in (ax, ay, az, t)):
                return None
            return SampleFrame(seq, t_us, ax, ay, az, t)
        if kind == "I":
            if len(fields) != 8:
                return None
            return IdentityFrame(
                Identity(
                    serial=fields[1],
                    sensor=fields[2],
                    fw=fields[3],
                    ug_per_lsb=float(fields[4]),
                    t_lsb_per_c=float(fields[5]),
                    t_lsb_at_25c=float(fields[6]),
                    odr_hz=float(fields[7]),
                )
            )
        if kind == "C":
            if len(fields) != 1 + N_THERMAL + 2 or fields[-1] not in ("0", "1"):
                return None
            return CalReadFrame(_finite_floats(fields[1 : 1 + N_THERMAL]), _crc_field(fields[-2]), fields[-1] == "1")
        if kind == "S":
            if len(fields) != 1 + N_SFEM + 1:
                return None
            return SfemReadFrame(_finite_floats(fields[1 : 1 + N_SFEM]), _crc_field(fields[-1]))
        if kind in ("G", "R"):
            return selfcal_frames.decode(fields)
        if kind == "A":
            if len(fields) < 2 or not fields[1]:
                return None
            return AckFrame(fields[1], tuple(fields[2:]))
        if kind == "E":
            if len(fields) < 2:
                return None
            return ErrorFrame(fields[1], ",".join(fields[2:]))
    except ValueError:
        return None
    return None


class FrameParser:
    """Incremental parser. `feed(data)` returns the complete, valid frames in `data`.

    board_side=False parses what a board sends (D/I/A/E); True parses station commands (the
    simulated board uses it). Every skipped byte or bad frame is counted in `stats`.
    """

    def __init__(self, stats: LinkStats | None = None, *, board_side: bool = False) -> None:
        self.stats = stats if stats is not None else LinkStats()
        self.board_side = board_side
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[Frame]:
        buf = self._buf
        buf += data
        out: list[Frame] = []
        start = 0
        while True:
            nl = buf.find(b"\n", start)
            if nl < 0:
                break
            frame = self._line(bytes(buf[start:nl]))
            if frame is not None:
                out.append(frame)
            start = nl + 1
        if start:
            del buf[:start]
        if len(buf) > MAX_LINE_BYTES:  # a run with no newline: garbage, keep a possible frame start
            dollar = buf.rfind(b"$")
            keep = dollar if dollar >= 0 and len(buf) - dollar <= MAX_LINE_BYTES else len(buf)
            self.stats.bytes_skipped += keep
            del buf[:keep]
        return out

    def _line(self, line: bytes) -> Frame | None:
        stats = self.stats
        if line.endswith(b"\r"):
            line = line[:-1]
        dollar = line.rfind(b"$")  # a body never holds '$': anything before the last one is junk
        if dollar < 0:
            stats.bytes_skipped += len(line) + 1
            return None
        if dollar:
            stats.bytes_skipped += dollar
            line = line[dollar:]
        star = line.rfind(b"*")
        if star < 0 or len(line) - star != 3:
            stats.frames_malformed += 1
            return None
        body = line[1:star]
        try:
            want = int(line[star + 1 :], 16)
        except ValueError:
            stats.frames_malformed += 1
            return None
        if checksum(body) != want:
            stats.frames_bad_checksum += 1
            return None
        try:
            text = body.decode("ascii")
        except UnicodeDecodeError:
            stats.frames_malformed += 1
            return None
        frame = _decode_body(text.split(","), self.board_side) if text else None
        if frame is None:
            stats.frames_malformed += 1
            return None
        stats.frames_ok += 1
        if isinstance(frame, ErrorFrame):
            stats.errors_reported += 1
        return frame


class SeqTracker:
    """Counts samples lost to gaps in a wrapping sequence number and extends it to an index.

    A forward jump of less than half the range is a gap (lost samples); a backward jump (board
    reset, restart) resynchronises without counting. `index` is the extended (unwrapped) sequence
    number, continuous across wraps.
    """

    def __init__(self, bits: int) -> None:
        self.mod = 1 << bits
        self.half = self.mod >> 1
        self.last: int | None = None
        self.index: int = 0
        self.lost: int = 0
        self.resyncs: int = 0

    def reset(self) -> None:
        self.last = None

    def update(self, seq: int) -> int:
        """Feed the next received seq; returns the samples lost just before it."""
        seq %= self.mod
        if self.last is None:
            self.last = seq
            self.index = seq if self.index == 0 else self.index + 1
            return 0
        step = (seq - self.last) % self.mod
        self.last = seq
        if step == 0 or step > self.half:  # duplicate or backwards: resync, not a loss
            self.resyncs += 1
            self.index += 1
            return 0
        self.index += step
        self.lost += step - 1
        return step - 1


class ClockUnwrapper:
    """Board microsecond clock to a monotonic count across a 32-bit wrap (71.6 min).

    A 64-bit board clock never wraps and passes through unchanged. A 32-bit clock is unwrapped
    only when the new time follows the previous one by about the sample period modulo 2^32
    (`steps` periods when the sequence numbers say samples were lost in between): one corrupt
    `t_us = 0xFFFFFFFF` once counted as a wrap and shifted that DUT's time by 4,295 s.

    `update()` returns None for a time that does not follow the previous sample: an outlier the
    caller counts as malformed and skips. When the next time follows that outlier instead (the
    board's clock really jumped: a reset, an ODR change), the new timeline is taken as it is
    (no offset change), so a real jump costs one sample, never the rest of the run.
    Until the period is known (first two samples, after `reset_period()`), any forward step of
    less than half the range is accepted, as before.
    """

    WRAP = 1 << 32
    TOLERANCE = 0.5  # of the expected step: board timers are regular, corrupt values are not

    def __init__(self) -> None:
        self.offset = 0
        self.last: int | None = None
        self.period_us: float | None = None
        self.outliers = 0
        self.jumps = 0
        self._candidate: int | None = None
        self._skipped_steps = 0  # periods of the outliers since the last accepted sample

    def reset_period(self) -> None:
        """The sample rate changed: learn the period again from the next step."""
        self.period_us = None

    def _follows(self, step_us: int, steps: int) -> bool:
        if step_us <= 0 or step_us >= self.WRAP // 2:
            return False
        if self.period_us is None:
            return True
        expected = self.period_us * max(1, steps)
        return abs(step_us - expected) <= self.TOLERANCE * expected

    def update(self, t_us: int, steps: int = 1) -> int | None:
        """t_us: the frame's clock; steps: sample periods since the previous frame (1 + lost)."""
        last = self.last
        if last is None or last >= self.WRAP or t_us >= self.WRAP:  # first sample, or a 64-bit clock
            self.last = t_us
            self._candidate = None
            self._skipped_steps = 0
            return t_us + self.offset
        step = (t_us - last) % self.WRAP
        since_last = steps + self._skipped_steps
        if self._follows(step, since_last):
            if t_us < last:
                self.offset += self.WRAP
            self.period_us = step / max(1, since_last)
            self.last = t_us
            self._candidate = None
            self._skipped_steps = 0
            return t_us + self.offset
        cand = self._candidate
        if cand is not None and 0 < t_us - cand < self.WRAP // 2:
            # two samples agree with each other and not with the past: the clock jumped
            self.jumps += 1
            self.period_us = (t_us - cand) / max(1, steps)
            self.last = t_us
            self._candidate = None
            self._skipped_steps = 0
            return t_us + self.offset
        self._candidate = t_us
        self._skipped_steps += steps
        self.outliers += 1
        return None


class StreamTimeline:
    """Is a sample frame on its board's one timeline? (design 3.1: a run is one board's stream)

    A board's seq and clock move together: seq +k, t_us +k sample periods. A frame off that line
    is either garbage that passed the 8-bit checksum (1 in 256 corrupt lines does), a single one
    that the next frames contradict, or the start of another timeline: the board restarted while
    streaming (its seq went back; a reset by power, brown-out or watchdog) or its clock jumped
    while its seq ran on. Only CONFIRM_FRAMES off-line frames that agree with EACH OTHER (seq +1,
    t_us one period on) make a break; anything less is skipped as garbage, never fatal. A forward
    step in time is a gap, not a break, when it is short (MAX_FORWARD_GAP_S) or when the board
    was really silent that long: its frames before and after the step arrived that far apart on the
    station's clock (wall seconds x `speed`, the plant time per wall second: 1 on real hardware). A
    board that stalled and took no samples, counting the frames it sends, is silent for as long as
    its clock moves on; a clock that jumps forward is not.

    Until CONFIRM_FRAMES frames in a row agree, there is no line yet (a stream's first frames, or
    garbage among them) and nothing to break: every frame is fed on.

    `check(seq, t_us)` returns "ok" (feed the frame on), "skip" (off the line, not confirmed),
    "gap" (a confirmed forward gap: feed the frame on) or "reset" / "clock_jump" (the frame
    confirms a new timeline). `restart()` at every START and
    ODR change: the first frames after it define the line.
    """

    CONFIRM_FRAMES = 3
    TOLERANCE = 0.5  # of a sample period per seq step, plus 0.1 % of the step (clock drift)
    MAX_FORWARD_GAP_S = 10.0
    SEQ_MOD = 1 << 32
    T_WRAP = 1 << 32

    def __init__(self, speed: float = 1.0) -> None:
        self.speed = float(speed)
        # the latest confirmed break: (seq, t_us) before it, the first frame after it, the new
        # clock's offset from the old line in us
        self.broke: tuple[tuple[int, int], tuple[int, int], float] | None = None
        self.restart()

    def restart(self) -> None:
        self.last: tuple[int, int] | None = None  # (seq, t_us) of the last frame on the line
        self.last_wall_s: float | None = None  # when it arrived (the station's monotonic clock)
        self.period_us: float | None = None
        self._n_on_line = 0  # frames on the line in a row: under CONFIRM_FRAMES it is not a line yet
        self._cand: list[tuple[int, int]] = []
        self._cand_wall_s: float | None = None  # when the first off-line frame arrived

    def _dt_us(self, t_from: int, t_to: int) -> int:
        if t_from < self.T_WRAP and t_to < self.T_WRAP:  # a 32-bit clock: steps modulo its wrap
            d = (t_to - t_from) % self.T_WRAP
            return d - self.T_WRAP if d >= self.T_WRAP // 2 else d
        return t_to - t_from

    def _on_line(self, a: tuple[int, int], b: tuple[int, int], period_us: float) -> bool:
        k = (b[0] - a[0]) % self.SEQ_MOD
        if k == 0 or k >= self.SEQ_MOD // 2:
            return False
        dt = self._dt_us(a[1], b[1])
        expected = k * period_us
        return abs(dt - expected) <= self.TOLERANCE * period_us + 1e-3 * expected

    def check(self, seq: int, t_us: int, wall_s: float | None = None) -> str:
        """wall_s: when the frame arrived (time.monotonic()); None: unknown (no gap is explained)."""
        frame = (seq % self.SEQ_MOD, t_us)
        last = self.last
        if last is not None and self.period_us is not None and self._on_line(last, frame, self.period_us):
            self.period_us += 0.05 * ((self._dt_us(last[1], frame[1]) / ((frame[0] - last[0]) % self.SEQ_MOD))
                                      - self.period_us)
            self.last, self.last_wall_s, self._cand = frame, wall_s, []
            self._n_on_line += 1
            return "ok"
        if self._n_on_line < self.CONFIRM_FRAMES:
            # No line yet (the stream's first frames, or garbage among them): nothing to break.
            # The line is learned again from the last frame to this one when both move forward.
            forward = last is not None and 0 < (frame[0] - last[0]) % self.SEQ_MOD < self.SEQ_MOD // 2 \
                and self._dt_us(last[1], frame[1]) > 0
            if forward:
                assert last is not None
                self.period_us = self._dt_us(last[1], frame[1]) / ((frame[0] - last[0]) % self.SEQ_MOD)
                self._n_on_line = 2
            else:
                self.period_us, self._n_on_line = None, 1
            self.last, self.last_wall_s, self._cand = frame, wall_s, []
            return "ok"
        return self._candidate(frame, wall_s)

    def _cand_period_us(self) -> float | None:
        """The period the candidates draw (their own: a restarted board may run another ODR)."""
        cand = self._cand
        if len(cand) < 2:
            return None
        return self._dt_us(cand[0][1], cand[1][1]) / ((cand[1][0] - cand[0][0]) % self.SEQ_MOD)

    def _candidate(self, frame: tuple[int, int], wall_s: float | None) -> str:
        cand = self._cand
        agrees = False
        if cand:
            k = (frame[0] - cand[-1][0]) % self.SEQ_MOD
            own = self._cand_period_us()
            if own is None:  # the second candidate: forward in seq and in time
                agrees = 0 < k < self.SEQ_MOD // 2 and self._dt_us(cand[-1][1], frame[1]) > 0
            else:
                agrees = own > 0 and self._on_line(cand[-1], frame, own)
        if agrees:
            cand.append(frame)
        elif len(cand) >= 2 and 0 < (frame[0] - cand[-1][0]) % self.SEQ_MOD < self.SEQ_MOD // 2 \
                and self._dt_us(cand[-1][1], frame[1]) > 0:
            self._cand = cand = [cand[-1], frame]  # the run may start at the last one (garbage before it)
        else:
            self._cand, self._cand_wall_s = [frame], wall_s
            cand = self._cand
        if len(cand) < self.CONFIRM_FRAMES:
            return "skip"
        last, period_us = self.last, self.period_us
        assert last is not None
        k = (cand[0][0] - last[0]) % self.SEQ_MOD
        dt = self._dt_us(last[1], cand[0][1])
        silent_s = None if self._cand_wall_s is None or self.last_wall_s is None else self._cand_wall_s - self.last_wall_s
        gap_max_s = self.MAX_FORWARD_GAP_S + (0.0 if silent_s is None else 1.5 * silent_s * self.speed)
        self.broke = (last, cand[0], dt - (k if k < self.SEQ_MOD // 2 else 0) * (period_us or 0.0))
        own = self._cand_period_us()
        self.restart()
        self.last, self.last_wall_s, self.period_us, self._n_on_line = frame, wall_s, own, len(cand)
        if 0 < k < self.SEQ_MOD // 2 and 0 < dt <= gap_max_s * 1e6:
            return "gap"  # the board took no samples for a while but counted on: the line moves on
        return "reset" if k == 0 or k >= self.SEQ_MOD // 2 else "clock_jump"
