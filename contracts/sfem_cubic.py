"""The version-2 NVM record: a cubic thermal SFEM that the board applies itself (sensors2023 eq. 8).

docs/design.md 3.1 ("version-2 record") is the contract; this module is the station's own
statement of it, written from the contract and not from the C code, so that a test comparing the
board's output with `compensate_counts` compares two independent readings of one datasheet.

With compensation on and a cubic SFEM stored, the board takes per sample its own temperature T,
clamped to [t_lo_c, t_hi_c], d = T - t_ref_c, and

    A(T)_ij = sum_k c[k][3i+j] d^k,   b(T)_i = sum_k c[k][9+i] d^k      (k = 0..3, b in g)
    out     = A(T) (raw - b(T) / lsb_g)                                   (counts in, counts out)

Eq. 13 (the linear TDB/TDSF of version 1) is NOT applied on top: the cubic model was fitted on
raw readings and already holds the thermal drift.

The board keeps float32, and the record's CRC is CRC-32 (zlib) of the 51 float32 little-endian
values in contract order: t_ref_c, t_lo_c, t_hi_c, c[0][0..11], c[1][0..11], c[2][0..11],
c[3][0..11]. The station rounds to float32 BEFORE writing (`to_f32`), as drivers/protocol/
cal_record.to_f32 does for version 1, so its CRC and the board's agree bit for bit.
"""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

N_POWERS = 4  # d^0 .. d^3
N_COEF = 12  # a11 a12 a13 a21 a22 a23 a31 a32 a33 (row by row), bx by bz (g)
N_VALUES = 3 + N_POWERS * N_COEF  # 51: what the CRC covers


def _f32(values: ArrayLike) -> tuple[float, ...]:
    """Values as IEEE float32 hold them, back in Python floats; -0.0 becomes 0.0 (the same rule as
    drivers/protocol/cal_record.to_f32, restated here: contracts import nothing above them)."""
    with np.errstate(over="ignore"):  # beyond float32's range: inf, which validation then refuses
        arr = np.asarray(values, dtype=np.float64).reshape(-1).astype(np.float32) + np.float32(0.0)
    return tuple(float(v) for v in arr)


@dataclass(frozen=True)
class SfemCubicRecord:
    """One cubic thermal SFEM (module doc): the validity range of temperature and 4 x 12
    coefficients. `coef[k]` holds power k's a11..a33, bx, by, bz. Refused at construction (a
    ValueError saying what is wrong) when a value is not finite, a shape is wrong or
    t_lo_c >= t_hi_c: the board would refuse the commit, and the station must not even try."""

    t_ref_c: float
    t_lo_c: float
    t_hi_c: float
    coef: tuple[tuple[float, ...], ...]  # 4 powers x 12 (a11..a33, bx, by, bz in g)

    def __post_init__(self) -> None:
        try:
            arr = np.asarray(self.coef, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"cubic SFEM coefficients are not a 4 x 12 table of numbers: {exc}") from None
        if arr.shape != (N_POWERS, N_COEF):
            raise ValueError(f"cubic SFEM needs {N_POWERS} x {N_COEF} coefficients, got shape {arr.shape}")
        temps = (float(self.t_ref_c), float(self.t_lo_c), float(self.t_hi_c))
        if not all(math.isfinite(t) for t in temps):
            raise ValueError(f"cubic SFEM temperatures must be finite: t_ref {temps[0]!r}, t_lo {temps[1]!r}, "
                             f"t_hi {temps[2]!r}")
        if not np.isfinite(arr).all():
            k, j = (int(i) for i in np.argwhere(~np.isfinite(arr))[0])
            raise ValueError(f"cubic SFEM coefficient c[{k}][{j}] is not finite: {arr[k, j]!r}")
        if not temps[1] < temps[2]:
            raise ValueError(f"cubic SFEM range needs t_lo_c < t_hi_c, got {temps[1]!r} .. {temps[2]!r}")
        # plain floats and tuples whatever came in (numpy arrays, lists): equality and hashing work
        object.__setattr__(self, "t_ref_c", temps[0])
        object.__setattr__(self, "t_lo_c", temps[1])
        object.__setattr__(self, "t_hi_c", temps[2])
        object.__setattr__(self, "coef", tuple(tuple(float(v) for v in row) for row in arr))

    @classmethod
    def from_values(cls, values: ArrayLike) -> "SfemCubicRecord":
        """The record from its 51 values in contract (CRC) order."""
        v = np.asarray(values, dtype=np.float64).reshape(-1)
        if v.shape != (N_VALUES,):
            raise ValueError(f"a cubic SFEM record has {N_VALUES} values, got {v.shape[0]}")
        return cls(float(v[0]), float(v[1]), float(v[2]), tuple(map(tuple, v[3:].reshape(N_POWERS, N_COEF))))

    def values(self) -> tuple[float, ...]:
        """The 51 values in contract order: t_ref_c, t_lo_c, t_hi_c, c[0][0..11], ..., c[3][0..11]."""
        return (self.t_ref_c, self.t_lo_c, self.t_hi_c, *(v for row in self.coef for v in row))

    def to_f32(self) -> "SfemCubicRecord":
        """The record as the board stores it: every value rounded to float32. Raises ValueError when
        rounding makes it invalid (a value beyond float32's range, t_lo_c == t_hi_c)."""
        return SfemCubicRecord.from_values(_f32(self.values()))

    def crc32(self) -> int:
        """CRC-32 (zlib) of the 51 float32 little-endian values in contract order: what `$SFTC`
        carries and what the board answers `A,SFTC,<crc>` with when it stored the same record."""
        vals = _f32(self.values())
        return zlib.crc32(struct.pack(f"<{N_VALUES}f", *vals)) & 0xFFFFFFFF

    def matrices(self, temp_c: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """(A(T) (n, 3, 3), b(T) (n, 3) in g) at the board's temperatures, clamped to the record's
        range, with the float32 coefficients the board stores."""
        rec = self.to_f32()
        t = np.clip(np.asarray(temp_c, dtype=np.float64).reshape(-1), rec.t_lo_c, rec.t_hi_c)
        d = t - rec.t_ref_c
        powers = d[:, None] ** np.arange(N_POWERS)[None, :]  # (n, 4): 1, d, d^2, d^3
        m = powers @ np.asarray(rec.coef, dtype=np.float64)  # (n, 12)
        return m[:, :9].reshape(-1, 3, 3), m[:, 9:]

    def compensate_counts(self, raw_counts: ArrayLike, temp_c: ArrayLike, ug_per_lsb: float) -> np.ndarray:
        """What the board sends with compensation on, in float64 before its rounding to integer
        counts: out = A(T) (raw - b(T) / lsb_g), T clamped (module doc). raw_counts (n, 3), temp_c
        (n,) the board's own temperature in C, ug_per_lsb its sensitivity. The board computes in
        float32 and rounds to the nearest count, so its D frames agree with rint(this) to within a
        count. This is the board's CONTRACT stated in numpy, not a copy of the C code."""
        raw = np.asarray(raw_counts, dtype=np.float64).reshape(-1, 3)
        a, b_g = self.matrices(temp_c)
        if a.shape[0] != raw.shape[0]:
            raise ValueError(f"{raw.shape[0]} samples but {a.shape[0]} temperatures")
        lsb_g = float(ug_per_lsb) * 1e-6
        out: np.ndarray = np.einsum("nij,nj->ni", a, raw - b_g / lsb_g)
        return out
