"""Frames of the version-2 record, the cubic thermal SFEM (docs/design.md 3.1, issue 42).

  `$SFTW,<k>,<c_k_a11>,...,<c_k_a33>,<c_k_bx>,<c_k_by>,<c_k_bz>*HH`  stage power k (0..3); `A,SFTW,<k>`
  `$SFTC,<t_ref_c>,<t_lo_c>,<t_hi_c>,<crc>*HH`  commit; `A,SFTC,<crc>` or `E,SFTC,<text>`
  `$SFTR,H*HH` -> `T,H,<t_ref_c>,<t_lo_c>,<t_hi_c>,<crc>`;  `$SFTR,<k>*HH` -> `T,<k>,<12 values>`;
                  `E,SFTR,no cubic SFEM stored` when none.
The record itself (validation, float32, CRC, what the board computes) is contracts/sfem_cubic.py.
Numbers go out as the shortest text that parses back to the same float32 (fmt_f32_short: a
coefficient of d^3 is tiny, and the board's line is short); they come back in whatever decimal
the board writes.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from contracts.sfem_cubic import N_COEF, N_POWERS, SfemCubicRecord
from drivers.protocol.cal_record import to_f32
from drivers.protocol.frame_text import encode, fmt_crc, fmt_f32, fmt_f32_short, parse_crc, parse_finite_f32


def _sftw_body(power: int, coef12: Iterable[float]) -> str:
    if not 0 <= int(power) < N_POWERS:
        raise ValueError(f"SFTW power must be 0..{N_POWERS - 1}, got {power}")
    vals = to_f32(coef12)
    if len(vals) != N_COEF or not all(np.isfinite(vals)):
        raise ValueError(f"SFTW needs {N_COEF} finite float32 values, got {list(vals)}")
    return ",".join(("SFTW", str(int(power)), *(fmt_f32_short(v) for v in vals)))


def cmd_sftw(power: int, coef12: Iterable[float]) -> bytes:
    """`$SFTW,<k>,<c_k_a11>,...,<c_k_a33>,<c_k_bx>,<c_k_by>,<c_k_bz>*HH`: stage power k's 12 coefficients."""
    return encode(_sftw_body(power, coef12))


def cmd_sftc(rec: SfemCubicRecord) -> bytes:
    """`$SFTC,<t_ref_c>,<t_lo_c>,<t_hi_c>,<crc>*HH`: commit the four staged powers (CRC of all 51 values)."""
    r = rec.to_f32()
    return encode(",".join(("SFTC", *(fmt_f32_short(v) for v in (r.t_ref_c, r.t_lo_c, r.t_hi_c)), fmt_crc(r.crc32()))))


def cmd_sftr(part: str | int) -> bytes:
    """`$SFTR,H*HH` (the header) or `$SFTR,<k>*HH` (power k's row)."""
    if part != "H" and not (isinstance(part, int) and 0 <= part < N_POWERS):
        raise ValueError(f"SFTR reads H or a power 0..{N_POWERS - 1}, not {part!r}")
    return encode(f"SFTR,{part}")


def sfem_cubic_commands(rec: SfemCubicRecord) -> list[bytes]:
    """The whole write of a record, in order: four SFTW (powers 0..3) then SFTC."""
    r = rec.to_f32()
    return [cmd_sftw(k, r.coef[k]) for k in range(N_POWERS)] + [cmd_sftc(r)]


@dataclass(frozen=True, slots=True)
class SfemCubicHeadFrame:
    """`T,H,<t_ref_c>,<t_lo_c>,<t_hi_c>,<crc>`: the stored cubic SFEM's range and CRC (reply to SFTR,H)."""

    t_ref_c: float
    t_lo_c: float
    t_hi_c: float
    crc: int

    def encode(self) -> bytes:
        return encode(",".join(("T", "H", *(fmt_f32(v) for v in (self.t_ref_c, self.t_lo_c, self.t_hi_c)),
                                fmt_crc(self.crc))))


@dataclass(frozen=True, slots=True)
class SfemCubicRowFrame:
    """`T,<k>,<12 values>`: the stored cubic SFEM's power k (reply to SFTR,k)."""

    power: int
    values: tuple[float, ...]  # 12: a11..a33, bx, by, bz (g), as float32

    def encode(self) -> bytes:
        return encode(",".join(("T", str(self.power), *(fmt_f32(v) for v in self.values))))


def decode(fields: list[str]) -> SfemCubicHeadFrame | SfemCubicRowFrame | None:
    """A `T` frame from its fields; None when malformed. Raises ValueError on bad numbers."""
    if len(fields) == 6 and fields[1] == "H":
        t_ref, t_lo, t_hi = parse_finite_f32(fields[2:5])
        return SfemCubicHeadFrame(t_ref, t_lo, t_hi, parse_crc(fields[5]))
    if len(fields) == 2 + N_COEF and fields[1] in tuple(str(k) for k in range(N_POWERS)):
        return SfemCubicRowFrame(int(fields[1]), parse_finite_f32(fields[2:]))
    return None


def board_command_args(fields: list[str]) -> tuple[str, ...] | None:
    """The board side: the arguments of an SFTW / SFTC / SFTR command as text, None if malformed.
    A non-finite number is the board's to refuse (`E,SFTC`), so it passes; a field that is no
    number does not. Raises ValueError on a field that is no number."""
    kind = fields[0]
    if kind == "SFTW" and len(fields) == 2 + N_COEF and fields[1].isdigit():
        [float(f) for f in fields[2:]]
        return tuple(fields[1:])
    if kind == "SFTC" and len(fields) == 5:
        [float(f) for f in fields[1:4]]
        parse_crc(fields[4])
        return tuple(fields[1:])
    if kind == "SFTR" and len(fields) == 2 and (fields[1] == "H" or fields[1].isdigit()):
        return (fields[1],)
    return None
