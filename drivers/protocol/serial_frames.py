"""Serial board frames (design 3.1): `$BODY*HH\\n`, HH = XOR of the BODY bytes in upper-case hex.

Pure codec: bytes in, frame records out, no I/O. The parser is incremental (feed it whatever a
read returned: split frames, several frames, garbage) and counts everything it skips in a
LinkStats, so a noisy line is measurable but never fatal.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import reduce
from operator import xor

from drivers.base import LinkStats
from station.types import Identity

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
class CommandFrame:
    """A station-to-board command as the board parses it (`ID`, `START`, `STOP`, `ODR,<hz>`)."""

    command: str
    args: tuple[str, ...] = ()


Frame = SampleFrame | IdentityFrame | AckFrame | ErrorFrame | CommandFrame


def _decode_body(fields: list[str], board_side: bool) -> Frame | None:
    """One frame from its comma-separated fields, or None if malformed/unknown."""
    kind = fields[0]
    try:
        if board_side:  # the board parses commands
            if kind in ("ID", "START", "STOP") and len(fields) == 1:
                return CommandFrame(kind)
            if kind == "ODR" and len(fields) == 2:
                float(fields[1])
                return CommandFrame(kind, (fields[1],))
            return None
        if kind == "D":
            if len(fields) != 7:
                return None
            seq, t_us, ax, ay, az, t = (int(f) for f in fields[1:])
            if seq < 0 or t_us < 0:
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

    A 64-bit board clock never wraps and passes through unchanged. A backward jump that does not
    look like a wrap (board reset) is passed through as is.
    """

    WRAP = 1 << 32

    def __init__(self) -> None:
        self.offset = 0
        self.last: int | None = None

    def update(self, t_us: int) -> int:
        last = self.last
        if last is not None and t_us < last and last < self.WRAP:
            if last >= self.WRAP // 2 and t_us < self.WRAP // 2 and last - t_us > self.WRAP // 2:
                self.offset += self.WRAP
        self.last = t_us
        return t_us + self.offset
