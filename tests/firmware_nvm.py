"""The firmware's NVM file decoded from its bytes, independently of the C code (layout:
firmware/core/fw_nvm.h): two slots of 256 bytes, each a 104-byte record whose last word is the
CRC-32 of the 100 before it; the valid record with the highest generation is the one in force."""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

SLOT_BYTES = 256
RECORD_BYTES = 104
MAGIC = 0x4C414346


@dataclass(frozen=True)
class NvmRecord:
    slot: int
    generation: int
    thermal: tuple[float, ...]
    thermal_crc: int
    sfem: tuple[float, ...] | None
    sfem_crc: int
    comp: bool


def decode_slot(slot: int, raw: bytes) -> NvmRecord | None:
    """The record of one slot, or None when the slot is erased or does not check."""
    if len(raw) < RECORD_BYTES or raw[:4] == b"\xff\xff\xff\xff":
        return None
    magic, version, length, generation = struct.unpack_from("<IHHI", raw, 0)
    (rec_crc,) = struct.unpack_from("<I", raw, 100)
    if magic != MAGIC or version != 1 or length != RECORD_BYTES or zlib.crc32(raw[:100]) != rec_crc:
        return None
    thermal = struct.unpack_from("<6f", raw, 12)
    (thermal_crc,) = struct.unpack_from("<I", raw, 36)
    has_sfem = raw[40]
    sfem = struct.unpack_from("<12f", raw, 44) if has_sfem else None
    (sfem_crc,) = struct.unpack_from("<I", raw, 92)
    if zlib.crc32(raw[12:36]) != thermal_crc:
        return None
    return NvmRecord(slot, generation, thermal, thermal_crc, sfem, sfem_crc, bool(raw[96]))


def read_nvm(data: bytes) -> NvmRecord | None:
    """The record a booting board applies: the valid one with the highest generation."""
    recs = [r for k in range(2) if (r := decode_slot(k, data[k * SLOT_BYTES:(k + 1) * SLOT_BYTES])) is not None]
    return max(recs, key=lambda r: r.generation, default=None)
