"""Sensor frame error model (sensors2023 eq. 1): U_SF = M C S (U - b), its fit, and its thermal model.

    M  misalignment, a rotation (3 parameters, rotation vector)
    C  non-orthogonality, lower triangular with unit diagonal (alpha_yx, alpha_zx, alpha_zy)
    S  scale, diagonal (g per raw unit)
    b  bias, raw units
    A = M C S maps raw readings, after bias removal, to g.

How the fit treats the fixture's reference directions (why it is built this way)
--------------------------------------------------------------------------------
Static readings carry two kinds of information with very different quality:
  * the gravity *norm*: |A (u_i - b)| = 1 g holds in every position whatever the fixture does, and
    is limited only by sensor noise (~0.03 mg for 200 averaged samples). It is rotation-invariant, so
    it determines b, C and S (9 parameters, needs >= 9 well-spread positions) but never M.
  * the *direction*: A (u_i - b) / |.| = r_i holds only as well as the fixture puts gravity where the
    reference says. A real fixture is good to a fraction of a degree, i.e. ~10 mg, 300x the noise.
An unweighted fit of A (u_i - b) = r_i lets those reference errors leak into the sensor's own
parameters (off-diagonal terms of C by ~deg/sqrt(n), scale through the projection of tilt errors).
So the reference fit is the maximum-likelihood fit in which each reference direction has its own
random error of `ref_sigma_deg` (the per-position errors are nuisance parameters; marginalised they
become a weight): the residual vector of position i is
    norm:       (|v_i| - 1) / sigma_i
    direction:  (v_i / |v_i| - r_i) / sqrt(sigma_ref^2 + sigma_i^2),     v_i = M C S (u_i - b)
all 12 parameters fitted together by Levenberg-Marquardt (scipy least_squares, method "lm").
With >= 9 positions the norm terms pin b, C, S at their noise limit and the directions only set M
(this is the limit of the "norm fit + orthogonal Procrustes for M" two-stage method, which is
what the initial guess does); with 6 positions (a Ferraris six-position set) the norm cannot
determine all nine sensor parameters and the directions supply the rest, weighted honestly. One
model, one covariance (from the Jacobian), no switch between methods.

The norm-only fit uses the 9 rotation-invariant parameters; M is not observable from the norm
alone and is reported as the identity with `misalignment_determined = False`.

Thermal model (sensors2023 eq. 8): each of the 12 parameters as a polynomial (cubic when there are
>= 4 temperature steps, lower otherwise) of (T - t_ref_c).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from station.science.static_detect import (
    StaticDetectConfig,
    StaticInterval,
    detect_static_intervals,
    robust_noise_g,
)
from contracts.types import StationError, T_REF_C

MIN_POSITIONS_REFERENCE = 6
MIN_POSITIONS_NORM_ONLY = 9
DEFAULT_REF_SIGMA_DEG = 1.0
DEFAULT_NOISE_G = 1e-4  # weight used when the caller gives no noise figure (covariance is rescaled)
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


def _lower_from_gram(q: np.ndarray) -> np.ndarray:
    """Lower-triangular L with L^T L = q (q symmetric positive definite)."""
    j = np.eye(3)[::-1]
    lc = np.linalg.cholesky(j @ q @ j)  # j q j = lc lc^T
    return j @ lc.T @ j


def _ellipsoid_init(u: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Algebraic ellipsoid fit u^T Q u + p^T u = 1 -> (b, L) with |L (u - b)| ~ 1; None if degenerate."""
    x, y, z = u.T
    design = np.column_stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, x, y, z])
    coef, *_ = np.linalg.lstsq(design, np.ones(len(u)), rcond=None)
    q = np.array([[coef[0], coef[3], coef[4]], [coef[3], coef[1], coef[5]], [coef[4], coef[5], coef[2]]])
    p = coef[6:]
    try:
        b = -0.5 * np.linalg.solve(q, p)
        k = 1.0 + b @ q @ b
        if k <= 0:
            return None
        low = _lower_from_gram(q / k)
    except np.linalg.LinAlgError:
        return None
    return b, low


def _wahba(v: np.ndarray, r: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Rotation M minimising sum w |M v_i - r_i|^2 (orthogonal Procrustes / Wahba, via SVD)."""
    w = np.ones(len(v)) if w is None else w
    h = (r * w[:, None]).T @ v
    uu, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(uu @ vt))
    return uu @ np.diag([1.0, 1.0, d]) @ vt


# ---------------------------------------------------------------------------------------------
# results


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
            "uncertainty_scaled": self.uncertainty_scaled,
            "success": self.success,
            "residuals": residuals,
            "notes": list(self.notes),
        }


# ---------------------------------------------------------------------------------------------
# the fit


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


def fit_sfem(
    acc: np.ndarray,
    ref_dir: np.ndarray | None = None,
    *,
    noise_g: float | np.ndarray | None = None,
    ref_sigma_deg: float = DEFAULT_REF_SIGMA_DEG,
    raw_per_g: float = 1.0,
    temp_c: float | None = None,
    positions: np.ndarray | None = None,
    n_samples: np.ndarray | None = None,
) -> SfemFit:
    """Fit the SFEM to m static mean readings `acc` (m, 3), in raw units.

    ref_dir (m, 3): reference gravity directions in the sensor frame (normalised here); None gives the
    norm-only fit (9 parameters, M undetermined). noise_g: 1-sigma of each mean reading in g (scalar
    or (m,)); when None the weights assume 0.1 mg and the covariance is rescaled by the reduced
    chi-square. ref_sigma_deg: assumed random error of each reference direction (see module doc).
    raw_per_g: nominal raw units per g, used only for the "before" RMSE (1 for readings in g).
    """
    u_raw = np.asarray(acc, dtype=np.float64).reshape(-1, 3)
    m = u_raw.shape[0]
    norm_only = ref_dir is None
    need = MIN_POSITIONS_NORM_ONLY if norm_only else MIN_POSITIONS_REFERENCE
    if m < need:
        kind = "a norm-only fit" if norm_only else "a reference fit"
        raise SfemInsufficientData(f"too few static positions: {m} (need at least {need} for {kind})")
    if not np.all(np.isfinite(u_raw)):
        raise SfemInsufficientData("static position means contain NaN/inf")
    if not norm_only:
        r = np.asarray(ref_dir, dtype=np.float64).reshape(-1, 3)
        if r.shape[0] != m:
            raise ValueError(f"ref_dir has {r.shape[0]} rows, acc has {m}")
        rn = np.linalg.norm(r, axis=1)
        if np.any(~np.isfinite(rn)) or np.any(rn < 0.5):
            raise SfemInsufficientData("reference directions must be (near) unit vectors")
        r = r / rn[:, None]
    notes: list[str] = []

    # internal units: raw / k with k ~ raw per g, so every parameter is O(1) for the optimiser
    k = float(np.median(np.linalg.norm(u_raw, axis=1)))
    if not k > 0:
        raise SfemInsufficientData("all readings are zero")
    u = u_raw / k
    scaled_cov = noise_g is None
    sig = np.broadcast_to(np.asarray(DEFAULT_NOISE_G if noise_g is None else noise_g, float), (m,)).copy()
    sig = np.maximum(sig, 1e-9)
    sref = math.radians(ref_sigma_deg)
    w_dir = 1.0 / np.sqrt(sref**2 + sig**2)

    # ---- initial guess: algebraic ellipsoid (b, C, S), then Procrustes for M; or affine LS
    init = _ellipsoid_init(u) if m >= MIN_POSITIONS_NORM_ONLY else None
    if init is not None:
        b0, low0 = init
        m0 = np.eye(3) if norm_only else _wahba((u - b0) @ low0.T, r)
        try:
            rot0, alpha0, scale0 = decompose_a(m0 @ low0)
        except SfemInsufficientData:
            init = None
    if init is None and not norm_only:
        design = np.column_stack([u, np.ones(m)])
        coef, *_ = np.linalg.lstsq(design, r, rcond=None)
        a0 = coef[:3].T
        b0 = -np.linalg.solve(a0, coef[3])
        rot0, alpha0, scale0 = decompose_a(a0)
    elif init is None:
        b0, rot0, alpha0, scale0 = np.zeros(3), np.zeros(3), np.zeros(3), np.ones(3)
    if norm_only:
        rot0 = np.zeros(3)

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        if norm_only:
            return np.zeros(3), p[0:3], p[3:6], p[6:9]
        return p[0:3], p[3:6], p[6:9], p[9:12]

    def residuals(p: np.ndarray) -> np.ndarray:
        rot, alpha, scale, b = unpack(p)
        v = (u - b) @ compose_a(rot, alpha, scale).T
        nv = np.linalg.norm(v, axis=1)
        res_norm = (nv - 1.0) / sig
        if norm_only:
            return res_norm
        res_dir = (v / nv[:, None] - r) * w_dir[:, None]
        return np.concatenate([res_norm, res_dir.ravel()])

    p0 = np.concatenate([alpha0, scale0, b0]) if norm_only else np.concatenate([rot0, alpha0, scale0, b0])
    n_res = m if norm_only else 4 * m
    if n_res < len(p0):
        raise SfemInsufficientData(f"too few static positions: {m} for {len(p0)} parameters")
    sol = least_squares(residuals, p0, method="lm", x_scale="jac", xtol=1e-14, ftol=1e-14, gtol=1e-14)
    if not sol.success:
        notes.append(f"optimiser: {sol.message}")
    rot, alpha, scale_int, b_int = unpack(sol.x)

    # ---- covariance from the Jacobian (weighted residuals => inverse of J^T J)
    jac = sol.jac
    jtj = jac.T @ jac
    cond = np.linalg.cond(jtj)
    if not np.isfinite(cond) or cond > 1e14:
        notes.append(f"poorly conditioned fit (cond {cond:.1e}): positions do not span enough directions")
    cov = np.linalg.pinv(jtj)
    dof = n_res - len(sol.x)
    if scaled_cov:
        if dof > 0:
            cov = cov * (2.0 * sol.cost / dof)
        else:
            notes.append("no redundancy: uncertainties not estimable without noise_g")
            cov = cov * np.nan
    # convert internal units (raw/k) back: scale_raw = scale_int / k, b_raw = b_int * k
    conv = np.ones(len(sol.x))
    off = 0 if norm_only else 3
    conv[off + 3 : off + 6] = 1.0 / k
    conv[off + 6 : off + 9] = k
    cov = cov * np.outer(conv, conv)
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    scale = scale_int / k
    b = b_int * k
    a = compose_a(rot, alpha, scale)

    # sigma of A by first-order propagation (numerical derivative of A with respect to the params)
    p_ext = np.concatenate([alpha, scale, b]) if norm_only else np.concatenate([rot, alpha, scale, b])

    def a_of(p: np.ndarray) -> np.ndarray:
        rr, al, sc, _ = (np.zeros(3), p[0:3], p[3:6], p[6:9]) if norm_only else (p[0:3], p[3:6], p[6:9], p[9:12])
        return compose_a(rr, al, sc).ravel()

    g = np.zeros((9, len(p_ext)))
    for j in range(len(p_ext)):
        h = 1e-7 * max(abs(p_ext[j]), 1e-3)
        dp = np.zeros(len(p_ext))
        dp[j] = h
        g[:, j] = (a_of(p_ext + dp) - a_of(p_ext - dp)) / (2 * h)
    sigma_a = np.sqrt(np.clip(np.diag(g @ cov @ g.T), 0, None)).reshape(3, 3)
    if norm_only:
        sigma = {"rotvec_rad": np.full(3, np.nan), "alpha": sd[0:3], "scale": sd[3:6], "b": sd[6:9], "A": sigma_a}
        notes.append(MISALIGNMENT_NOTE)
    else:
        sigma = {"rotvec_rad": sd[0:3], "alpha": sd[3:6], "scale": sd[6:9], "b": sd[9:12], "A": sigma_a}

    v = (u_raw - b) @ a.T
    nv = np.linalg.norm(v, axis=1)
    res_norm_mg = (nv - 1.0) * 1e3
    before_mg = (np.linalg.norm(u_raw / raw_per_g, axis=1) - 1.0) * 1e3
    if norm_only:
        rmse_dir, res_dir_deg = None, None
    else:
        rmse_dir = _rms(np.linalg.norm(v - r, axis=1)) * 1e3
        cosang = np.clip(np.sum(v * r, axis=1) / nv, -1.0, 1.0)
        res_dir_deg = np.degrees(np.arccos(cosang))
        if m >= 4:
            notes.append(
                f"reference direction residual {_rms(res_dir_deg):.3f} deg RMS (assumed {ref_sigma_deg:g} deg)"
            )
    return SfemFit(
        A=a,
        b=b,
        misalignment_rotvec_rad=np.asarray(rot, dtype=np.float64).copy(),
        nonorthogonality=np.asarray(alpha, dtype=np.float64).copy(),
        scale=scale,
        misalignment_determined=not norm_only,
        method="norm-only" if norm_only else "reference",
        n_positions=m,
        rmse_before_mg=_rms(before_mg),
        rmse_after_mg=_rms(res_norm_mg),
        rmse_direction_mg=rmse_dir,
        residual_norm_mg=res_norm_mg,
        residual_direction_deg=res_dir_deg,
        sigma=sigma,
        covariance=cov,
        uncertainty_scaled=scaled_cov,
        ref_sigma_deg=None if norm_only else ref_sigma_deg,
        noise_g=sig,
        temp_c=temp_c,
        positions=None if positions is None else np.asarray(positions).reshape(-1),
        n_samples=None if n_samples is None else np.asarray(n_samples).reshape(-1),
        success=bool(sol.success),
        nfev=int(sol.nfev),
        notes=notes,
    )


# ---------------------------------------------------------------------------------------------
# static positions of a record (pure: arrays in)


@dataclass
class PositionSet:
    """Static positions of one temperature step: one averaged reading per fixture position."""

    mean: np.ndarray  # (m, 3) raw units
    noise_g: np.ndarray  # (m,) 1-sigma of each mean, RMS over axes (white-noise assumption)
    n_samples: np.ndarray  # (m,)
    temp_c: np.ndarray  # (m,) mean temperature of each position
    ref_dir: np.ndarray | None  # (m, 3)
    position: np.ndarray | None  # (m,) fixture position index, -1 where unknown
    spans: list[list[tuple[int, int]]]  # sample index ranges [start, stop) averaged per position

    @property
    def step_temp_c(self) -> float:
        return float(np.average(self.temp_c, weights=self.n_samples))

    def __len__(self) -> int:
        return int(self.mean.shape[0])


def _runs(labels: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) runs of equal consecutive rows of a (n,) or (n, k) label array."""
    n = labels.shape[0]
    if n == 0:
        return []
    lab = labels.reshape(n, -1)
    change = np.any(lab[1:] != lab[:-1], axis=1)
    edges = np.concatenate([[0], np.flatnonzero(change) + 1, [n]])
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def temperature_steps(temps_c: np.ndarray, gap_c: float = 3.0) -> np.ndarray:
    """Label values by temperature step: sorted, a new step wherever the gap exceeds gap_c."""
    t = np.asarray(temps_c, dtype=np.float64)
    order = np.argsort(t)
    labels = np.empty(len(t), dtype=np.int64)
    if len(t):
        labels[order] = np.concatenate([[0], np.cumsum(np.diff(t[order]) > gap_c)])
    return labels


def _temperature_trend(time_s: np.ndarray, temp_c: np.ndarray, window_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Centred moving mean of the temperature and its rate (C/min) from the two half-window means."""
    n = len(temp_c)
    dt = float(np.median(np.diff(time_s))) if n > 1 else 1.0
    dt = dt if dt > 0 else 1.0
    h = max(2, int(round(window_s / dt / 2)))
    c = np.concatenate([[0.0], np.cumsum(temp_c - temp_c[0])])
    i = np.arange(n)
    lo, mid, hi = np.clip(i - h, 0, n), i, np.clip(i + h, 0, n)
    left = (c[mid] - c[lo]) / np.maximum(mid - lo, 1)
    right = (c[hi] - c[mid]) / np.maximum(hi - mid, 1)
    smooth = (c[hi] - c[lo]) / np.maximum(hi - lo, 1) + temp_c[0]
    span_s = 0.5 * ((mid - lo) + (hi - mid)) * dt
    rate = np.where((mid - lo > 0) & (hi - mid > 0), (right - left) / np.maximum(span_s, 1e-12) * 60.0, 0.0)
    return smooth, rate


def group_static_positions(
    time_s: np.ndarray | None,
    acc: np.ndarray,
    temp_c: np.ndarray | None = None,
    ref_dir: np.ndarray | None = None,
    position: np.ndarray | None = None,
    *,
    config: StaticDetectConfig | None = None,
    acc_g_per_raw: float = 1.0,
    temp_gap_c: float = 3.0,
    merge_angle_deg: float = 2.0,
    temp_window_s: float = 120.0,
    max_temp_rate_c_per_min: float = 0.3,
    temp_tol_c: float = 0.5,
    equalize_positions: bool = True,
) -> list[PositionSet]:
    """Static intervals -> averaged positions, split into temperature steps (coldest first).

    Intervals are found on acc * acc_g_per_raw (detector thresholds are in g), cut wherever the
    position or reference column changes, then merged per (temperature step, position): by the
    position index when known, else by the reference direction, else by measured direction
    (within merge_angle_deg).
    Soak discipline (sensors2023 4.3) when temperature and time are given: a DUT resting in one
    position while the chamber ramps is static for the accelerometer but not a soak, so samples
    count only where the temperature, smoothed over temp_window_s, changes by at most
    max_temp_rate_c_per_min and lies within temp_tol_c of its step's median. Steps are
    temperature clusters separated by more than temp_gap_c.
    equalize_positions (with temperature and time): within a step, a position keeps at most the
    step's median sample count, taken from the end of its longest span. The position a DUT rests
    in while the chamber settles is static for many times the plan's hold; its extra samples are
    the soak's tail, where the die still converges by tenths of a degree that a 1 C thermometer
    cannot resolve (x TDB ~1 mg/C: ~0.1 mg), and their number would make that position's noise
    sigma the smallest, so the fit would trust the most biased position most. The end of the
    soak is its most settled part, and every position then weighs as the plan intends.
    """
    cfg = config or StaticDetectConfig()
    a = np.asarray(acc, dtype=np.float64).reshape(-1, 3)
    n = a.shape[0]
    temps = np.zeros(n) if temp_c is None else np.asarray(temp_c, dtype=np.float64).reshape(-1)
    refs = None if ref_dir is None else np.asarray(ref_dir, dtype=np.float64).reshape(-1, 3)
    pos = None if position is None else np.asarray(position).reshape(-1).astype(np.int64)
    intervals = detect_static_intervals(time_s, a * acc_g_per_raw, cfg)
    label_cols = []
    if pos is not None:
        label_cols.append(pos[:, None].astype(np.float64))
    if refs is not None:
        label_cols.append(np.round(refs, 6))
    labels = np.concatenate(label_cols, axis=1) if label_cols else None
    settled = np.ones(n, dtype=bool)
    ts = temps
    if temp_c is not None and time_s is not None and n > 2:
        ts, rate = _temperature_trend(np.asarray(time_s, dtype=np.float64).reshape(-1), temps, temp_window_s)
        settled = np.abs(rate) <= max_temp_rate_c_per_min
    split_cols = [settled[:, None].astype(np.float64)]
    if labels is not None:
        split_cols.append(labels)
    split = np.concatenate(split_cols, axis=1)
    pieces: list[tuple[int, int]] = []
    for iv in intervals:
        for s, e in _runs(split[iv.start : iv.stop]):
            if e - s >= cfg.min_samples and settled[iv.start + s]:
                pieces.append((iv.start + s, iv.start + e))
    if refs is not None:
        pieces = [(s, e) for s, e in pieces if np.all(np.isfinite(refs[s])) and np.linalg.norm(refs[s]) > 0.5]
    if not pieces:
        return []
    piece_temp = np.array([ts[s:e].mean() for s, e in pieces])
    steps = temperature_steps(piece_temp, temp_gap_c)
    if temp_c is not None:  # keep only samples near their step's temperature
        kept, kept_steps = [], []
        for step in range(int(steps.max()) + 1):
            mine = [pc for pc, st in zip(pieces, steps) if st == step]
            med = float(np.median(np.concatenate([ts[s:e] for s, e in mine])))
            near = np.abs(ts - med) <= temp_tol_c
            for s0, e0 in mine:
                for s, e in _runs(near[s0:e0]):
                    if e - s >= cfg.min_samples and near[s0 + s]:
                        kept.append((s0 + s, s0 + e))
                        kept_steps.append(step)
        if not kept:
            return []
        pieces, steps = kept, np.array(kept_steps)
    out: list[PositionSet] = []
    cos_merge = math.cos(math.radians(merge_angle_deg))
    for step in range(int(steps.max()) + 1):
        groups: list[list[tuple[int, int]]] = []
        keys: list[object] = []
        for (s, e), st in zip(pieces, steps):
            if st != step:
                continue
            if pos is not None and pos[s] >= 0:
                key: object = ("p", int(pos[s]))
            elif refs is not None:
                key = ("r", tuple(np.round(refs[s], 4)))
            else:
                d = a[s:e].mean(axis=0)
                key = ("d", d / np.linalg.norm(d))
            hit = None
            for gi, kk in enumerate(keys):
                if key[0] == "d" and kk[0] == "d":
                    if float(np.dot(key[1], kk[1])) >= cos_merge:
                        hit = gi
                        break
                elif key[0] != "d" and kk == key:
                    hit = gi
                    break
            if hit is None:
                keys.append(key)
                groups.append([(s, e)])
            else:
                groups[hit].append((s, e))
        if not groups:
            continue
        if equalize_positions and temp_c is not None and time_s is not None and len(groups) > 1:
            cap = max(cfg.min_samples, int(np.median([sum(e - s for s, e in g) for g in groups])))
            for gi, spans in enumerate(groups):
                if sum(e - s for s, e in spans) > cap:
                    s, e = max(spans, key=lambda se: se[1] - se[0])
                    groups[gi] = [(max(s, e - cap), e)]
        means, noise, counts, tmeans, rlist, plist = [], [], [], [], [], []
        for spans in groups:
            idx = np.concatenate([np.arange(s, e) for s, e in spans])
            seg = a[idx]
            means.append(seg.mean(axis=0))
            std_g = seg.std(axis=0, ddof=1) * acc_g_per_raw
            noise.append(float(np.sqrt(np.mean(std_g**2)) / math.sqrt(len(idx))))
            counts.append(len(idx))
            tmeans.append(float(temps[idx].mean()))
            if refs is not None:
                rlist.append(np.median(refs[idx], axis=0))
            plist.append(int(pos[spans[0][0]]) if pos is not None else -1)
        out.append(
            PositionSet(
                mean=np.array(means),
                noise_g=np.array(noise),
                n_samples=np.array(counts),
                temp_c=np.array(tmeans),
                ref_dir=np.array(rlist) if refs is not None else None,
                position=np.array(plist) if pos is not None else None,
                spans=groups,
            )
        )
    return out


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



# ---------------------------------------------------------------------------------------------
# a whole record: static positions per temperature step, one fit per step, thermal polynomials


@dataclass
class SfemRecordResult:
    """SFEM of a record: one fit per temperature step (coldest first) and, with >= 2 steps, the
    polynomial thermal model. `main` is the step nearest t_ref_c (the headline figures)."""

    fits: list[SfemFit]
    main: SfemFit
    thermal: SfemThermalModel | None
    n_static_intervals: int
    skipped_steps: list[dict]
    notes: list[str]

    def to_json(self) -> dict:
        out = self.main.to_json()
        out["n_static_intervals"] = self.n_static_intervals
        out["temperature_steps_c"] = [f.temp_c for f in self.fits]
        out["steps"] = [f.to_json() for f in self.fits]
        out["thermal"] = None if self.thermal is None else self.thermal.to_json()
        out["skipped_steps"] = self.skipped_steps
        out["notes"] = list(dict.fromkeys(out["notes"] + self.notes))
        return out


def heldout_rmse(acc: np.ndarray, ps: "PositionSet", norm_only: bool, ref_sigma_deg: float,
                 acc_g_per_raw: float) -> tuple[float | None, str | None]:
    """Held-out |a| - 1 g RMSE of an SFEM step, in mg.

    With one position more than the fit needs: leave one position out (each predicted by a fit of
    the others). Otherwise (six positions for the 12-parameter reference fit: the in-sample "after"
    is near zero by construction) held-out halves: fit the first half of every static interval,
    test on the second half, and the other way round.
    """
    need = MIN_POSITIONS_NORM_ONLY if norm_only else MIN_POSITIONS_REFERENCE
    m = len(ps)
    ref = None if norm_only else ps.ref_dir
    res = []
    try:
        if m - 1 >= need:
            for i in range(m):
                keep = np.arange(m) != i
                f = fit_sfem(ps.mean[keep], None if ref is None else ref[keep], noise_g=ps.noise_g[keep],
                             ref_sigma_deg=ref_sigma_deg, raw_per_g=1.0 / acc_g_per_raw)
                res.append((np.linalg.norm(f.apply(ps.mean[i]) * 1.0) - 1.0) * 1e3)
            return _rms(np.asarray(res)), "leave one position out"
        halves = []
        for spans in ps.spans:
            idx = np.concatenate([np.arange(a, b) for a, b in spans])
            if idx.size < 4:
                return None, None
            h = idx.size // 2
            halves.append((acc[idx[:h]].mean(axis=0), acc[idx[h:]].mean(axis=0)))
        u1 = np.array([a for a, _ in halves])
        u2 = np.array([b for _, b in halves])
        for fit_on, test_on in ((u1, u2), (u2, u1)):
            f = fit_sfem(fit_on, ref, noise_g=ps.noise_g * np.sqrt(2.0), ref_sigma_deg=ref_sigma_deg,
                         raw_per_g=1.0 / acc_g_per_raw)
            res.extend((np.linalg.norm(f.apply(test_on), axis=1) - 1.0) * 1e3)
        return _rms(np.asarray(res)), "held-out halves (fit on one half of every static interval, tested on the other)"
    except SfemInsufficientData:
        return None, None


def fit_sfem_record(
    time_s: np.ndarray | None,
    acc: np.ndarray,
    temp_c: np.ndarray | None = None,
    ref_dir: np.ndarray | None = None,
    position: np.ndarray | None = None,
    *,
    norm_only: bool = False,
    ref_sigma_deg: float = DEFAULT_REF_SIGMA_DEG,
    config: StaticDetectConfig | None = None,
    acc_g_per_raw: float = 1.0,
    temp_gap_c: float = 3.0,
    t_ref_c: float = T_REF_C,
) -> SfemRecordResult:
    """Static intervals -> positions per temperature step -> fit_sfem per step -> cubic model.

    norm_only ignores ref_dir; otherwise ref_dir is required. Steps with too few positions are
    skipped (listed in skipped_steps); no usable step raises SfemInsufficientData.
    """
    if not norm_only and ref_dir is None:
        raise SfemInsufficientData("no reference directions (ref_x, ref_y, ref_z): give them or use a norm-only fit")
    need = MIN_POSITIONS_NORM_ONLY if norm_only else MIN_POSITIONS_REFERENCE
    cfg = config or StaticDetectConfig()
    sets = group_static_positions(
        time_s, acc, temp_c, None if norm_only else ref_dir, position,
        config=cfg, acc_g_per_raw=acc_g_per_raw, temp_gap_c=temp_gap_c,
    )  # fmt: skip
    n_intervals = sum(len(spans) for ps in sets for spans in ps.spans)
    fits, skipped = [], []
    for ps in sets:
        if len(ps) < need:
            skipped.append({"temp_c": ps.step_temp_c, "n_positions": len(ps), "reason": f"fewer than {need} positions"})
            continue
        fit = fit_sfem(
            ps.mean,
            None if norm_only else ps.ref_dir,
            noise_g=ps.noise_g,
            ref_sigma_deg=ref_sigma_deg,
            raw_per_g=1.0 / acc_g_per_raw,
            temp_c=ps.step_temp_c,
            positions=ps.position,
            n_samples=ps.n_samples,
        )
        fit.rmse_heldout_mg, fit.heldout_method = heldout_rmse(
            np.asarray(acc, dtype=np.float64), ps, norm_only, ref_sigma_deg, acc_g_per_raw)
        fits.append(fit)
    if not fits:
        best = max((len(ps) for ps in sets), default=0)
        kind = "norm-only fit" if norm_only else "reference fit"
        raise SfemInsufficientData(
            f"too few static positions: found {best} in the best temperature step (need at least {need} for a {kind})"
        )
    notes = []
    if skipped:
        notes.append(f"{len(skipped)} temperature step(s) skipped: too few static positions")
    thermal = None
    if len(fits) >= 2:
        thermal = SfemThermalModel.fit([(f.temp_c, f) for f in fits], t_ref_c=t_ref_c)
        notes.extend(thermal.notes)
    main = min(fits, key=lambda f: abs(f.temp_c - t_ref_c))
    return SfemRecordResult(fits, main, thermal, n_intervals, skipped, notes)

__all__ = [
    "SfemFit",
    "SfemParams",
    "SfemThermalModel",
    "SfemInsufficientData",
    "PositionSet",
    "fit_sfem",
    "fit_sfem_record",
    "heldout_rmse",
    "SfemRecordResult",
    "group_static_positions",
    "temperature_steps",
    "detect_static_intervals",
    "StaticDetectConfig",
    "StaticInterval",
    "compose_a",
    "decompose_a",
    "c_matrix",
    "robust_noise_g",
    "MIN_POSITIONS_REFERENCE",
    "MIN_POSITIONS_NORM_ONLY",
]
