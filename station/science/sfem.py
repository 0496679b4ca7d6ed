"""Fitting the sensor frame error model (sensors2023 eq. 1) to static mean readings: `fit_sfem`.

Why this module: the fit is where the fixture's reference directions are weighed against the
sensor's noise (below), and that reasoning belongs next to the optimiser that implements it, apart
from the model it fits and from what is built on top of a fit. The SFEM is split along those seams:

    sfem_model      the model U_SF = M C S (U - b), its algebra and the fitted result SfemFit
    sfem            the fit of one set of static positions (this module)
    sfem_positions  a record's static intervals -> averaged positions per temperature step
    sfem_heldout    the held-out RMSE of a fit (positions or samples the fit never saw)
    sfem_thermal    each parameter as a polynomial of temperature (sensors2023 eq. 8)
    sfem_record     a whole record: positions -> one fit per step -> thermal model

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
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares

from station.science.sfem_model import (
    MISALIGNMENT_NOTE,
    SfemFit,
    SfemInsufficientData,
    compose_a,
    decompose_a,
)

MIN_POSITIONS_REFERENCE = 6
MIN_POSITIONS_NORM_ONLY = 9
DEFAULT_REF_SIGMA_DEG = 1.0
DEFAULT_NOISE_G = 1e-4  # weight used when the caller gives no noise figure (covariance is rescaled)


# ---------------------------------------------------------------------------------------------
# initial guess


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


__all__ = [
    "fit_sfem",
    "MIN_POSITIONS_REFERENCE",
    "MIN_POSITIONS_NORM_ONLY",
    "DEFAULT_REF_SIGMA_DEG",
]
