"""The records one DUT run produces, typed, as they travel from the science to the database and the page.

Why here: the daemon makes them (station/daemon/results.py, program_verify.py), the events carry
them (contracts/events.py DutResult, DutProgrammed), the database writer stores them and the
journal keeps them while the database is away (db/), the verdict reads them (station/decisions).
The database may import nothing of the station, so the shapes live on the ground floor, like
`SfemResult` (contracts/sfem_result.py), which this module's records follow: the figures a reader
reads are typed fields; the whole document is kept as JSON (`detail`) for what is only stored and
shown; `to_json` and `from_json` are the one codec each way, used at the database and HTTP edges
and by the journal. A dict of any other shape is a ValueError at the edge, never a half-read record.

    ThermalReport   one DUT's thermal calibration: `station calibrate --json`'s document
                    (station/science/thermal_calibration.py calibrate): the reported TDB/TDSF per
                    axis with their 1-sigma (the offline fit's, `axes_method`), the streaming and
                    offline method results, residual drift and uncertainty budget, and the live
                    calibrator's own result (`streaming_live`)
    ProgramRecord   program and verify, part 1 (design 4): what was written to a board, read back
                    and switched on, or why not (`error_kind`: no_result, identity, link, or the
                    driver's CalibrationError kind: refused, crc, readback, no_reply...)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from contracts.json_safe import JsonDict, finite_or_none, plain_json_dict
from contracts.types import AXES, AxisThermal

THERMAL_METHODS = ("streaming", "offline")


def _axis(d: object, where: str) -> AxisThermal:
    if not isinstance(d, dict):
        raise ValueError(f"thermal result: {where} is not an object")
    try:
        tdb, tdsf = float(d["tdb_mg_per_c"]), float(d["tdsf_ppm_per_c"])
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"thermal result: {where} has no numeric tdb_mg_per_c/tdsf_ppm_per_c") from None

    return AxisThermal(tdb, tdsf, finite_or_none(d.get("tdb_sigma_mg_per_c")),
                       finite_or_none(d.get("tdsf_sigma_ppm_per_c")), bool(d.get("tdsf_clamped", False)))


@dataclass(frozen=True)
class MethodResult:
    """One method's TDB/TDSF per axis (contracts.types.ThermalResult.to_json, read back)."""

    method: str
    axes: dict[str, AxisThermal]
    n_segments: int
    detail: JsonDict

    @classmethod
    def from_json(cls, d: object, default_method: str) -> "MethodResult":
        if not isinstance(d, dict) or not isinstance(d.get("axes"), dict):
            raise ValueError(f"thermal result: {default_method} has no axes")
        axes = {a: _axis(d["axes"].get(a), f"{default_method} axis {a}") for a in AXES}
        n = d.get("n_segments")
        return cls(str(d.get("method") or default_method), axes, int(n) if isinstance(n, int) else 0,
                   plain_json_dict(d))


@dataclass(frozen=True)
class ThermalReport:
    """One DUT's thermal calibration (module doc). `axes` is what the station reports and programs."""

    serial: str
    axes_method: str
    axes: dict[str, AxisThermal]
    methods: dict[str, MethodResult]  # "streaming", "offline": each method's own result
    detail: JsonDict = field(repr=False)  # the whole document, as stored and shown

    def coefficients(self) -> tuple[list[float], list[float]] | None:
        """(tdb_mg_per_c[3], tdsf_ppm_per_c[3]) to write into the board, None unless all are finite."""
        tdb = [self.axes[a].tdb_mg_per_c for a in AXES]
        tdsf = [self.axes[a].tdsf_ppm_per_c for a in AXES]
        return (tdb, tdsf) if all(math.isfinite(v) for v in tdb + tdsf) else None

    @property
    def uncertainty(self) -> JsonDict | None:
        """The budget behind the offline sigmas (its bias wander: the verification reuses it)."""
        u = self.detail.get("uncertainty")
        return u if isinstance(u, dict) else None

    def to_json(self) -> JsonDict:
        return dict(self.detail)

    @classmethod
    def from_json(cls, d: object) -> "ThermalReport":
        """The report from `station calibrate --json`'s document (or the database's copy of it).
        It must hold at least one method's result; `axes` (the reported coefficients) default to
        the offline fit's, else the streaming method's."""
        if not isinstance(d, dict):
            raise ValueError("thermal result: not an object")
        methods = {k: MethodResult.from_json(d[k], k) for k in THERMAL_METHODS if isinstance(d.get(k), dict)
                   and isinstance(d[k].get("axes"), dict)}
        if not methods and isinstance(d.get("axes"), dict):
            lone = MethodResult.from_json(d, "streaming")  # one method's result alone (ThermalResult.to_json)
            methods = {lone.method: lone}
        if isinstance(d.get("axes"), dict):
            axes = {a: _axis(d["axes"].get(a), f"axis {a}") for a in AXES}
        elif methods:
            axes = (methods.get("offline") or methods["streaming"]).axes
        else:
            raise ValueError("thermal result: neither axes nor a streaming/offline result")
        if not methods:
            raise ValueError("thermal result: no streaming or offline method result")
        return cls(serial=str(d.get("serial") or ""), axes_method=str(d.get("axes_method") or ""), axes=axes,
                   methods=methods, detail=plain_json_dict(d))


@dataclass(frozen=True)
class ProgramRecord:
    """Program and verify, part 1, of one DUT (module doc)."""

    programmed: bool
    tdb_mg_per_c: tuple[float, ...] = ()
    tdsf_ppm_per_c: tuple[float, ...] = ()
    method: str = ""
    error_kind: str | None = None
    error: str | None = None
    attempts: int | None = None
    comp: bool | None = None
    # the board's answer (drivers.base.ProgramReport.to_json): CRCs, values read back, retries, and
    # comp_from_t, the board time from which every sample is compensated
    readback: JsonDict = field(default_factory=dict)

    @property
    def comp_from_t(self) -> float | None:
        return finite_or_none(self.readback.get("comp_from_t"))

    def to_json(self) -> JsonDict:
        out: JsonDict = {"programmed": self.programmed}
        if self.tdb_mg_per_c or self.tdsf_ppm_per_c:
            out.update(tdb_mg_per_c=list(self.tdb_mg_per_c), tdsf_ppm_per_c=list(self.tdsf_ppm_per_c),
                       method=self.method)
        for key in ("error_kind", "error", "attempts", "comp"):
            v = getattr(self, key)
            if v is not None:
                out[key] = v
        out.update(self.readback)
        return plain_json_dict(out)

    @classmethod
    def from_json(cls, d: object) -> "ProgramRecord":
        if not isinstance(d, dict) or not isinstance(d.get("programmed"), bool):
            raise ValueError("program record: no 'programmed' flag")
        own = {"programmed", "tdb_mg_per_c", "tdsf_ppm_per_c", "method", "error_kind", "error", "attempts", "comp"}

        def floats(key: str) -> tuple[float, ...]:
            v = d.get(key)
            return tuple(float(x) for x in v) if isinstance(v, list) else ()

        attempts, comp = d.get("attempts"), d.get("comp")
        return cls(programmed=d["programmed"], tdb_mg_per_c=floats("tdb_mg_per_c"),
                   tdsf_ppm_per_c=floats("tdsf_ppm_per_c"), method=str(d.get("method") or ""),
                   error_kind=None if d.get("error_kind") is None else str(d["error_kind"]),
                   error=None if d.get("error") is None else str(d["error"]),
                   attempts=attempts if isinstance(attempts, int) else None,
                   comp=comp if isinstance(comp, bool) else None,
                   readback={k: v for k, v in d.items() if k not in own})


__all__ = ["ThermalReport", "MethodResult", "ProgramRecord", "THERMAL_METHODS"]
