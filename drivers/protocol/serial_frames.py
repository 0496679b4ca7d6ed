"""Serial board frames (design 3.1): `$BODY*HH\\n`, HH = XOR of the BODY bytes in upper-case hex.

Pure codec: bytes in, frame records out, no I/O. The parser is incremental (feed it whatever a
read returned: split frames, several frames, garbage) and counts everything it skips in a
LinkStats, so a noisy line is measurable but never fatal. The sample stream's seq and clock
bookkeeping (SeqTracker, ClockUnwrapper, StreamTimeline) is drivers/protocol/stream_timeline.py,
the framing and number texts frame_text.py, the optional families (issue 42) identity_keys.py and
sfem_cubic_frames.py, beside selfcal_frames.py: all re-exported here (callers import them here).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from drivers.base import LinkStats
from drivers.protocol.cal_record import N_SFEM, N_THERMAL, to_f32
from drivers.protocol import selfcal_frames
from drivers.protocol.sample_lines import SampleLines, decode_sample_lines
from drivers.protocol.stream_timeline import ClockUnwrapper as ClockUnwrapper  # re-exported: callers import them here
from drivers.protocol.stream_timeline import SeqTracker as SeqTracker
from drivers.protocol.stream_timeline import StreamTimeline as StreamTimeline
from drivers.protocol import sfem_cubic_frames
from drivers.protocol.frame_text import checksum as checksum, encode as encode, fmt_crc as fmt_crc  # re-exported
from drivers.protocol.frame_text import fmt_f32 as fmt_f32, fmt_f32_short as fmt_f32_short, fmt_number as fmt_number
from drivers.protocol.frame_text import parse_crc, parse_finite_f32
from drivers.protocol.identity_keys import health_fields, identity_health, parse_key_values, record_fields, record_info
from drivers.protocol.sfem_cubic_frames import SfemCubicHeadFrame as SfemCubicHeadFrame  # re-exported
from drivers.protocol.sfem_cubic_frames import SfemCubicRowFrame as SfemCubicRowFrame
from drivers.protocol.sfem_cubic_frames import cmd_sftc as cmd_sftc, cmd_sftr as cmd_sftr, cmd_sftw as cmd_sftw
from drivers.protocol.sfem_cubic_frames import sfem_cubic_commands as sfem_cubic_commands
from contracts.board_health import BoardRecordInfo
from contracts.types import Identity

_U32_MAX = (1 << 32) - 1
_U64_MAX = (1 << 64) - 1
_I32_MIN, _I32_MAX = -(1 << 31), (1 << 31) - 1
# no valid frame is this long; longer runs without a newline are garbage. A `T` row (12 float32 in
# positional text, up to ~50 characters each for the tiniest values) is the longest frame there is.
MAX_LINE_BYTES = 1024


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

def _values_body(kind: str, values: Iterable[float], n: int) -> str:
    vals = to_f32(values)
    if len(vals) != n:
        raise ValueError(f"{kind} needs {n} values, got {len(vals)}")
    if not all(np.isfinite(vals)):
        raise ValueError(f"{kind}: every value must be a finite float32")
    return ",".join((kind, *(fmt_f32(v) for v in vals)))


def cmd_calw(tdb_mg_per_c: Iterable[float], tdsf_ppm_per_c: Iterable[float]) -> bytes:
    """`$CALW,<tdb_x>,<tdb_y>,<tdb_z>,<tdsf_x>,<tdsf_y>,<tdsf_z>*HH`."""
    return encode(_values_body("CALW", [*tdb_mg_per_c, *tdsf_ppm_per_c], N_THERMAL))


def cmd_sfew(a_3x3: ArrayLike, b_g: ArrayLike) -> bytes:
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
        return encode(",".join((
            f"I,{i.serial},{i.sensor},{i.fw},{fmt_number(i.ug_per_lsb)},{fmt_number(i.t_lsb_per_c)},"
            f"{fmt_number(i.t_lsb_at_25c)},{fmt_number(i.odr_hz)}", *health_fields(i))))


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
    record: BoardRecordInfo | None = None  # `rec_*=` after <comp> (version-2 firmware)

    def encode(self) -> bytes:
        return encode(",".join(("C", *(fmt_f32(v) for v in self.values), fmt_crc(self.crc), "1" if self.comp else "0",
                                *record_fields(self.record))))


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
         | SfemCubicHeadFrame | SfemCubicRowFrame
         | selfcal_frames.SegmentReportFrame | selfcal_frames.SelfCalResultFrame)

UNSOLICITED_ERRORS = ("SENSOR", "NVM")  # `E` codes a board sends of its own accord, never a command's reply


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
                parse_finite_f32(fields[1:])
                return CommandFrame(kind, tuple(fields[1:]))
            if kind in ("COMP", "SCAL") and len(fields) == 2 and fields[1] in ("0", "1"):
                return CommandFrame(kind, (fields[1],))
            if kind in ("SFTW", "SFTC", "SFTR"):
                args = sfem_cubic_frames.board_command_args(fields)
                return CommandFrame(kind, args) if args is not None else None
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
            if len(fields) < 8:
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
                    **identity_health(parse_key_values(fields[8:])),
                )
            )
        if kind == "C":
            n = 1 + N_THERMAL + 2
            if len(fields) < n or fields[n - 1] not in ("0", "1"):
                return None
            return CalReadFrame(parse_finite_f32(fields[1 : 1 + N_THERMAL]), parse_crc(fields[n - 2]), fields[n - 1] == "1",
                                record_info(parse_key_values(fields[n:])))
        if kind == "T":
            return sfem_cubic_frames.decode(fields)
        if kind == "S":
            if len(fields) != 1 + N_SFEM + 1:
                return None
            return SfemReadFrame(parse_finite_f32(fields[1 : 1 + N_SFEM]), parse_crc(fields[-1]))
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

    def feed_samples(self, data: bytes) -> SampleLines | None:
        """The fast path for a read of nothing but clean sample frames (sample_lines.py): `data` is
        taken in; when every complete line held is such a frame, they are decoded at once, counted
        and returned (a partial line stays for the next read). Else None, and nothing is consumed:
        `feed(b"")` then reads the lines one by one, as ever."""
        buf = self._buf
        buf += data
        end = buf.rfind(b"\n") + 1
        if end == 0 or self.board_side:
            return None
        lines = decode_sample_lines(bytes(buf[:end]))
        if lines is None:
            return None
        del buf[:end]
        self.stats.frames_ok += len(lines)
        return lines

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
            if frame.code == "SENSOR":
                stats.sensor_reinits_reported += 1
        return frame
