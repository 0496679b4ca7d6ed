"""Frames of the board's own streaming calibrator (design 3.1, on-board self-calibration).

A board that runs martinez2022 section 3.3 itself (firmware/core/fw_selfcal.c) reports what it
logs, so a line (or a field unit) can compare it with the station's calibrator:
  `$SCAL,<0|1>`  station -> board: on-board calibrator off / on (on restarts it); reply `A,SCAL`
  `G,<index>,<orientation>,<t_end_us>,<ax_g>,<ay_g>,<az_g>,<temp_c>,<n>`  board -> station, as
                 a segment is saved (raw means of its averaged samples)
  `$SCRR`        station -> board: read the result; reply
  `R,<tdb_x>,<tdb_y>,<tdb_z>,<tdsf_x>,<tdsf_y>,<tdsf_z>,<n_segments>,<flags>` (mg/C, ppm/C; flags
                 bit k: TDSF of axis k was positive and clamped to 0), or `E,SCRR,<text>`.
The existing frames are unchanged; a station that does not know these counts them as unknown.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class SegmentReportFrame:
    index: int
    orientation: int
    t_end_us: int
    acc_g: tuple[float, float, float]
    temp_c: float
    n: int


@dataclass(frozen=True, slots=True)
class SelfCalResultFrame:
    tdb_mg_per_c: tuple[float, float, float]
    tdsf_ppm_per_c: tuple[float, float, float]
    n_segments: int
    flags: int


def _floats(fields: list[str]) -> tuple[float, ...]:
    vals = tuple(float(f) for f in fields)
    if not all(math.isfinite(v) for v in vals):
        raise ValueError("non-finite value")
    return vals


def decode(fields: list[str]) -> SegmentReportFrame | SelfCalResultFrame | None:
    """A `G` or `R` frame from its fields; None when malformed. Raises ValueError on bad numbers."""
    if fields[0] == "G" and len(fields) == 9:
        index, orientation, t_end_us, n = int(fields[1]), int(fields[2]), int(fields[3]), int(fields[8])
        ax, ay, az, temp_c = _floats(fields[4:8])
        if min(index, orientation, t_end_us, n) < 0:
            return None
        return SegmentReportFrame(index, orientation, t_end_us, (ax, ay, az), temp_c, n)
    if fields[0] == "R" and len(fields) == 9:
        v = _floats(fields[1:7])
        n_seg, flags = int(fields[7]), int(fields[8])
        if n_seg < 0 or flags < 0:
            return None
        return SelfCalResultFrame((v[0], v[1], v[2]), (v[3], v[4], v[5]), n_seg, flags)
    return None
