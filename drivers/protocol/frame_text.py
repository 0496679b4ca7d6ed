"""The text of serial board frames (design 3.1): framing and number formats, shared by every codec.

`$BODY*HH\\n`, HH = XOR of the BODY bytes in upper-case hex. Kept apart from serial_frames.py so
that the codecs of the optional frame families (selfcal_frames.py, sfem_cubic_frames.py,
identity_keys.py) write their numbers exactly as the base protocol does; serial_frames re-exports
all of it (callers import it there).
"""

from __future__ import annotations

from functools import reduce
from operator import xor

import numpy as np

from drivers.protocol.cal_record import to_f32


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


def fmt_crc(crc: int) -> str:
    """8 hex digits, upper case like the frame checksum."""
    return f"{int(crc) & 0xFFFFFFFF:08X}"


def fmt_f32(value: float) -> str:
    """Shortest decimal text that parses back to the same float32 ("-0.35", "1.2e-05" never: positional)."""
    return np.format_float_positional(np.float32(value), unique=True, trim="-")


def fmt_f32_short(value: float) -> str:
    """The shortest decimal text (positional or scientific) that parses back to the same float32
    through float() then float32, as the board's parser does (firmware/core/fw_num.h). Why not
    fmt_f32: a cubic coefficient (per C^3) can be 1e-9 or less, and 12 of them in positional text
    would overrun the board's line; scientific keeps every SFTW line under 200 bytes."""
    v = np.float32(value)
    texts = [np.format_float_positional(v, unique=True, trim="-"),
             np.format_float_scientific(v, unique=True, trim="-")]
    for text in sorted(texts, key=len):
        if np.float32(float(text)) == v:
            return text
    return repr(float(v))  # a float64 repr always holds the float32 exactly


def parse_crc(text: str) -> int:
    """A CRC field: exactly 8 hex digits (fmt_crc's form)."""
    if len(text) != 8:
        raise ValueError("CRC field must be 8 hex digits")
    return int(text, 16)


def parse_finite_f32(fields: list[str]) -> tuple[float, ...]:
    """Decimal fields as the float32 values they denote (the board stores float32); ValueError on a
    non-finite one."""
    vals = to_f32([float(f) for f in fields])
    if not all(np.isfinite(vals)):
        raise ValueError("non-finite value")
    return vals
