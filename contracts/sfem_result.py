"""The SFEM result of one DUT run as it travels and is stored: one typed shape, `SfemResult`.

Why in contracts: the same record is produced by the science (station/science/sfem_record.py, for
the daemon and `station sfem --json` alike), stored by the database writer (db/event_rows.py
sfem_rows: one row per temperature step plus one for the record), read back by the repository
(GET /api/duts/{serial}, the MES feed), judged by the verdict and printed on the certificate. The
database may import nothing of the station, so the shape lives on the ground floor, and every
reader parses it here (`SfemResult.from_json`) instead of guessing key names: a dict of any other
shape raises ValueError, so a reader never judges or prints a half-understood record.

The JSON (`to_json`) is the `station sfem --json` document (docs/design.md 5.2): the reference
step's fit at the top level (A, b, scale, bias, misalignment, ..., rmse_*_mg; station/science/
sfem_model.py SfemFit.to_json) plus the record's own keys:

    shape             SFEM_RESULT_SHAPE
    t_ref_c           the temperature the headline and the verdict refer to (25 C, or the
                      profile's sfem_reference_temp_c)
    reference_step    index in steps of the step nearest t_ref_c (derived: recomputed on reading)
    steps             one fit per temperature step, coldest first (SfemFit.to_json + temperature_step)
    thermal           the polynomial thermal model (sensors2023 eq. 8; sfem_thermal.py to_json, with
                      "drift_at_t_ref" in the TDSF/TDB convention of martinez2022), null with one step
    model_check       the goodness of fit of the worst step (derived): residual ratio and words
    temperature_steps_c, n_static_intervals, skipped_steps, notes

Units are in the names; bias and b in g (station logs are in g), scale in g per raw unit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeAlias, TypedDict

from contracts.json_safe import JsonDict, finite_or_none, plain_json_dict

SFEM_RESULT_SHAPE = "sfem-record/1"

Vec3: TypeAlias = tuple[float | None, float | None, float | None]  # x, y, z; None: not a finite number


def _vec3(d: JsonDict, key: str, *, required: bool = True) -> Vec3:
    v = d.get(key)
    if isinstance(v, (list, tuple)) and len(v) == 3:
        return (finite_or_none(v[0]), finite_or_none(v[1]), finite_or_none(v[2]))
    if required:
        raise ValueError(f"SFEM step: {key!r} must be a list of 3 numbers")
    return (None, None, None)


@dataclass(frozen=True)
class SfemStepResult:
    """One temperature step's fit: the figures the verdict and the certificate read, typed, and
    the step's whole JSON (`detail`, SfemFit.to_json) for everything else."""

    temperature_step: int
    temp_c: float
    n_positions: int
    bias_g: Vec3
    bias_sigma_g: Vec3
    scale: Vec3
    scale_sigma: Vec3
    rmse_before_mg: float | None
    rmse_after_mg: float | None
    rmse_heldout_mg: float | None
    residual_ratio: float | None  # RMS |a| - 1 g residual / what the part's noise predicts
    misses_effect: bool  # the residual is far above the noise: the model misses an effect
    fit_words: str  # the goodness of fit in words
    detail: JsonDict

    @classmethod
    def from_json(cls, d: object, index: int) -> "SfemStepResult":
        if not isinstance(d, dict):
            raise ValueError("SFEM step: not an object")
        temp = finite_or_none(d.get("temp_c"))
        if temp is None:
            raise ValueError("SFEM step: no temp_c")
        raw_gof = d.get("goodness_of_fit")
        gof: JsonDict = raw_gof if isinstance(raw_gof, dict) else {}
        return cls(
            temperature_step=int(d.get("temperature_step", index)),
            temp_c=temp,
            n_positions=int(d.get("n_positions") or 0),
            bias_g=_vec3(d, "bias"),
            bias_sigma_g=_vec3(d, "bias_sigma", required=False),
            scale=_vec3(d, "scale"),
            scale_sigma=_vec3(d, "scale_sigma", required=False),
            rmse_before_mg=finite_or_none(d.get("rmse_before_mg")),
            rmse_after_mg=finite_or_none(d.get("rmse_after_mg")),
            rmse_heldout_mg=finite_or_none(d.get("rmse_heldout_mg")),
            residual_ratio=finite_or_none(gof.get("residual_ratio")),
            misses_effect=bool(gof.get("misses_effect", False)),
            fit_words=str(gof.get("words") or ""),
            detail=dict(d),
        )

    def to_json(self) -> JsonDict:
        return plain_json_dict({**self.detail, "temperature_step": self.temperature_step})


@dataclass(frozen=True)
class SfemDrift:
    """The thermal model's drift at t_ref_c in the TDSF/TDB convention of the thermal calibration
    (martinez2022 eq. 1: the raw output per g changes by TDSF per C), per axis x, y, z."""

    tdsf_ppm_per_c: Vec3
    tdsf_sigma_ppm_per_c: Vec3
    tdb_mg_per_c: Vec3
    tdb_sigma_mg_per_c: Vec3
    convention: str

    @classmethod
    def from_thermal(cls, thermal: JsonDict | None) -> "SfemDrift | None":
        d = (thermal or {}).get("drift_at_t_ref")
        if not isinstance(d, dict):
            return None
        return cls(_vec3(d, "tdsf_ppm_per_c"), _vec3(d, "tdsf_sigma_ppm_per_c", required=False),
                   _vec3(d, "tdb_mg_per_c"), _vec3(d, "tdb_sigma_mg_per_c", required=False),
                   str(d.get("convention") or ""))


class SfemModelCheck(TypedDict):
    """The goodness of fit of the worst step (SfemResult.model_check, the JSON's "model_check")."""

    worst_residual_ratio: float | None
    worst_step_temp_c: float
    misses_effect: bool
    words: str


@dataclass(frozen=True)
class SfemResult:
    """The SFEM of one run (module doc): its steps, the temperature it refers to, its thermal model."""

    steps: tuple[SfemStepResult, ...]  # coldest first
    t_ref_c: float
    thermal: JsonDict | None = None
    n_static_intervals: int = 0
    skipped_steps: tuple[JsonDict, ...] = ()
    notes: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.steps:
            raise ValueError("an SFEM result needs at least one temperature step")

    @property
    def reference_index(self) -> int:
        """The step the headline, the verdict and the certificate use: nearest t_ref_c (the
        coldest of two equally near). Derived, never stored alone, so it cannot disagree."""
        return min(range(len(self.steps)), key=lambda i: (abs(self.steps[i].temp_c - self.t_ref_c), i))

    @property
    def reference(self) -> SfemStepResult:
        return self.steps[self.reference_index]

    @property
    def worst(self) -> SfemStepResult:
        """The step whose residual is furthest above its noise (the model check's step)."""
        return max(self.steps, key=lambda s: -1.0 if s.residual_ratio is None else s.residual_ratio)

    @property
    def drift(self) -> SfemDrift | None:
        return SfemDrift.from_thermal(self.thermal)

    def model_check(self) -> SfemModelCheck:
        w = self.worst
        return {"worst_residual_ratio": w.residual_ratio, "worst_step_temp_c": w.temp_c,
                "misses_effect": any(s.misses_effect for s in self.steps),
                "words": w.fit_words if w.fit_words else "not testable"}

    def to_json(self) -> JsonDict:
        ref = self.reference
        ref_notes = ref.detail.get("notes")
        merged = list(dict.fromkeys([*(ref_notes if isinstance(ref_notes, (list, tuple)) else []), *self.notes]))
        return plain_json_dict({
            **ref.detail,
            "shape": SFEM_RESULT_SHAPE,
            "t_ref_c": self.t_ref_c,
            "reference_step": self.reference_index,
            "temperature_steps_c": [s.temp_c for s in self.steps],
            "n_static_intervals": self.n_static_intervals,
            "steps": [s.to_json() for s in self.steps],
            "thermal": self.thermal,
            "model_check": self.model_check(),
            "skipped_steps": list(self.skipped_steps),
            "record_notes": list(self.notes),
            "notes": merged,
        })

    @classmethod
    def from_json(cls, d: object) -> "SfemResult":
        """The record from its JSON (to_json, or the database's rows put back together); ValueError
        for any other shape."""
        if not isinstance(d, dict) or d.get("shape") != SFEM_RESULT_SHAPE:
            raise ValueError(f"not an SFEM result of shape {SFEM_RESULT_SHAPE!r}")
        steps = d.get("steps")
        if not isinstance(steps, list) or not steps:
            raise ValueError("SFEM result: no steps")
        t_ref = finite_or_none(d.get("t_ref_c"))
        if t_ref is None:
            raise ValueError("SFEM result: no t_ref_c")
        thermal = d.get("thermal")
        return cls(
            steps=tuple(SfemStepResult.from_json(s, i) for i, s in enumerate(steps)),
            t_ref_c=t_ref,
            thermal=thermal if isinstance(thermal, dict) else None,
            n_static_intervals=int(d.get("n_static_intervals") or 0),
            skipped_steps=tuple(s for s in (d.get("skipped_steps") or []) if isinstance(s, dict)),
            notes=tuple(str(n) for n in (d.get("record_notes") or [])),
        )

    def record_row_json(self) -> JsonDict:
        """The record without its steps (the database keeps each step in a row of its own)."""
        out = self.to_json()
        out.pop("steps")
        return out


__all__ = ["SFEM_RESULT_SHAPE", "SfemDrift", "SfemModelCheck", "SfemResult", "SfemStepResult"]
