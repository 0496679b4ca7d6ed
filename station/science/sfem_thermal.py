"""Temperature dependence of the SFEM: each parameter as a polynomial of temperature.

Why a module of its own: a thermal model is built from several finished fits (one per temperature
step) and then used without any of them, to give the parameters (and compensate samples) at any
temperature in its range. It needs the model's algebra, not the optimiser.

Thermal model (sensors2023 eq. 8): each of the 12 parameters as a polynomial (cubic when there are
>= 4 temperature steps, lower otherwise) of (T - t_ref_c).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from station.science.sfem_model import SfemFit, SfemInsufficientData, compose_a
from contracts.types import T_REF_C


# ---------------------------------------------------------------------------------------------
# thermal model (sensors2023 eq. 8)


@dataclass
class SfemParams:
    """SFEM parameters at one or more temperatures (leading dims broadcast)."""

    rotvec_rad: np.ndarray  # (..., 3)
    alpha: np.ndarray  # (..., 3)
    scale: np.ndarray  # (..., 3)
    b: np.ndarray  # (..., 3)

    @property
    def A(self) -> np.ndarray:
        return compose_a(self.rotvec_rad, self.alpha, self.scale)


@dataclass
class SfemThermalModel:
    """Each SFEM parameter as a polynomial of (T - t_ref_c), one temperature step per fit.

    coef[name] has shape (degree + 1, 3), lowest power first, for name in rotvec_rad, alpha, scale, b.
    """

    degree: int
    coef: dict[str, np.ndarray]
    temps_c: np.ndarray
    misalignment_determined: bool
    t_ref_c: float = T_REF_C
    residual_rms: dict[str, np.ndarray] = field(default_factory=dict)  # polynomial misfit at the steps
    notes: list[str] = field(default_factory=list)

    NAMES = ("rotvec_rad", "alpha", "scale", "b")

    @classmethod
    def fit(
        cls, steps: list[tuple[float, SfemFit]], max_degree: int = 3, t_ref_c: float = T_REF_C
    ) -> "SfemThermalModel":
        """Least-squares polynomial per parameter; degree = min(max_degree, n_steps - 1)."""
        if not steps:
            raise SfemInsufficientData("no temperature steps to fit a thermal model")
        steps = sorted(steps, key=lambda s: s[0])
        temps = np.array([float(t) for t, _ in steps])
        if len(np.unique(np.round(temps, 6))) < len(temps):
            raise SfemInsufficientData("two SFEM fits at the same temperature")
        degree = min(max_degree, len(steps) - 1)
        notes = []
        if degree < max_degree:
            notes.append(
                f"{len(steps)} temperature step(s): polynomial degree {degree} instead of {max_degree} "
                f"(a degree-{max_degree} polynomial needs at least {max_degree + 1} steps)"
            )
        determined = all(f.misalignment_determined for _, f in steps)
        if not determined:
            notes.append("misalignment not determined in every step (norm-only): kept at identity")
        values = {
            "rotvec_rad": np.array([f.misalignment_rotvec_rad if determined else np.zeros(3) for _, f in steps]),
            "alpha": np.array([f.nonorthogonality for _, f in steps]),
            "scale": np.array([f.scale for _, f in steps]),
            "b": np.array([f.b for _, f in steps]),
        }
        x = temps - t_ref_c
        coef, resid = {}, {}
        for name, vals in values.items():
            c = np.polynomial.polynomial.polyfit(x, vals, degree)  # (degree+1, 3)
            coef[name] = c
            resid[name] = np.sqrt(np.mean((np.polynomial.polynomial.polyval(x, c).T - vals) ** 2, axis=0))
        return cls(degree, coef, temps, determined, t_ref_c, resid, notes)

    @property
    def temp_range_c(self) -> tuple[float, float]:
        return float(self.temps_c.min()), float(self.temps_c.max())

    def params_at(self, temp_c: float | np.ndarray) -> SfemParams:
        x = np.asarray(temp_c, dtype=np.float64) - self.t_ref_c
        vals = {k: np.moveaxis(np.polynomial.polynomial.polyval(x, c), 0, -1) for k, c in self.coef.items()}
        return SfemParams(vals["rotvec_rad"], vals["alpha"], vals["scale"], vals["b"])

    def compensate(self, acc: np.ndarray, temp_c: float | np.ndarray) -> np.ndarray:
        """Calibrated acceleration in g: A(T) (u - b(T)) per sample, T from temp_c (scalar or (n,))."""
        u = np.asarray(acc, dtype=np.float64).reshape(-1, 3)
        t = np.broadcast_to(np.asarray(temp_c, dtype=np.float64), (u.shape[0],))
        p = self.params_at(t)
        return np.einsum("nij,nj->ni", p.A, u - p.b)

    def to_json(self) -> dict:
        return {
            "degree": self.degree,
            "t_ref_c": self.t_ref_c,
            "temps_c": self.temps_c.tolist(),
            "misalignment_determined": self.misalignment_determined,
            "coef": {k: v.tolist() for k, v in self.coef.items()},
            "coef_layout": "coef[name][power][axis], polynomial of (temp_c - t_ref_c), lowest power first",
            "residual_rms": {k: v.tolist() for k, v in self.residual_rms.items()},
            "notes": list(self.notes),
        }


__all__ = [
    "SfemParams",
    "SfemThermalModel",
]
