"""Records shared by drivers, science, sequencer, database and web.

Everything that crosses a folder boundary is one of these. Units are in the names:
acceleration in g, temperature in degrees C, time in seconds unless a name says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from contracts.board_health import BoardRecordInfo as BoardRecordInfo  # re-exported: Identity.record
from contracts.json_safe import JsonDict

AXES = ("x", "y", "z")
T_REF_C = 25.0  # reference temperature of the thermal model (martinez2022 eq. 1)


@dataclass(frozen=True)
class Identity:
    """A board's identity reply (design 3.1 `I,...` frame or the CAN 0x580 frames).

    The first seven fields say WHICH board this is and how to read its counts: two identities are
    equal when these are. The fields after them are what the board reports of its own health
    (docs/design.md 3.1, contracts/board_health.py), None / empty when it reports none
    (older firmware, the simulated Python boards): they change legitimately over a board's life
    (a reset moves `boots`), so they are kept out of the equality (compare=False) and a board is
    never taken for another one because it restarted. A restart within a run is its own finding
    (station/daemon/identity_check.board_restart)."""

    serial: str
    sensor: str = "LIS3DSH"
    fw: str = ""
    ug_per_lsb: float = 60.0
    t_lsb_per_c: float = 1.0
    t_lsb_at_25c: float = 0.0
    odr_hz: float = 3.125
    reset_cause: str | None = field(default=None, compare=False)  # `reset=`: power pin watchdog fault ...
    boots: int | None = field(default=None, compare=False)  # `boots=`: starts since power-up (1 after power-on)
    fault_cfsr: int | None = field(default=None, compare=False)  # `fault=`: CFSR stored by the fault handler
    fault_pc: int | None = field(default=None, compare=False)  # `fault_pc=`: stacked PC of the faulting code
    record: BoardRecordInfo | None = field(default=None, compare=False)  # `rec_*=`: the NVM record in force
    caps: frozenset[str] = field(default=frozenset(), compare=False)  # `caps=`: scal, sfem3, ...
    sensor_reinits: int | None = field(default=None, compare=False)  # `sensor_reinit=`: silent sensor re-inits

    def __post_init__(self) -> None:
        if not isinstance(self.caps, frozenset):  # a set or a list given: the record stays hashable
            object.__setattr__(self, "caps", frozenset(self.caps))
        # A NaN or zero scale would turn every sample into NaN and blind the over-temperature
        # check of this DUT: such an identity is refused where it is decoded (a malformed frame).
        for name in ("ug_per_lsb", "t_lsb_per_c", "t_lsb_at_25c", "odr_hz"):
            value = getattr(self, name)
            if not np.isfinite(value):
                raise ValueError(f"identity {name} is not a finite number: {value!r}")
        if self.ug_per_lsb <= 0 or self.odr_hz <= 0 or self.t_lsb_per_c == 0:
            raise ValueError(f"identity out of range: ug_per_lsb {self.ug_per_lsb:g} (> 0), "
                             f"t_lsb_per_c {self.t_lsb_per_c:g} (!= 0), odr_hz {self.odr_hz:g} (> 0)")

    def acc_g(self, counts: np.ndarray) -> np.ndarray:
        """Raw acceleration counts to g."""
        return np.asarray(counts, dtype=np.float64) * (self.ug_per_lsb / 1e6)

    def temp_c(self, counts: np.ndarray) -> np.ndarray:
        """Raw temperature counts to degrees C."""
        return T_REF_C + (np.asarray(counts, dtype=np.float64) - self.t_lsb_at_25c) / self.t_lsb_per_c


@dataclass
class SampleBlock:
    """A run of consecutive samples from one DUT, already in physical units.

    time_s is the board's sample time (board clock or sample index / ODR), not wall time, so a
    live stream, a compressed-time replay and a CSV give the same science.
    """

    time_s: np.ndarray  # (n,) float64
    acc_g: np.ndarray  # (n, 3) float64
    temp_c: np.ndarray  # (n,) float64
    lost_samples: int = 0  # samples the link lost before/inside this block (seq gaps)

    def __post_init__(self) -> None:
        self.time_s = np.asarray(self.time_s, dtype=np.float64).reshape(-1)
        self.acc_g = np.asarray(self.acc_g, dtype=np.float64).reshape(-1, 3)
        self.temp_c = np.asarray(self.temp_c, dtype=np.float64).reshape(-1)
        n = self.time_s.shape[0]
        if self.acc_g.shape[0] != n or self.temp_c.shape[0] != n:
            raise ValueError(
                f"SampleBlock columns differ in length: time {n}, acc {self.acc_g.shape[0]}, "
                f"temp {self.temp_c.shape[0]}"
            )

    def __len__(self) -> int:
        return int(self.time_s.shape[0])

    @staticmethod
    def concat(blocks: list["SampleBlock"]) -> "SampleBlock":
        blocks = list(blocks)  # one snapshot: a list another task appends to must not skew the columns
        if not blocks:
            return SampleBlock(np.empty(0), np.empty((0, 3)), np.empty(0))
        return SampleBlock(
            np.concatenate([b.time_s for b in blocks]),
            np.concatenate([b.acc_g for b in blocks]),
            np.concatenate([b.temp_c for b in blocks]),
            sum(b.lost_samples for b in blocks),
        )


@dataclass(frozen=True)
class Segment:
    """One averaged stable segment, as the streaming calibrator logs it (martinez2022 Table 1).

    orientation is the calibrator's own orientation counter (0, 1, ...), incremented on every
    orientation change it detects; position is the fixture/profile position index when known.
    """

    index: int
    orientation: int
    n_samples: int
    t_start_s: float
    t_end_s: float
    acc_mean_g: tuple[float, float, float]
    acc_std_g: tuple[float, float, float]
    temp_mean_c: float
    temp_std_c: float
    position: int | None = None


@dataclass(frozen=True)
class AxisThermal:
    """TDB/TDSF of one axis; uncertainties are 1-sigma, None where a method gives none."""

    tdb_mg_per_c: float
    tdsf_ppm_per_c: float
    tdb_sigma_mg_per_c: float | None = None
    tdsf_sigma_ppm_per_c: float | None = None
    tdsf_clamped: bool = False


@dataclass(frozen=True)
class OrientationDrift:
    """TD_i and Acc0_i of one orientation for one axis (martinez2022 Table 2/5)."""

    orientation: int
    td_mg_per_c: float
    acc0_g: float


@dataclass
class ThermalResult:
    """Result of one thermal calibration method for one DUT."""

    method: str  # "streaming" or "offline"
    axes: dict[str, AxisThermal]
    orientations: dict[str, list[OrientationDrift]] = field(default_factory=dict)
    n_segments: int = 0

    def to_json(self) -> JsonDict:
        axes: JsonDict = {
            name: {
                "tdb_mg_per_c": ax.tdb_mg_per_c,
                "tdsf_ppm_per_c": ax.tdsf_ppm_per_c,
                "tdb_sigma_mg_per_c": ax.tdb_sigma_mg_per_c,
                "tdsf_sigma_ppm_per_c": ax.tdsf_sigma_ppm_per_c,
                "tdsf_clamped": ax.tdsf_clamped,
            }
            for name, ax in self.axes.items()
        }
        orientations: JsonDict = {
            name: [
                {"orientation": o.orientation, "td_mg_per_c": o.td_mg_per_c, "acc0_g": o.acc0_g}
                for o in lst
            ]
            for name, lst in self.orientations.items()
        }
        return {"method": self.method, "n_segments": self.n_segments, "axes": axes, "orientations": orientations}


class StationError(Exception):
    """A user-facing error: one clear line, no traceback (CLI exits non-zero, REST gives 4xx)."""


class NotFound(KeyError):
    """What a request names does not exist (an unknown batch, run, profile, export format): REST
    answers 404 with the message. It is a KeyError for the callers that already catch one; a plain
    KeyError anywhere else is a bug, and REST answers 500 for it, never "not found"."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else "not found"


class StorageUnavailable(StationError):
    """The station's database cannot be used now (not answering, its file deleted): what needs it
    (a new batch: its runs are numbered there) is refused; REST answers 503 with the reason."""
