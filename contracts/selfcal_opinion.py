"""The board's own calibrator as a second opinion (issue 42): what the station read of it, and the
comparison with the station's own TDB/TDSF, as typed records.

Why in contracts: the reading is made by the daemon (station/daemon/board_selfcal.py, from the
driver's `$SCRR` reply and `G` frames, design 3.1), compared by the science
(station/science/selfcal_compare.py) and judged by the verdict (station/decisions/checks.py
`BoardSelfCalAgrees`, the check `board_selfcal_agrees`); the shapes live on the ground floor so
none of them imports another's.

    BoardSegment        one `G` frame: a segment the board's calibrator saved (raw means, g and C)
    BoardSelfCalReading what the station read of one board at the end of the thermal steps: the
                        board's result (`R`), its segments, or why there is none; `capable` False
                        for a board whose identity has no `scal` capability (the check is then not
                        applicable, never failed)
    OpinionRow          one figure (TDB or TDSF of one axis) side by side: the board's, the
                        station's, their difference and the uncertainties it is judged with
    SelfCalOpinion      the comparison of one run (`to_json` is what the verdict reads and stores)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from contracts.json_safe import JsonDict, finite_or_none

SELFCAL_OPINION_SHAPE = "board-selfcal/1"
Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class BoardSegment:
    """One segment as the board reported it (`G,<index>,<orientation>,<t_end_us>,...`)."""

    index: int
    orientation: int
    t_end_us: int  # the board's clock (uint32, wraps every 4295 s)
    acc_g: Vec3
    temp_c: float
    n: int  # samples averaged

    def to_json(self) -> JsonDict:
        return {"index": self.index, "orientation": self.orientation, "t_end_us": self.t_end_us,
                "acc_g": list(self.acc_g), "temp_c": self.temp_c, "n": self.n}


@dataclass(frozen=True)
class BoardSelfCalReading:
    """What the station read of one board's own calibrator (module doc)."""

    capable: bool
    tdb_mg_per_c: Vec3 | None = None
    tdsf_ppm_per_c: Vec3 | None = None
    n_segments: int = 0
    clamped_axes: tuple[bool, bool, bool] = (False, False, False)
    segments: tuple[BoardSegment, ...] = ()
    error: str | None = None  # a capable board whose result could not be read: why
    note: str = ""  # a board that is not capable: why the comparison does not apply

    @property
    def has_result(self) -> bool:
        return self.capable and self.error is None and self.tdb_mg_per_c is not None \
            and self.tdsf_ppm_per_c is not None

    def to_json(self) -> JsonDict:
        return {"capable": self.capable, "tdb_mg_per_c": None if self.tdb_mg_per_c is None else list(self.tdb_mg_per_c),
                "tdsf_ppm_per_c": None if self.tdsf_ppm_per_c is None else list(self.tdsf_ppm_per_c),
                "n_segments": self.n_segments, "clamped_axes": list(self.clamped_axes),
                "segments": [s.to_json() for s in self.segments], "error": self.error, "note": self.note}


@dataclass(frozen=True)
class OpinionRow:
    """One figure side by side (module doc). u_* are 1-sigma; agrees: |difference| <= k u_combined."""

    axis: str
    figure: str  # "tdb_mg_per_c" | "tdsf_ppm_per_c"
    board: float
    station: float
    u_board: float
    u_station: float | None  # None: the station's result carries no sigma (then u_combined = u_board)
    k: float
    board_from_segments: float | None = None  # the board's figure recomputed by the station from its G frames
    clamped_board: bool = False
    clamped_station: bool = False

    @property
    def difference(self) -> float:
        return self.board - self.station

    @property
    def u_combined(self) -> float:
        return math.hypot(self.u_board, self.u_station or 0.0)

    @property
    def agrees(self) -> bool:
        return abs(self.difference) <= self.k * self.u_combined

    @property
    def unit(self) -> str:
        return "mg/C" if self.figure == "tdb_mg_per_c" else "ppm/C"

    @property
    def label(self) -> str:
        return "TDB" if self.figure == "tdb_mg_per_c" else "TDSF"

    def to_json(self) -> JsonDict:
        return {"axis": self.axis, "figure": self.figure, "unit": self.unit, "board": self.board,
                "station": self.station, "difference": self.difference, "u_board": self.u_board,
                "u_station": self.u_station, "u_combined": self.u_combined, "k": self.k, "agrees": self.agrees,
                "board_from_segments": self.board_from_segments, "clamped_board": self.clamped_board,
                "clamped_station": self.clamped_station}

    @classmethod
    def from_json(cls, d: object) -> "OpinionRow":
        if not isinstance(d, dict):
            raise ValueError("board selfcal row: not an object")
        board, station, u_b = finite_or_none(d.get("board")), finite_or_none(d.get("station")), \
            finite_or_none(d.get("u_board"))
        k = finite_or_none(d.get("k"))
        if board is None or station is None or u_b is None or k is None:
            raise ValueError("board selfcal row: board, station, u_board and k must be numbers")
        figure = str(d.get("figure"))
        if figure not in ("tdb_mg_per_c", "tdsf_ppm_per_c"):
            raise ValueError(f"board selfcal row: unknown figure {figure!r}")
        return cls(str(d.get("axis")), figure, board, station, u_b, finite_or_none(d.get("u_station")), k,
                   finite_or_none(d.get("board_from_segments")), bool(d.get("clamped_board")),
                   bool(d.get("clamped_station")))


@dataclass(frozen=True)
class SelfCalOpinion:
    """The board's calibrator against the station's result for one run (module doc).

    applicable False: the board has no calibrator (`note` says why; never a fail). error: a capable
    board whose result could not be read or compared (an error verdict, never a pass). Otherwise
    `rows` (TDB and TDSF per axis) decide: the opinion agrees when every row does."""

    applicable: bool
    rows: tuple[OpinionRow, ...] = ()
    error: str | None = None
    note: str = ""
    n_segments_board: int = 0
    n_segments_station: int = 0
    noise: JsonDict = field(default_factory=dict)  # how the board's uncertainty was obtained (figures, source)
    assumptions: str = ""

    @property
    def agrees(self) -> bool:
        return self.applicable and self.error is None and bool(self.rows) and all(r.agrees for r in self.rows)

    def to_json(self) -> JsonDict:
        return {"shape": SELFCAL_OPINION_SHAPE, "applicable": self.applicable, "error": self.error, "note": self.note,
                "agrees": self.agrees, "rows": [r.to_json() for r in self.rows],
                "n_segments_board": self.n_segments_board, "n_segments_station": self.n_segments_station,
                "noise": dict(self.noise), "assumptions": self.assumptions}

    @classmethod
    def from_json(cls, d: object) -> "SelfCalOpinion":
        if not isinstance(d, dict) or d.get("shape") != SELFCAL_OPINION_SHAPE:
            raise ValueError(f"not a board selfcal opinion of shape {SELFCAL_OPINION_SHAPE!r}")
        rows = d.get("rows")
        noise = d.get("noise")
        err = d.get("error")
        return cls(applicable=bool(d.get("applicable")),
                   rows=tuple(OpinionRow.from_json(r) for r in rows) if isinstance(rows, list) else (),
                   error=None if err is None else str(err), note=str(d.get("note") or ""),
                   n_segments_board=int(d.get("n_segments_board") or 0),
                   n_segments_station=int(d.get("n_segments_station") or 0),
                   noise=dict(noise) if isinstance(noise, dict) else {},
                   assumptions=str(d.get("assumptions") or ""))


__all__ = ["SELFCAL_OPINION_SHAPE", "BoardSegment", "BoardSelfCalReading", "OpinionRow", "SelfCalOpinion"]
