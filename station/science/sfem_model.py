"""The sensor frame error model (sensors2023 eq. 1), U_SF = M C S (U - b), and one fitted instance of it.

Why a module of its own: the algebra of A = M C S and the fitted result `SfemFit` (apply, JSON)
are what every SFEM module and every caller share (the thermal polynomials, the record pipeline,
the `station sfem` command, the daemon), while the optimiser that produces a fit
(station.science.sfem) is needed only where a fit is made. Keeping the model apart lets them
read, apply and report a fit without depending on how it was made.

    M  misalignment, a rotation (3 parameters, rotation vector)
    C  non-orthogonality, lower triangular with unit diagonal (alpha_yx, alpha_zx, alpha_zy)
    S  scale, diagonal (g per raw unit)
    b  bias, raw units
    A = M C S maps raw readings, after bias removal, to g.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from contracts.types import StationError

PARAM_NAMES = (
    "rot_x", "rot_y", "rot_z", "alpha_yx", "alpha_zx", "alpha_zy",
    "scale_x", "scale_y", "scale_z", "b_x", "b_y", "b_z",
)  # fmt: skip
MISALIGNMENT_NOTE = (
    "misalignment not determined: the gravity norm is rotation-invariant, so M is not observable "
    "without reference directions; M reported as identity"
)


class SfemInsufficientData(StationError):
    """Too few (or too poorly spread) static positions for the requested fit."""


# ---------------------------------------------------------------------------------------------
# model algebra


def c_matrix(alpha: np.ndarray) -> np.ndarray:
    """Non-orthogonality matrix C from (alpha_yx, alpha_zx, alpha_zy); broadcasts over (..., 3)."""
    alpha = np.asarray(alpha, dtype=np.float64)
    c = np.zeros(alpha.shape[:-1] + (3, 3))
    c[..., 0, 0] = c[..., 1, 1] = c[..., 2, 2] = 1.0
    c[..., 1, 0] = alpha[..., 0]
    c[..., 2, 0] = alpha[..., 1]
    c[..., 2, 1] = alpha[..., 2]
    return c


def compose_a(rotvec_rad: np.ndarray, alpha: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """A = M C S; broadcasts over leading dimensions of (..., 3) inputs."""
    rotvec_rad = np.asarray(rotvec_rad, dtype=np.float64)
    m = Rotation.from_rotvec(rotvec_rad.reshape(-1, 3)).as_matrix().reshape(rotvec_rad.shape[:-1] + (3, 3))
    cs = c_matrix(alpha) * np.asarray(scale, dtype=np.float64)[..., None, :]
    return m @ cs


def decompose_a(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A -> (rotvec_rad, alpha, scale) with A = M C S (an orthogonal-times-lower-triangular split).

    QR of A with reversed columns: A J = Q R  =>  A = (Q J)(J R J), J R J lower triangular.
    """
    a = np.asarray(a, dtype=np.float64)
    j = np.eye(3)[::-1]
    q, r = np.linalg.qr(a @ j)
    m = q @ j
    low = j @ r @ j
    d = np.sign(np.diag(low))
    d[d == 0] = 1.0
    low = d[:, None] * low
    m = m * d[None, :]
    if np.linalg.det(m) < 0:
        raise SfemInsufficientData("fitted A has a negative determinant (left-handed axes): check the data")
    scale = np.diag(low).copy()
    alpha = np.array([low[1, 0] / scale[0], low[2, 0] / scale[0], low[2, 1] / scale[1]])
    return Rotation.from_matrix(m).as_rotvec(), alpha, scale


# ---------------------------------------------------------------------------------------------
# results


@dataclass(frozen=True)
class SfemGoodness:
    """How the residual of a fit compares with what the part's noise predicts (computed by
    station/science/sfem_goodness.py; a plain record here so a fit carries it without depending
    on how it was judged).

    residual_ratio: RMS of the |a| - 1 g residuals in units of each position's noise sigma, over
    the residual's degrees of freedom (1 when the model is complete and the noise is white); None
    when the positions leave too few degrees of freedom to tell (`dof`)."""

    residual_ratio: float | None
    dof: int
    mark_ratio: float  # the ratio above which the fit is marked (sfem_goodness.GOF_MARK_RATIO)
    misses_effect: bool
    words: str
    effect: str | None = None  # the named effect that explains the residual, when one does
    effect_mg: tuple[float, ...] | None = None  # its size per axis (x, y, z), mg/g^n
    ratio_with_effect: float | None = None  # the residual ratio once the named effect is allowed for

    def to_json(self) -> dict:
        return {"residual_ratio": self.residual_ratio, "dof": self.dof, "mark_ratio": self.mark_ratio,
                "misses_effect": self.misses_effect, "words": self.words, "effect": self.effect,
                "effect_mg": None if self.effect_mg is None else list(self.effect_mg),
                "ratio_with_effect": self.ratio_with_effect}


@dataclass
class SfemFit:
    """One SFEM fit. Raw units are whatever the readings were in (g for station logs)."""

    A: np.ndarray  # (3,3) raw -> g after bias removal, = M C S
    b: np.ndarray  # (3,) raw units
    misalignment_rotvec_rad: np.ndarray  # (3,) zeros when not determined
    nonorthogonality: np.ndarray  # (3,) alpha_yx, alpha_zx, alpha_zy (rad, small-angle)
    scale: np.ndarray  # (3,) g per raw unit
    misalignment_determined: bool
    method: str  # "reference" or "norm-only"
    n_positions: int
    rmse_before_mg: float
    rmse_after_mg: float
    rmse_direction_mg: float | None  # RMS |A(u-b) - r| over positions (reference fits)
    residual_norm_mg: np.ndarray  # (m,) |A(u_i - b)| - 1 g
    residual_direction_deg: np.ndarray | None  # (m,) angle between A(u_i - b) and r_i
    sigma: dict[str, np.ndarray]  # 1-sigma of rotvec_rad/alpha/scale/b (3,) and A (3,3)
    covariance: np.ndarray  # over the fitted parameters (PARAM_NAMES order; 9 for norm-only)
    uncertainty_scaled: bool  # True when the covariance was rescaled by the reduced chi-square
    ref_sigma_deg: float | None
    noise_g: np.ndarray  # (m,) per-position 1-sigma of the mean reading, in g, used as weight
    temp_c: float | None = None
    positions: np.ndarray | None = None  # (m,) fixture position index per row, when known
    n_samples: np.ndarray | None = None  # (m,)
    success: bool = True
    nfev: int = 0
    notes: list[str] = field(default_factory=list)
    # held-out |a| - 1 g RMSE (mg): positions or samples the fit never saw (see heldout_rmse)
    rmse_heldout_mg: float | None = None
    heldout_method: str | None = None
    # where ref_sigma_deg came from (station/science/sfem_goodness.py): measured on this step's
    # direction residuals, the profile's setting, or the documented default
    ref_sigma_source: str = ""
    goodness: "SfemGoodness | None" = None  # the residual against the noise (sfem_goodness.py)

    @property
    def M(self) -> np.ndarray:
        return Rotation.from_rotvec(self.misalignment_rotvec_rad).as_matrix()

    @property
    def C(self) -> np.ndarray:
        return c_matrix(self.nonorthogonality)

    @property
    def S(self) -> np.ndarray:
        return np.diag(self.scale)

    @property
    def bias(self) -> np.ndarray:
        return self.b

    def params(self) -> np.ndarray:
        """The 12 parameters in PARAM_NAMES order."""
        return np.concatenate([self.misalignment_rotvec_rad, self.nonorthogonality, self.scale, self.b])

    def apply(self, raw: np.ndarray) -> np.ndarray:
        """Calibrated acceleration in g of raw readings (..., 3)."""
        return (np.asarray(raw, dtype=np.float64) - self.b) @ self.A.T

    def to_json(self) -> dict:
        mis = {
            "determined": self.misalignment_determined,
            "rotvec_deg": np.degrees(self.misalignment_rotvec_rad).tolist(),
            "matrix": self.M.tolist(),
        }
        if self.misalignment_determined:
            mis["rotvec_sigma_deg"] = np.degrees(self.sigma["rotvec_rad"]).tolist()
        else:
            mis["note"] = MISALIGNMENT_NOTE
        residuals = []
        for i in range(self.n_positions):
            row = {"norm_err_mg": float(self.residual_norm_mg[i])}
            if self.residual_direction_deg is not None:
                row["direction_err_deg"] = float(self.residual_direction_deg[i])
            if self.positions is not None:
                row["position"] = int(self.positions[i])
            if self.n_samples is not None:
                row["n_samples"] = int(self.n_samples[i])
            residuals.append(row)
        return {
            "method": self.method,
            "temp_c": self.temp_c,
            "A": self.A.tolist(),
            "A_sigma": self.sigma["A"].tolist(),
            "b": self.b.tolist(),
            "misalignment": mis,
            "nonorthogonality": {
                "alpha_yx_rad": float(self.nonorthogonality[0]),
                "alpha_zx_rad": float(self.nonorthogonality[1]),
                "alpha_zy_rad": float(self.nonorthogonality[2]),
                "sigma_rad": self.sigma["alpha"].tolist(),
            },
            "scale": self.scale.tolist(),
            "scale_sigma": self.sigma["scale"].tolist(),
            "bias": self.b.tolist(),
            "bias_sigma": self.sigma["b"].tolist(),
            "rmse_before_mg": self.rmse_before_mg,
            "rmse_after_mg": self.rmse_after_mg,
            "rmse_direction_mg": self.rmse_direction_mg,
            "rmse_heldout_mg": self.rmse_heldout_mg,
            "heldout_method": self.heldout_method,
            "n_positions": self.n_positions,
            "ref_sigma_deg": self.ref_sigma_deg,
            "ref_sigma_source": self.ref_sigma_source,
            "goodness_of_fit": None if self.goodness is None else self.goodness.to_json(),
            "uncertainty_scaled": self.uncertainty_scaled,
            "success": self.success,
            "residuals": residuals,
            "notes": list(self.notes),
        }


__all__ = [
    "SfemFit",
    "SfemGoodness",
    "SfemInsufficientData",
    "compose_a",
    "decompose_a",
    "c_matrix",
    "PARAM_NAMES",
    "MISALIGNMENT_NOTE",
]
