"""The calibration record as a board stores it (design 3.1/3.2, program and verify).

The board keeps float32 values; the CRC is CRC-32 (zlib) of those float32 values, little-endian,
in the order written. The station therefore rounds to float32 BEFORE writing and writes the
shortest decimal that parses back to exactly that float32, so its own CRC and the board's agree.
Shared by both links' codecs, the driver interface and the simulated boards' NVM.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np


N_THERMAL = 6  # tdb_x, tdb_y, tdb_z (mg/C), tdsf_x, tdsf_y, tdsf_z (ppm/C)
N_SFEM = 12  # a11..a33 row by row, b_x, b_y, b_z (g)


def to_f32(values) -> tuple[float, ...]:
    """The values as the board stores them (IEEE float32), back in Python floats."""
    arr = np.asarray(values, dtype=np.float32).reshape(-1) + np.float32(0.0)  # -0.0 -> 0.0
    return tuple(float(v) for v in arr)


def crc32_f32(values) -> int:
    """CRC-32 (zlib) of the values packed as IEEE float32 little-endian (design 3.1/3.2)."""
    vals = to_f32(values)
    return zlib.crc32(struct.pack(f"<{len(vals)}f", *vals)) & 0xFFFFFFFF
