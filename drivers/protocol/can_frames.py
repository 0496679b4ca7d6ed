"""CAN board frames (design 3.2), CAN 2.0A, node id N = 1..127. Pure codec, no I/O.

    0x180+N board -> station  sample: int16 ax, ay, az (LE raw counts), int8 t (0 = 25 C,
                                      1 C per count), uint8 seq (wraps)
    0x600+N station -> board  command: 0x01 START, 0x02 STOP, 0x03 IDENTIFY, 0x04 SET_ODR + f32 Hz
    0x580+N board -> station  identity: four frames, byte 0 = index; 0,1: serial chars (7 each,
                                      NUL padded); 2: f32 ug_per_lsb; 3: f32 ODR Hz
                              issue 42 (docs/design.md 3.2), optional: 11: byte 1
                                      reset cause, 2 record state, 3 record version, 4-7 record
                                      generation (uint32 LE); 12,13: serial chars 15..28 (NUL
                                      padded, only for a serial longer than 14)

Calibration write-back (program and verify):
    0x600+N  0x05 CAL_FIELD  byte 1 field index 0..5 (tdb x y z mg/C, tdsf x y z ppm/C), bytes 2-5 f32
             0x06 CAL_COMMIT bytes 1-4 CRC-32 (zlib) of the six float32 values in index order
             0x07 CAL_READ   0x08 COMP byte 1 = 0 off / 1 on
    0x580+N  index 4: byte 1 status (0 stored, 1 CRC mismatch, 2 write failed), byte 2 comp 0/1,
                      bytes 3-6 stored CRC; index 5..10: stored field 0..5 (bytes 1-4 f32), sent
                      after CAL_READ before the index-4 frame.
The contract does not name the byte order of the CRC: little-endian like every other multi-byte
field of 3.2 (uint32 LE).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from contracts.board_health import RECORD_STATES, RESET_CAUSES, BoardRecordInfo
from contracts.types import Identity

SAMPLE_BASE = 0x180
IDENT_BASE = 0x580
CMD_BASE = 0x600

CMD_START = 0x01
CMD_STOP = 0x02
CMD_IDENTIFY = 0x03
CMD_SET_ODR = 0x04
CMD_CAL_FIELD = 0x05
CMD_CAL_COMMIT = 0x06
CMD_CAL_READ = 0x07
CMD_COMP = 0x08

CAL_STATUS_INDEX = 4
CAL_FIELD_INDEX0 = 5  # reply index of stored field 0; field k is index 5 + k
N_CAL_FIELDS = 6
CAL_STORED = 0
CAL_CRC_MISMATCH = 1
CAL_WRITE_FAILED = 2
CAL_STATUS_TEXT = {CAL_STORED: "stored", CAL_CRC_MISMATCH: "CRC mismatch", CAL_WRITE_FAILED: "write failed"}

SERIAL_MAX_CHARS = 14  # frames 0 and 1 (a board without frames 12/13)
SERIAL_MAX_CHARS_EXT = 28  # with frames 12 and 13
IDENT_HEALTH_INDEX = 11
IDENT_SERIAL_EXT = (12, 13)
TEMP_C_AT_ZERO = 25.0

_SAMPLE = struct.Struct("<hhhbB")
_F32 = struct.Struct("<f")
_U32 = struct.Struct("<I")


def check_node(node_id: int) -> int:
    if not 1 <= int(node_id) <= 127:
        raise ValueError(f"CAN node id must be 1..127, got {node_id}")
    return int(node_id)


def split_id(arbitration_id: int) -> tuple[int, int]:
    """(function base, node id) of an 11-bit identifier, e.g. 0x185 -> (0x180, 5)."""
    return arbitration_id & 0x780, arbitration_id & 0x7F


@dataclass(frozen=True, slots=True)
class CanSample:
    ax: int
    ay: int
    az: int
    t: int  # int8, C relative to 25 C
    seq: int  # uint8


def encode_sample(ax: int, ay: int, az: int, t: int, seq: int) -> bytes:
    return _SAMPLE.pack(ax, ay, az, t, seq & 0xFF)


def decode_sample(data: bytes) -> CanSample:
    """Raises ValueError for a frame that is not 8 bytes."""
    if len(data) != 8:
        raise ValueError(f"sample frame must be 8 bytes, got {len(data)}")
    return CanSample(*_SAMPLE.unpack(bytes(data)))


# _SAMPLE as a numpy record: many sample frames decoded at once (the CAN bus's bulk intake)
_SAMPLE_DTYPE = np.dtype([("ax", "<i2"), ("ay", "<i2"), ("az", "<i2"), ("t", "i1"), ("seq", "u1")])
assert _SAMPLE_DTYPE.itemsize == _SAMPLE.size == 8 and _SAMPLE.format == "<hhhbB"


def decode_samples(data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sample payloads (n, 8) uint8 -> (raw counts (n, 4) int64: ax ay az t, seq (n,) int64).

    Why: `decode_sample` per frame (a struct unpack into a dataclass) was most of a CAN board's
    cost per sample; this reads a whole run with the same field layout (`_SAMPLE_DTYPE`)."""
    rec = np.ascontiguousarray(data, dtype=np.uint8).reshape(-1).view(_SAMPLE_DTYPE)
    counts = np.empty((len(rec), 4), dtype=np.int64)
    for k, name in enumerate(("ax", "ay", "az", "t")):
        counts[:, k] = rec[name]
    return counts, rec["seq"].astype(np.int64)


MIN_GROUP = 8  # fewer sample frames of one node in a run: frame by frame (numpy's cost per call)


@dataclass(frozen=True)
class SampleGroup:
    """Consecutive sample frames of one node out of a run: payloads (n, 8) uint8, raw counts
    (n, 4) int64 (ax ay az t) and seq (n,) int64, as `decode_samples` gives them."""

    node: int
    data: np.ndarray
    counts: np.ndarray
    seq: np.ndarray


def route_run(ids: np.ndarray, data: np.ndarray, min_group: int | None = None) -> list[int | SampleGroup]:
    """A run of frames (ids (n,), payloads (n, 8)) in the order to hand them on: an int k is frame
    k on its own (not a sample frame: a reply, a command echo); a SampleGroup is consecutive sample
    frames of one node id, in order, between two such frames (a reply is handled after the samples
    before it and before those after it; different nodes' samples do not affect each other). A
    node's group under `min_group` (MIN_GROUP) frames comes as single frames (in its place, in order).
    Why: the bus hands each board its samples a run at a time, not a frame at a time."""
    min_group = MIN_GROUP if min_group is None else max(1, min_group)
    is_sample = (ids & 0x780) == SAMPLE_BASE
    if len(ids) < min_group or np.bincount(ids[is_sample] & 0x7F, minlength=1).max(initial=0) < min_group:
        return list(range(len(ids)))  # no group can be big enough: skip the sorting
    counts, seq = decode_samples(data)
    out: list[int | SampleGroup] = []
    a = 0
    for b in [*np.flatnonzero(~is_sample).tolist(), len(ids)]:
        if b > a:
            nodes = ids[a:b] & 0x7F
            order = np.argsort(nodes, kind="stable")
            for sel in np.split(order, np.flatnonzero(np.diff(nodes[order])) + 1):
                if len(sel) >= min_group:
                    k = a + sel
                    out.append(SampleGroup(int(nodes[sel[0]]), data[k], counts[k], seq[k]))
                else:
                    out.extend((a + sel).tolist())
        if b < len(ids):
            out.append(b)
        a = b + 1
    return out


def seq_stretches(seq: np.ndarray, last: int | None) -> list[tuple[int, int, bool]]:
    """(start, stop, clean) covering a board's sample seqs (uint8) in order: clean stretches
    simply go on, every seq one more (mod 256) than the one before (the first: than `last`, the
    tracker's); the frames in between (the first ever, a gap, a duplicate, a step back) come one
    per stretch, not clean. Why: a clean stretch can be taken at once (no loss, no resync)."""
    n = len(seq)
    prev = np.empty(n, dtype=np.int64)
    prev[0] = -1 if last is None else last
    prev[1:] = seq[:-1]
    out: list[tuple[int, int, bool]] = []
    a = 0
    for b in np.flatnonzero(((seq - prev) % 256 != 1) | (prev < 0)).tolist() + [n]:
        if b > a:
            out.append((a, b, True))
        if b < n:
            out.append((b, b + 1, False))
        a = b + 1
    return out


def sensor_from_ug(ug_per_lsb: float) -> str:
    """The CAN identity has no sensor field: the known boards differ by sensitivity."""
    if abs(ug_per_lsb - 60.0) < 0.5:
        return "LIS3DSH"
    if abs(ug_per_lsb - 3.9) < 0.05 or abs(ug_per_lsb - 62.4) < 0.05:
        return "ADXL355"
    return "unknown"


def encode_command(cmd: int, odr_hz: float | None = None) -> bytes:
    if cmd == CMD_SET_ODR:
        if odr_hz is None:
            raise ValueError("SET_ODR needs odr_hz")
        return bytes([CMD_SET_ODR]) + _F32.pack(float(odr_hz))
    if cmd not in (CMD_START, CMD_STOP, CMD_IDENTIFY):
        raise ValueError(f"unknown CAN command 0x{cmd:02X}")
    return bytes([cmd])


def decode_command(data: bytes) -> tuple[int, float | None]:
    """(command byte, odr_hz or None). Raises ValueError for an empty or short frame."""
    if not data:
        raise ValueError("empty command frame")
    cmd = data[0]
    if cmd == CMD_SET_ODR:
        if len(data) < 5:
            raise ValueError("SET_ODR frame shorter than 5 bytes")
        return cmd, _F32.unpack(bytes(data[1:5]))[0]
    return cmd, None


def encode_identity(serial: str, ug_per_lsb: float, odr_hz: float) -> list[bytes]:
    """The four 0x580+N reply payloads of a board without the issue-42 frames (serial at most 14)."""
    raw = serial.encode("ascii")
    if len(raw) > SERIAL_MAX_CHARS:
        raise ValueError(f"serial {serial!r} longer than {SERIAL_MAX_CHARS} characters")
    return _identity_base(raw, ug_per_lsb, odr_hz)


def _identity_base(raw: bytes, ug_per_lsb: float, odr_hz: float) -> list[bytes]:
    raw = raw.ljust(SERIAL_MAX_CHARS, b"\0")
    return [
        bytes([0]) + raw[:7],
        bytes([1]) + raw[7:14],
        bytes([2]) + _F32.pack(float(ug_per_lsb)),
        bytes([3]) + _F32.pack(float(odr_hz)),
    ]


def encode_identity_v2(serial: str, ug_per_lsb: float, odr_hz: float, *, reset_cause: str | None = None,
                       record: BoardRecordInfo | None = None) -> list[bytes]:
    """The reply of an issue-42 board (docs/design.md 3.2): frames 0..3, then 11 (reset
    cause and record), then 12 and 13 when the serial is longer than 14 characters (at most 28)."""
    raw = serial.encode("ascii")
    if len(raw) > SERIAL_MAX_CHARS_EXT:
        raise ValueError(f"serial {serial!r} longer than {SERIAL_MAX_CHARS_EXT} characters")
    out = _identity_base(raw[:SERIAL_MAX_CHARS], ug_per_lsb, odr_hz)
    out.append(encode_identity_health(reset_cause, record))
    if len(raw) > SERIAL_MAX_CHARS:
        ext = raw[SERIAL_MAX_CHARS:].ljust(SERIAL_MAX_CHARS_EXT - SERIAL_MAX_CHARS, b"\0")
        out += [bytes([12]) + ext[:7], bytes([13]) + ext[7:14]]
    return out


def encode_identity_health(reset_cause: str | None, record: BoardRecordInfo | None) -> bytes:
    """Identity frame 11: reset cause, record state, record version, record generation (uint32 LE)."""
    cause = RESET_CAUSES.index(reset_cause) if reset_cause in RESET_CAUSES else 0
    rec = record or BoardRecordInfo()
    state = RECORD_STATES.index(rec.rec_state) if rec.rec_state in RECORD_STATES else 0
    return bytes([IDENT_HEALTH_INDEX, cause, state, (rec.rec_ver or 0) & 0xFF]) + _U32.pack((rec.rec_gen or 0) & 0xFFFFFFFF)


def decode_identity_health(data: bytes) -> tuple[str, BoardRecordInfo]:
    """(reset cause, record info) of identity frame 11. A code this station does not know is
    "unknown" (a newer board's); ValueError for a frame shorter than 8 bytes."""
    if len(data) < 8 or data[0] != IDENT_HEALTH_INDEX:
        raise ValueError("identity frame 11 needs 8 bytes")
    cause = RESET_CAUSES[data[1]] if data[1] < len(RESET_CAUSES) else "unknown"
    state = RECORD_STATES[data[2]] if data[2] < len(RECORD_STATES) else "unknown"
    return cause, BoardRecordInfo(rec_ver=data[3], rec_gen=_U32.unpack(bytes(data[4:8]))[0], rec_slot=None,
                                  rec_state=state)


@dataclass
class IdentityAssembler:
    """Collects the identity frames (any order); `complete` once the four base frames are in.

    Frames 11, 12 and 13 (issue 42) are optional: `waits_for_more` says whether the reply so far
    can only be the beginning of a longer one (frames 0 and 1 hold 14 serial characters and 12/13
    have not come, or only one of them came): a driver then gives the rest a moment; otherwise
    the identity is taken as it is, so a board that sends none of them answers as fast as before."""

    serial_a: bytes | None = None
    serial_b: bytes | None = None
    ug_per_lsb: float | None = None
    odr_hz: float | None = None
    serial_c: bytes | None = None  # frame 12: serial chars 15..21
    serial_d: bytes | None = None  # frame 13: serial chars 22..28
    health: tuple[str, BoardRecordInfo] | None = None  # frame 11: reset cause, record info

    def feed(self, data: bytes) -> bool:
        """Returns True when the identity is complete. Malformed frames raise ValueError."""
        if not data:
            raise ValueError("empty identity frame")
        idx = data[0]
        if idx in (0, 1, *IDENT_SERIAL_EXT):
            part = bytes(data[1:8]).ljust(7, b"\0")
            if idx == 0:
                self.serial_a = part
            elif idx == 1:
                self.serial_b = part
            elif idx == 12:
                self.serial_c = part
            else:
                self.serial_d = part
        elif idx == IDENT_HEALTH_INDEX:
            self.health = decode_identity_health(data)
        elif idx in (2, 3):
            if len(data) < 5:
                raise ValueError(f"identity frame {idx} shorter than 5 bytes")
            value = _F32.unpack(bytes(data[1:5]))[0]
            if idx == 2:
                self.ug_per_lsb = value
            else:
                self.odr_hz = value
        else:
            raise ValueError(f"identity frame index {idx} not in 0..3, 11..13")
        return self.complete

    @property
    def complete(self) -> bool:
        return None not in (self.serial_a, self.serial_b, self.ug_per_lsb, self.odr_hz)

    @property
    def waits_for_more(self) -> bool:
        """The serial may go on in frames 12/13 that have not (all) come: frames 0 and 1 are full
        (14 characters, no NUL) without 12 and 13, or one of 12/13 came without the other."""
        if (self.serial_c is None) != (self.serial_d is None):
            return True
        full = self.serial_a is not None and self.serial_b is not None and b"\0" not in self.serial_a + self.serial_b
        return full and self.serial_c is None

    @property
    def extension_incomplete(self) -> bool:
        """Only one of frames 12/13 came: the serial cannot be known (the reply is asked again)."""
        return (self.serial_c is None) != (self.serial_d is None)

    @property
    def serial(self) -> str:
        raw = (self.serial_a or b"") + (self.serial_b or b"")
        if self.serial_c is not None and self.serial_d is not None and b"\0" not in raw:
            raw += self.serial_c + self.serial_d
        return raw.split(b"\0", 1)[0].decode("ascii", errors="replace")

    def identity(self, sensor: str | None) -> Identity:
        """The complete identity as the station's Identity (sensor: from configuration, else guessed
        from the sensitivity). ValueError for a NaN/zero sensitivity or ODR (Identity refuses it)."""
        assert self.ug_per_lsb is not None and self.odr_hz is not None
        ug = float(f"{self.ug_per_lsb:.7g}")
        odr = float(f"{self.odr_hz:.7g}")
        cause, record = self.health if self.health is not None else (None, None)
        return Identity(serial=self.serial, sensor=sensor or sensor_from_ug(ug), fw="",
                        ug_per_lsb=ug, t_lsb_per_c=1.0, t_lsb_at_25c=0.0, odr_hz=odr,
                        reset_cause=cause, record=record)


def float32(value: float) -> float:
    """The value as it survives a float32 field (3.9 -> 3.9000000954); for exact comparisons."""
    return _F32.unpack(_F32.pack(value))[0]


# ---- calibration write-back ----------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class CalCommand:
    """A decoded calibration command (board side): CAL_FIELD, CAL_COMMIT, CAL_READ or COMP."""

    cmd: int
    field: int | None = None  # CAL_FIELD
    value: float | None = None  # CAL_FIELD, float32
    crc: int | None = None  # CAL_COMMIT
    on: bool | None = None  # COMP


def encode_cal_field(index: int, value: float) -> bytes:
    if not 0 <= int(index) < N_CAL_FIELDS:
        raise ValueError(f"calibration field index must be 0..{N_CAL_FIELDS - 1}, got {index}")
    return bytes([CMD_CAL_FIELD, int(index)]) + _F32.pack(float(value))


def encode_cal_commit(crc: int) -> bytes:
    return bytes([CMD_CAL_COMMIT]) + _U32.pack(int(crc) & 0xFFFFFFFF)


def encode_cal_read() -> bytes:
    return bytes([CMD_CAL_READ])


def encode_comp(on: bool) -> bytes:
    return bytes([CMD_COMP, 1 if on else 0])


def decode_cal_command(data: bytes) -> CalCommand:
    """Raises ValueError for a frame that is not a well-formed calibration command."""
    if not data:
        raise ValueError("empty command frame")
    cmd = data[0]
    if cmd == CMD_CAL_FIELD:
        if len(data) < 6 or data[1] >= N_CAL_FIELDS:
            raise ValueError("CAL_FIELD frame needs a field index 0..5 and a float32")
        return CalCommand(cmd, field=data[1], value=_F32.unpack(bytes(data[2:6]))[0])
    if cmd == CMD_CAL_COMMIT:
        if len(data) < 5:
            raise ValueError("CAL_COMMIT frame shorter than 5 bytes")
        return CalCommand(cmd, crc=_U32.unpack(bytes(data[1:5]))[0])
    if cmd == CMD_CAL_READ:
        return CalCommand(cmd)
    if cmd == CMD_COMP:
        if len(data) < 2 or data[1] not in (0, 1):
            raise ValueError("COMP frame needs byte 1 = 0 or 1")
        return CalCommand(cmd, on=bool(data[1]))
    raise ValueError(f"0x{cmd:02X} is not a calibration command")


def encode_cal_status(status: int, comp: bool, crc: int) -> bytes:
    """Reply frame index 4: status, compensation flag, stored CRC."""
    return bytes([CAL_STATUS_INDEX, int(status), 1 if comp else 0]) + _U32.pack(int(crc) & 0xFFFFFFFF)


def encode_cal_stored_field(index: int, value: float) -> bytes:
    """Reply frame index 5 + index: stored field `index` (0..5)."""
    if not 0 <= int(index) < N_CAL_FIELDS:
        raise ValueError(f"calibration field index must be 0..{N_CAL_FIELDS - 1}, got {index}")
    return bytes([CAL_FIELD_INDEX0 + int(index)]) + _F32.pack(float(value))


@dataclass(frozen=True, slots=True)
class CalStatus:
    status: int
    comp: bool
    crc: int

    @property
    def text(self) -> str:
        return CAL_STATUS_TEXT.get(self.status, f"status {self.status}")


def commit_refusal(status: int) -> tuple[str, str] | None:
    """Why a CAL_COMMIT status is not "stored": (CalibrationError kind, text); None when stored.
    One table of the board's answers, so the driver only adds its node to the text."""
    if status == CAL_STORED:
        return None
    if status == CAL_CRC_MISMATCH:
        return "crc_mismatch", "the board's CRC of the received fields does not match the commit CRC (nothing stored)"
    if status == CAL_WRITE_FAILED:
        return "refused", "write failed"
    return "refused", f"unknown commit status {status}"


def decode_cal_reply(data: bytes) -> tuple[int, CalStatus | float]:
    """(frame index, CalStatus for index 4 or the float32 value for 5..10). ValueError if malformed."""
    if not data:
        raise ValueError("empty reply frame")
    idx = data[0]
    if idx == CAL_STATUS_INDEX:
        if len(data) < 7:
            raise ValueError("calibration status frame shorter than 7 bytes")
        return idx, CalStatus(data[1], bool(data[2]), _U32.unpack(bytes(data[3:7]))[0])
    if CAL_FIELD_INDEX0 <= idx < CAL_FIELD_INDEX0 + N_CAL_FIELDS:
        if len(data) < 5:
            raise ValueError(f"stored field frame {idx} shorter than 5 bytes")
        return idx, _F32.unpack(bytes(data[1:5]))[0]
    raise ValueError(f"frame index {idx} is not a calibration reply")


def is_cal_reply(data: bytes) -> bool:
    return bool(data) and CAL_STATUS_INDEX <= data[0] < CAL_FIELD_INDEX0 + N_CAL_FIELDS
