"""The firmware's NVM file decoded from its bytes, and records encoded, independently of the C code
(layout: firmware/core/fw_nvm.h): two slots of SLOT_BYTES, each holding a version-1 record (104
bytes, the last word the CRC-32 of the 100 before it) or a version-2 record (312 bytes: version 1
plus the cubic SFEM, record CRC over the 308 before it); the valid record with the highest
generation is the one in force. A record with a non-finite value is never valid, whatever its CRCs
say (a board must never apply one), and neither is a version-2 record whose t_lo_c >= t_hi_c."""

from __future__ import annotations

import math
import struct
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

SLOT_BYTES = 512  # firmware/core/fw_hal.h FW_NVM_SLOT_BYTES (256 before the version-2 record)
RECORD_BYTES = 104
RECORD2_BYTES = 312
MAGIC = 0x4C414346
N_CUBIC = 51  # t_ref_c, t_lo_c, t_hi_c, c[0..3][0..11]


@dataclass(frozen=True)
class NvmRecord:
    slot: int
    generation: int
    thermal: tuple[float, ...]
    thermal_crc: int
    sfem: tuple[float, ...] | None
    sfem_crc: int
    comp: bool
    version: int = 1
    cubic: tuple[float, ...] | None = None  # version 2: the 51 values in the $SFTC CRC order
    cubic_crc: int = 0


def crc_f32(values: Iterable[float]) -> int:
    """CRC-32 (zlib) of float32 little-endian values, -0.0 as +0.0 (design 3.1)."""
    return zlib.crc32(b"".join(struct.pack("<f", float(v) + 0.0) for v in values))


def encode_record(generation: int, thermal: Sequence[float], sfem: Sequence[float] | None = None,
                  comp: bool = False, cubic: Sequence[float] | None = None, *, fix_crcs: bool = True) -> bytes:
    """A record as the layout says (version 2 when `cubic`, the 51 values, is given). With
    fix_crcs every CRC is right for the bytes written, whatever the values (NaN included): what a
    board must still refuse."""
    thermal = [float(v) for v in thermal]
    out = bytearray(RECORD2_BYTES if cubic is not None else RECORD_BYTES)
    struct.pack_into("<IHHI", out, 0, MAGIC, 2 if cubic is not None else 1, len(out), generation)
    struct.pack_into("<6f", out, 12, *thermal)
    struct.pack_into("<I", out, 36, zlib.crc32(bytes(out[12:36])))
    if sfem is not None:
        out[40] = 1
        struct.pack_into("<12f", out, 44, *[float(v) for v in sfem])
        struct.pack_into("<I", out, 92, zlib.crc32(bytes(out[44:92])))
    out[96] = 1 if comp else 0
    if cubic is not None:
        assert len(cubic) == N_CUBIC
        struct.pack_into(f"<{N_CUBIC}f", out, 100, *[float(v) for v in cubic])
        struct.pack_into("<I", out, 304, crc_f32(cubic))
    if fix_crcs:
        struct.pack_into("<I", out, len(out) - 4, zlib.crc32(bytes(out[:-4])))
    return bytes(out)


def slot_image(record: bytes | None) -> bytes:
    """One slot as flash holds it: the record, then erased bytes."""
    rec = record or b""
    return rec + b"\xff" * (SLOT_BYTES - len(rec))


def decode_slot(slot: int, raw: bytes) -> NvmRecord | None:
    """The record of one slot, or None when the slot is erased or does not check."""
    if len(raw) < RECORD_BYTES or raw[:4] == b"\xff\xff\xff\xff":
        return None
    magic, version, length, generation = struct.unpack_from("<IHHI", raw, 0)
    if magic != MAGIC or (version, length) not in ((1, RECORD_BYTES), (2, RECORD2_BYTES)) or len(raw) < length:
        return None
    (rec_crc,) = struct.unpack_from("<I", raw, length - 4)
    if zlib.crc32(raw[:length - 4]) != rec_crc or raw[40] > 1 or raw[96] > 1:
        return None
    thermal = struct.unpack_from("<6f", raw, 12)
    (thermal_crc,) = struct.unpack_from("<I", raw, 36)
    has_sfem = raw[40]
    sfem = struct.unpack_from("<12f", raw, 44) if has_sfem else None
    (sfem_crc,) = struct.unpack_from("<I", raw, 92)
    if zlib.crc32(raw[12:36]) != thermal_crc:
        return None
    if (sfem is not None and zlib.crc32(raw[44:92]) != sfem_crc) or (sfem is None and sfem_crc != 0):
        return None
    values = [*thermal, *(sfem or ())]
    cubic, cubic_crc = None, 0
    if version == 2:
        cubic = struct.unpack_from(f"<{N_CUBIC}f", raw, 100)
        (cubic_crc,) = struct.unpack_from("<I", raw, 304)
        if crc_f32(cubic) != cubic_crc:
            return None
        values += cubic
    if not all(math.isfinite(v) for v in values):
        return None
    if cubic is not None and not cubic[1] < cubic[2]:
        return None
    return NvmRecord(slot, generation, thermal, thermal_crc, sfem, sfem_crc, bool(raw[96]), version, cubic, cubic_crc)


def read_nvm(data: bytes) -> NvmRecord | None:
    """The record a booting board applies: the valid one with the highest generation."""
    recs = [r for k in range(2) if (r := decode_slot(k, data[k * SLOT_BYTES:(k + 1) * SLOT_BYTES])) is not None]
    return max(recs, key=lambda r: r.generation, default=None)
