"""CAN board frames (design 3.2), CAN 2.0A, node id N = 1..127. Pure codec, no I/O.

    0x180+N board -> station  sample: int16 ax, ay, az (LE raw counts), int8 t (0 = 25 C,
                                      1 C per count), uint8 seq (wraps)
    0x600+N station -> board  command: 0x01 START, 0x02 STOP, 0x03 IDENTIFY, 0x04 SET_ODR + f32 Hz
    0x580+N board -> station  identity: four frames, byte 0 = index; 0,1: serial chars (7 each,
                                      NUL padded); 2: f32 ug_per_lsb; 3: f32 ODR Hz
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

SAMPLE_BASE = 0x180
IDENT_BASE = 0x580
CMD_BASE = 0x600

CMD_START = 0x01
CMD_STOP = 0x02
CMD_IDENTIFY = 0x03
CMD_SET_ODR = 0x04

SERIAL_MAX_CHARS = 14
TEMP_C_AT_ZERO = 25.0

_SAMPLE = struct.Struct("<hhhbB")
_F32 = struct.Struct("<f")


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
    """The four 0x580+N reply payloads."""
    raw = serial.encode("ascii")
    if len(raw) > SERIAL_MAX_CHARS:
        raise ValueError(f"serial {serial!r} longer than {SERIAL_MAX_CHARS} characters")
    raw = raw.ljust(SERIAL_MAX_CHARS, b"\0")
    return [
        bytes([0]) + raw[:7],
        bytes([1]) + raw[7:14],
        bytes([2]) + _F32.pack(float(ug_per_lsb)),
        bytes([3]) + _F32.pack(float(odr_hz)),
    ]


@dataclass
class IdentityAssembler:
    """Collects the four identity frames (any order); `complete` once all four are in."""

    serial_a: bytes | None = None
    serial_b: bytes | None = None
    ug_per_lsb: float | None = None
    odr_hz: float | None = None

    def feed(self, data: bytes) -> bool:
        """Returns True when the identity is complete. Malformed frames raise ValueError."""
        if not data:
            raise ValueError("empty identity frame")
        idx = data[0]
        if idx in (0, 1):
            part = bytes(data[1:8]).ljust(7, b"\0")
            if idx == 0:
                self.serial_a = part
            else:
                self.serial_b = part
        elif idx in (2, 3):
            if len(data) < 5:
                raise ValueError(f"identity frame {idx} shorter than 5 bytes")
            value = _F32.unpack(bytes(data[1:5]))[0]
            if idx == 2:
                self.ug_per_lsb = value
            else:
                self.odr_hz = value
        else:
            raise ValueError(f"identity frame index {idx} not in 0..3")
        return self.complete

    @property
    def complete(self) -> bool:
        return None not in (self.serial_a, self.serial_b, self.ug_per_lsb, self.odr_hz)

    @property
    def serial(self) -> str:
        raw = (self.serial_a or b"") + (self.serial_b or b"")
        return raw.split(b"\0", 1)[0].decode("ascii", errors="replace")


def float32(value: float) -> float:
    """The value as it survives a float32 field (3.9 -> 3.9000000954); for exact comparisons."""
    return _F32.unpack(_F32.pack(value))[0]
