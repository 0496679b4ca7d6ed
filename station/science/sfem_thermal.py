"""Temperature dependence of the SFEM: each parameter as a polynomial of temperature.

Why a module of its own: a thermal model is built from several finished fits (one per temperature
step) and then used without any of them, to give the parameters (and compensate samples) at any
temperature in its range. It needs the model's algebra, not the optimiser.

Thermal model (sensors2023 eq. 8): each of the 12 parameters as a polynomial (cubic when there are
>= 4 temperature steps, lower otherwise) of (T - t_ref_c).

Sign convention of the drift (`drift_at_t_ref`): the SFEM's scale S maps raw readings to g, so a
sensor whose output per g falls as it warms has a RISING S. The thermal calibration (martinez2022
eq. 1, Acc = Acc0 (1 + TDSF dT) + TDB dT) states the drift of the output instead, so a true TDSF of
-225 ppm/C shows as dS/dT = +225 ppm/C of S. The station prints and stores the drift in the thermal
calibration's convention, TDSF = -(dS/dT) / S and TDB = db/dT - TDSF b (the bias b moves with the
scale too: b(T) = b (1 + TDSF dT) + TDB dT), so the SFEM's figures compare with `station
calibrate`'s directly; the raw slopes are kept beside them under their own names.
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
    coef_sigma: dict[str, np.ndarray] = field(default_factory=dict)  # 1-sigma of coef from the steps' sigmas
    acc_g_per_raw: float = 1.0  # g per raw unit of the readings (b is in raw units): TDB in mg/C needs it

    NAMES = ("rotvec_rad", "alpha", "scale", "b")

    @classmethod
    def fit(
        cls, steps: list[tuple[float, SfemFit]], max_degree: int = 3, t_ref_c: float = T_REF_C,
        acc_g_per_raw: float = 1.0,
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
        sigmas = {
            "rotvec_rad": np.array([f.sigma["rotvec_rad"] if determined else np.zeros(3) for _, f in steps]),
            "alpha": np.array([f.sigma["alpha"] for _, f in steps]),
            "scale": np.array([f.sigma["scale"] for _, f in steps]),
            "b": np.array([f.sigma["b"] for _, f in steps]),
        }
        x = temps - t_ref_c
        # the least-squares polynomial is linear in the step values: coef = L @ values, so each
        # coefficient's variance is sum_j L_ij^2 sigma_j^2 (the steps are independent fits)
        lmap = np.linalg.pinv(np.polynomial.polynomial.polyvander(x, degree))  # (degree+1, n_steps)
        coef, resid, coef_sigma = {}, {}, {}
        for name, vals in values.items():
            c = np.polynomial.polynomial.polyfit(x, vals, degree)  # (degree+1, 3)
            coef[name] = c
            resid[name] = np.sqrt(np.mean((np.polynomial.polynomial.polyval(x, c).T - vals) ** 2, axis=0))
            coef_sigma[name] = np.sqrt((lmap**2) @ np.nan_to_num(sigmas[name]) ** 2)
        return cls(degree, coef, temps, determined, t_ref_c, resid, notes, coef_sigma, acc_g_per_raw)

    def drift_at_t_ref(self) -> dict | None:
        """The drift at t_ref_c per axis in the thermal calibration's convention (module doc):
        TDSF ppm/C, TDB mg/C, with their 1-sigma from the steps' sigmas, and the raw slopes of S
        and b under their own names; None without a slope (one step)."""
        if self.degree < 1:
            return None
        s0, ds = self.coef["scale"][0], self.coef["scale"][1]
        acc_g_per_raw = self.acc_g_per_raw
        b0_g, db_g = self.coef["b"][0] * acc_g_per_raw, self.coef["b"][1] * acc_g_per_raw
        tdsf = -ds / s0  # 1/C
        sig = self.coef_sigma or {}
        sds = sig.get("scale", np.full((2, 3), np.nan))[1]
        sdb = sig.get("b", np.full((2, 3), np.nan))[1] * acc_g_per_raw
        tdsf_sigma = sds / np.abs(s0)
        tdb = db_g - tdsf * b0_g
        tdb_sigma = np.sqrt(sdb**2 + (b0_g * tdsf_sigma) ** 2)
        return {
            "convention": "martinez2022 eq. 1: Acc = Acc0 (1 + TDSF dT) + TDB dT, the drift of the raw output; "
                          "TDSF = -(dS/dT)/S, TDB = db/dT - TDSF b",
            "sigma_covers": "the steps' fit noise only: not the part's bias wander over the hours between steps "
                            "nor the error of the board's temperature reading",
            "t_ref_c": self.t_ref_c,
            "tdsf_ppm_per_c": (tdsf * 1e6).tolist(),
            "tdsf_sigma_ppm_per_c": (tdsf_sigma * 1e6).tolist(),
            "tdb_mg_per_c": (tdb * 1e3).tolist(),
            "tdb_sigma_mg_per_c": (tdb_sigma * 1e3).tolist(),
            "dscale_dT_ppm_of_scale_per_c": (ds / s0 * 1e6).tolist(),
            "db_dT_mg_per_c": (db_g * 1e3).tolist(),
        }

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
            "coef_sigma": {k: v.tolist() for k, v in self.coef_sigma.items()},
            "residual_rms": {k: v.tolist() for k, v in self.residual_rms.items()},
            "drift_at_t_ref": self.drift_at_t_ref(),
            "notes": list(self.notes),
        }


__all__ = [
    "SfemParams",
    "SfemThermalModel",
]
