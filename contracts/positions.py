"""Named fixture positions: the nominal gravity direction in the DUT frame, as a unit vector.

The position index is what the fixture's holding register 0 holds (design 3.3) and what the log's
`position` column records. Profiles name positions; the simulator turns the nominal direction
into the sensor frame through each DUT's own mounting misalignment.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

_S = 1.0 / math.sqrt(3.0)  # 0.577 g on every axis (martinez2022 eq. 5)


def _ring(axis: int) -> list[tuple[float, float, float]]:
    """Eight directions 45 deg apart in the plane perpendicular to `axis` (sensors2023 Table 1)."""
    out: list[tuple[float, float, float]] = []
    a, b = [k for k in range(3) if k != axis]
    for step in range(8):
        ang = math.radians(45.0 * step)
        v = [0.0, 0.0, 0.0]
        v[a], v[b] = math.cos(ang), math.sin(ang)
        out.append((round(v[0], 12), round(v[1], 12), round(v[2], 12)))
    return out


# Index -> (name, direction). Indices are stable: the fixture and stored logs refer to them.
_TABLE: list[tuple[str, tuple[float, float, float]]] = [
    ("P", (_S, _S, _S)),  # 0: fast-thermal positive orientation
    ("N", (-_S, -_S, -_S)),  # 1: plate turned over
    ("+x", (1.0, 0.0, 0.0)),  # 2..7: six-position reference test
    ("-x", (-1.0, 0.0, 0.0)),
    ("+y", (0.0, 1.0, 0.0)),
    ("-y", (0.0, -1.0, 0.0)),
    ("+z", (0.0, 0.0, 1.0)),
    ("-z", (0.0, 0.0, -1.0)),
]
for _axis, _label in ((2, "z"), (1, "y"), (0, "x")):
    for _k, _v in enumerate(_ring(_axis)):
        _TABLE.append((f"sfem-{_label}{_k * 45}", _v))  # 8..31: sfem-24 positions

POSITION_NAMES: list[str] = [name for name, _ in _TABLE]
POSITION_INDEX: dict[str, int] = {name: i for i, name in enumerate(POSITION_NAMES)}
GRAVITY_DIRECTIONS: npt.NDArray[np.float64] = np.array([v for _, v in _TABLE], dtype=np.float64)
SFEM24 = [f"sfem-{label}{k * 45}" for label in ("z", "y", "x") for k in range(8)]
SIX_POSITION = ["+x", "-x", "+y", "-y", "+z", "-z"]


def direction(position: int | str) -> npt.NDArray[np.float64]:
    """Nominal gravity direction (unit vector, DUT frame) of a position index or name."""
    idx = POSITION_INDEX[position] if isinstance(position, str) else int(position)
    if not 0 <= idx < len(POSITION_NAMES):
        raise KeyError(f"unknown position {position!r}")
    return GRAVITY_DIRECTIONS[idx, :].copy()


FACING_MAX_ANGLE_DEG = 20.0  # under half the 45 deg between neighbouring sfem-24 positions


def first_facing(acc_g: np.ndarray, position: int | str, max_angle_deg: float = FACING_MAX_ANGLE_DEG) -> int | None:
    """Index of the first sample whose measured gravity points within max_angle_deg of the
    position's nominal direction, or None. A static step's settle and dwell start there: samples
    that still show the previous position (a reader behind the plant in compressed time, a slow
    fixture, a DUT that is not seated) never count as the new one. Mounting misalignment and scale
    errors are a few degrees, well inside the tolerance."""
    acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    if acc.shape[0] == 0:
        return None
    norm = np.linalg.norm(acc, axis=1)
    cos = (acc @ direction(position)) / np.where(norm > 0, norm, np.inf)
    hit = np.flatnonzero(cos >= math.cos(math.radians(max_angle_deg)))
    return int(hit[0]) if hit.size else None
