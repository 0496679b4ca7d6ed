"""Rank candidate effects against the baseline, admit the ones the data supports, refit (design 7).

Statistics, for one DUT or a batch (sums over DUTs: each DUT has its own parameters, the effect
structure is shared). Real MEMS parts have a wandering bias (random walk, flicker), so the residual
of a perfect model is not white and its minutes are not independent; every figure accounts for it:

- held-out RMS: blocked K-fold over whole thermal legs (a heating or cooling ramp with its hold,
  i.e. a profile step; model.Segmentation), each predicted by a fit that saw neither the leg nor a
  guard of 10 min on each side of it. Never short interleaved chunks, never at random.
- noise model of the residual: AR(p) (p <= 6 by BIC) of the 10 s block means, per DUT and axis and
  within constant-orientation runs, estimated on the residual of the larger model of each
  comparison (so an effect missing from the smaller model is not mistaken for noise). A bias
  random walk shows up as phi ~ 1; the AR filter prewhitens data and regressors (GLS).
- likelihood-ratio test (reported as score / score_p): LR = sum n ln(SSR_small / SSR_big) of the
  prewhitened GLS fits ~ chi2(dk), dk = extra linear and nonlinear parameters.
- delta BIC = sum n ln(SSR_big / SSR_small) + dk ln(N), N = prewhitened block count.
- uncertainties: GLS covariance sigma^2 (X~' X~)^-1 of the prewhitened fit.
- admission gate (model before -> model with the effect): delta BIC < -30, LR p < 0.001 and
  held-out RMS lower by >= 3 %. The forward staircase gates every candidate against the model
  holding exactly the effects admitted before it and admits, of those that pass, the one with the
  lowest delta BIC; repeated until none passes. `admitted` is the staircase `--add` of those effects
  reproduces, each step lowering the held-out error. When no single candidate passes, the (at most
  3) candidates strong in sample but worse held-out are tried in pairs: two effects of opposite
  sign that mask each other are admitted together when the pair passes the gate.
- aliases: candidates whose regressors are identical on the data (bias_t2 and scale_t2 with one
  orientation: dT^2 Acc0 is a multiple of dT^2) are one term, ranked and admitted under the first
  name, with the others listed.
- unidentifiable: regressors inside the baseline's span (cross_axis from two orientations), and
  TDSF with one orientation (only the total drift TDB + TDSF Acc0 is measurable): reported with the
  test that would identify them.
- confusable: pairs only a data feature separates (thermal_lag and hysteresis need >= 2 ramp
  rates) or whose fitted contributions are nearly collinear: the better one may be admitted, flagged
  with its partner, and the partner is not tested on top of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter
from scipy.stats import chi2

from station.diagnostics.effects import BUILTIN_NAMES, REGISTRY, get_effect, load_effects_file
from station.diagnostics.model import (
    DiagnosticModel, DutData, DutFit, Segmentation, _tau_int, fit_dut, heldout_residual, predict_dut, prepare,
    tdsf_identifiable, window_rms,
)
from contracts.logfile import DutLog, read_log
from contracts.types import AXES, StationError

BIC_GATE = -30.0  # "very strong" is -10 for an exact likelihood; a margin for the approximate noise model
HELDOUT_GAIN_GATE = 0.03
SCORE_P_GATE = 1e-3
UNIDENTIFIABLE_REL = 1e-3
CONFUSABLE_COS = 0.9
MIN_TEMP_SPAN_C = 3.0


@dataclass
class ModelEval:
    """A fitted model structure over all DUTs, with its in-sample and held-out residuals."""

    effects: list[str]
    fits: list[DutFit]
    resid: list[np.ndarray]  # per DUT (n, 3) mg, in-sample
    heldout: list[np.ndarray]  # per DUT (n, 3) mg, held-out
    rms_mg: float = 0.0
    heldout_rms_mg: float = 0.0
    rms_sample_mg: float = 0.0
    heldout_rms_sample_mg: float = 0.0
    n_params: int = 0


@dataclass
class DiagnosisReport:
    """What `station diagnose` prints and the web page shows (design 5.2 JSON via to_json())."""

    serials: list[str]
    rms_basis: str
    baseline: ModelEval
    ranking: list[dict]
    model: ModelEval
    staircase: list[dict]
    confusable: list[dict]
    unidentifiable: list[dict]
    parameters: dict
    features: dict = field(default_factory=dict)
    data: list[DutData] = field(repr=False, default_factory=list)
    admitted: list[str] = field(default_factory=list)
    admitted_staircase: list[dict] = field(default_factory=list)
    aliases: list[dict] = field(default_factory=list)
    noise_model: dict = field(default_factory=dict)
    drift: dict = field(default_factory=dict)
    baseline_parameters: dict = field(default_factory=dict)
    candidates: dict[str, ModelEval] = field(repr=False, default_factory=dict)

    def to_json(self) -> dict:
        return {
            "serials": self.serials,
            "residual": "measured - model, mg",
            "rms_basis": self.rms_basis,
            "baseline": _eval_json(self.baseline),
            "ranking": self.ranking,
            "model": {"effects": self.model.effects, **_eval_json(self.model), "parameters": self.parameters},
            "staircase": self.staircase,
            "confusable": self.confusable,
            "unidentifiable": self.unidentifiable,
            "data_features": self.features,
            "admitted": self.admitted,
            "admitted_staircase": self.admitted_staircase,
            "aliases": self.aliases,
            "noise_model": self.noise_model,
            "drift": self.drift,
            "baseline_parameters": self.baseline_parameters,
        }

    def models(self) -> list[DiagnosticModel]:
        """The final model per DUT, ready to save or to compensate with."""
        return [DiagnosticModel.from_fit(d.serial, f, d.t_power_on_s) for d, f in zip(self.data, self.model.fits)]


def _eval_json(m: ModelEval) -> dict:
    return {"rms_mg": _r(m.rms_mg), "heldout_rms_mg": _r(m.heldout_rms_mg),
            "rms_per_sample_mg": _r(m.rms_sample_mg), "heldout_rms_per_sample_mg": _r(m.heldout_rms_sample_mg)}


def _r(x, nd=4):
    if x is None or not np.isfinite(x):
        return None
    return round(float(x), nd)


def _sig(x, n=6):
    """Round to n significant digits (parameters span 1e-4 mg/C^3 to 1e3 ppm/C)."""
    if x is None or not np.isfinite(x):
        return None
    return float(f"{float(x):.{n}g}")


# ---------------------------------------------------------------------------------------------


def _pooled_rms(data: list[DutData], res: list[np.ndarray], basis: str) -> float:
    """RMS over every DUT's samples (each DUT weighted by its sample count)."""
    num = den = 0.0
    for d, r in zip(data, res):
        ok = ~np.isnan(r).any(axis=1)
        if not ok.any():
            continue
        v = window_rms(d, r, basis=basis)
        num += v * v * ok.sum()
        den += ok.sum()
    return math.sqrt(num / den) if den else float("nan")


def evaluate(data: list[DutData], effects: list[str], basis: str, n_folds: int,
             nl_start: list[dict] | None = None) -> ModelEval:
    fits, res, held = [], [], []
    for k, d in enumerate(data):
        f = fit_dut(d, effects, nl_start=nl_start[k] if nl_start else None)
        f.beta_sigma = gls_sigma(d, f)  # the residual's AR noise model, not white noise
        fits.append(f)
        res.append(d.acc_mg - predict_dut(d, f))
        held.append(heldout_residual(d, effects, f, n_folds))
    m = ModelEval(effects=list(effects), fits=fits, resid=res, heldout=held)
    m.rms_mg = _pooled_rms(data, res, basis)
    m.heldout_rms_mg = _pooled_rms(data, held, basis)
    m.rms_sample_mg = _pooled_rms(data, res, "sample")
    m.heldout_rms_sample_mg = _pooled_rms(data, held, "sample")
    m.n_params = sum(int(sum(np.count_nonzero(b) for b in f.beta) + sum(len(v) for v in f.nl.values())) for f in fits)
    return m


tau_int = _tau_int


def block_resid(d: DutData, r: np.ndarray) -> np.ndarray:
    """Block means of a per-sample residual (n_blocks, 3)."""
    return d.block_mean(np.nan_to_num(r))


def n_eff_axes(d: DutData, r: np.ndarray) -> np.ndarray:
    """Effective number of independent block means per axis (autocorrelation within runs)."""
    rb = block_resid(d, r)
    run_b = d.run[d.block_starts]
    out = np.zeros(3)
    for i in range(3):
        taus, counts = [], []
        for run_id in np.unique(run_b):
            x = rb[run_b == run_id, i]
            if x.size >= 8:
                taus.append(tau_int(x))
                counts.append(x.size)
        tau = float(np.average(taus, weights=counts)) if taus else 1.0
        out[i] = rb.shape[0] / tau
    return out


def _ssr_block(d: DutData, r: np.ndarray) -> np.ndarray:
    rb = block_resid(d, r)
    return np.sum(d.block_count[:, None] * rb**2, axis=0)


def _baseline_design(d: DutData, fit: DutFit):
    """Baseline columns per axis (block means) at the fitted Acc0."""
    from station.diagnostics.model import _Design

    mats, _ = _Design(d, []).matrices({}, fit.acc0_g)
    return [d.block_mean(m) for m in mats]


def _residualize(Xb: np.ndarray, Z: np.ndarray, w: np.ndarray) -> np.ndarray:
    sw = np.sqrt(w)[:, None]
    A = Xb * sw
    live = np.any(A != 0, axis=0)
    A = A[:, live]
    Zw = Z * sw
    coef, *_ = np.linalg.lstsq(A, Zw, rcond=None)
    return (Zw - A @ coef) / sw


def candidate_regressors(d: DutData, base_fit: DutFit, cand_fit: DutFit) -> list[np.ndarray]:
    """Per axis (n_blocks, m): the candidate's regressors at its fitted nonlinear values.

    For a temperature-changing effect (thermal_lag) the regressor is the change of the baseline
    prediction when the lagged temperature replaces the measured one (the derivative direction).
    """
    from station.diagnostics.model import _Design

    eff = [get_effect(n) for n in cand_fit.effects if n not in base_fit.effects]
    design = _Design(d, eff)
    mats, names = design.matrices(cand_fit.nl, base_fit.acc0_g)
    P = len(d.pos_labels)
    out = []
    for i in range(3):
        cols = [mats[i][:, P + 2:]]
        if design.lag:
            base_mats, _ = _Design(d, []).matrices({}, base_fit.acc0_g)
            base_pred = base_mats[i] @ base_fit.beta[i][: P + 2]
            lag_pred = mats[i][:, : P + 2] @ base_fit.beta[i][: P + 2]
            cols.append((lag_pred - base_pred)[:, None])
        out.append(d.block_mean(np.hstack(cols)))
    return out


AR_MAX = 6
THETA_GRID = np.concatenate([[0.0], 1.0 - 10.0 ** np.linspace(-0.3, -3.5, 28)])


def _runs_of_blocks(d: DutData) -> list[np.ndarray]:
    """Block indices of each constant-orientation run (the noise filter restarts at a run)."""
    run_b = d.run[d.block_starts]
    cut = np.flatnonzero(np.diff(run_b) != 0) + 1
    return np.split(np.arange(run_b.size), cut)


@dataclass
class NoiseFilter:
    """Residual noise model of block means: a local level (random walk + white: IMA(1,1), theta) and
    AR(p) for what is left (flicker, short-range correlation). apply() is its prediction-error
    (whitening) filter, run per constant-orientation run, started at the run's first value."""

    theta: float
    phi: np.ndarray
    sigma: float

    def _ima(self, v: np.ndarray) -> np.ndarray:
        # (1 - L) y_t = (1 - theta L) e_t  ->  e = lfilter([1, -1], [1, -theta], y), level removed
        zi = -v[:1]  # the filter's state for a constant input equal to the first value: output 0
        y, _ = lfilter([1.0, -1.0], [1.0, -self.theta], v, axis=0, zi=zi)
        return y[1:]

    def _ar(self, v: np.ndarray) -> np.ndarray:
        p_ = self.phi.size
        if v.shape[0] <= p_:
            return v[:0]
        w = v[p_:].copy()
        for j in range(1, p_ + 1):
            w -= self.phi[j - 1] * v[p_ - j:v.shape[0] - j]
        return w

    def apply(self, x: np.ndarray, runs: list[np.ndarray]) -> np.ndarray:
        out = [self._ar(self._ima(x[idx])) for idx in runs if idx.size > self.phi.size + 2]
        return np.concatenate(out) if out else x[:0]

    def to_json(self) -> dict:
        s = float(np.sum(self.phi))
        return {"model": "local level (random walk + white, IMA(1,1)) + AR(p)", "theta": _r(self.theta, 5),
                "ar_order": int(self.phi.size), "phi": [round(float(x), 4) for x in self.phi],
                "innovation_mg": _r(self.sigma, 5),
                "random_walk": bool(self.theta < 0.999),
                "long_run_factor": _r(1.0 / max(abs(1.0 - s), 1e-3), 2)}


def ar_fit(e: np.ndarray, runs: list[np.ndarray], pmax: int = AR_MAX) -> NoiseFilter:
    """Fit the residual noise model: theta of the local level by conditional sum of squares on a
    grid (theta -> 1: no random walk), then AR(p) (p <= pmax by BIC) of the IMA-filtered residual."""
    e = np.asarray(e, float)
    best = None
    for th in THETA_GRID:
        f = NoiseFilter(float(th), np.zeros(0), 0.0)
        w = f.apply(e, runs)
        ss = float(np.mean(w**2)) if w.size else math.inf
        if best is None or ss < best[0]:
            best = (ss, float(th))
    theta = best[1]
    pieces = [NoiseFilter(theta, np.zeros(0), 0.0)._ima(e[idx]) for idx in runs if idx.size > pmax + 3]
    rows_y, rows_x = [], []
    for x in pieces:
        if x.size <= pmax + 1:
            continue
        rows_y.append(x[pmax:])
        rows_x.append(np.stack([x[pmax - j:x.size - j] for j in range(1, pmax + 1)], axis=1))
    if not rows_y:
        return NoiseFilter(theta, np.zeros(0), float(np.std(e)) if e.size else 0.0)
    Y = np.concatenate(rows_y)
    X = np.concatenate(rows_x)
    n = Y.size
    bbest = (math.inf, np.zeros(0), float(np.sqrt(np.mean(Y**2))))
    for p_ in range(pmax + 1):
        if p_:
            phi, *_ = np.linalg.lstsq(X[:, :p_], Y, rcond=None)
            r = Y - X[:, :p_] @ phi
        else:
            phi, r = np.zeros(0), Y
        s2 = max(float(np.mean(r**2)), 1e-300)
        bic = n * math.log(s2) + p_ * math.log(n)
        if bic < bbest[0]:
            bbest = (bic, phi, math.sqrt(s2))
    return NoiseFilter(theta, bbest[1], bbest[2])


def whiten(x: np.ndarray, runs: list[np.ndarray], nf: NoiseFilter) -> np.ndarray:
    return nf.apply(x, runs)


def _design_blocks(d: DutData, effects: list[str], nl: dict, acc0_g: np.ndarray) -> list[np.ndarray]:
    from station.diagnostics.model import _Design

    mats, _ = _Design(d, [get_effect(n) for n in effects]).block_matrices(nl, acc0_g)
    return mats


def _n_nl(effects: list[str]) -> int:
    return sum(len(get_effect(n).nonlinear) for n in effects)


def _gls_ssr(Xw: np.ndarray, yw: np.ndarray) -> tuple[float, int]:
    live = np.any(np.abs(Xw) > 0, axis=0)
    A = Xw[:, live]
    if A.shape[1] == 0:
        return float(yw @ yw), 0
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    sol, _, rank, _ = np.linalg.lstsq(A / scale, yw, rcond=None)
    r = yw - (A / scale) @ sol
    return float(r @ r), int(rank)


@dataclass
class Comparison:
    """Small model vs big model under the big model's AR noise (prewhitened GLS)."""

    lr: float
    df: int
    p: float
    delta_bic: float
    n: int
    noise: dict


def compare(data: list[DutData], small: list[tuple], big: list[tuple]) -> Comparison:
    """Likelihood-ratio test and delta BIC of `big` against `small` (per DUT: (effects, nl, acc0_g)).

    The noise model (AR(p) per DUT and axis) is fitted on the OLS residual of the big model and both
    models are refitted by GLS under it, so the comparison is fair and the random-walk part of the
    residual is not counted as independent evidence."""
    lr = 0.0
    df = 0
    n_tot = 0
    noise: dict = {}
    for d, (es, nls, a0s), (eb, nlb, a0b) in zip(data, small, big):
        Xs = _design_blocks(d, es, nls, a0s)
        Xb = _design_blocks(d, eb, nlb, a0b)
        runs = _runs_of_blocks(d)
        noise[d.serial] = {}
        for i in range(3):
            y = d.y_block[:, i]
            live = np.any(np.abs(Xb[i]) > 0, axis=0)
            coef, *_ = np.linalg.lstsq(Xb[i][:, live], y, rcond=None)
            e = y - Xb[i][:, live] @ coef
            nf = ar_fit(e, runs)
            yw = nf.apply(y, runs)
            ss, ks = _gls_ssr(nf.apply(Xs[i], runs), yw)
            sb, kb = _gls_ssr(nf.apply(Xb[i], runs), yw)
            n = yw.size
            lr += n * math.log(max(ss, 1e-300) / max(sb, 1e-300))
            df += max(kb - ks, 0)
            n_tot += n
            noise[d.serial][AXES[i]] = nf.to_json()
        df += max(_n_nl(eb) - _n_nl(es), 0)
    df = max(df, 1)
    lr = max(lr, 0.0)
    p = float(chi2.sf(lr, df))
    dbic = -lr + df * math.log(max(n_tot, 2))
    return Comparison(lr=lr, df=df, p=p, delta_bic=dbic, n=n_tot, noise=noise)


def _spec(m: ModelEval) -> list[tuple]:
    return [(list(m.effects), f.nl, f.acc0_g) for f in m.fits]


def _spec_plus(m: ModelEval, cand: ModelEval, name: str) -> list[tuple]:
    """The model m plus candidate `name` at the candidate's own nonlinear values (cheap screen)."""
    out = []
    for f, cf in zip(m.fits, cand.fits):
        nl = {**f.nl, name: cf.nl.get(name, {})}
        out.append((list(m.effects) + [name], nl, f.acc0_g))
    return out


def gls_sigma(d: DutData, fit: DutFit) -> list[np.ndarray]:
    """1-sigma of every linear parameter from the GLS fit under the residual's AR noise model."""
    X = _design_blocks(d, fit.effects, fit.nl, fit.acc0_g)
    runs = _runs_of_blocks(d)
    out = []
    for i in range(3):
        y = d.y_block[:, i]
        sig = np.full(X[i].shape[1], np.nan)
        live = np.any(np.abs(X[i]) > 0, axis=0)
        A = X[i][:, live]
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        nf = ar_fit(y - A @ coef, runs)
        Aw = nf.apply(A, runs)
        yw = nf.apply(y, runs)
        scale = np.linalg.norm(Aw, axis=0)
        scale[scale == 0] = 1.0
        sol, *_ = np.linalg.lstsq(Aw / scale, yw, rcond=None)
        r = yw - (Aw / scale) @ sol
        s2 = float(r @ r) / max(1, yw.size - A.shape[1])
        cov = np.linalg.pinv((Aw / scale).T @ (Aw / scale)) / np.outer(scale, scale)
        sig[live] = np.sqrt(np.maximum(np.diag(cov), 0.0) * s2)
        out.append(sig)
    return out


def identifiability(data: list[DutData], base: ModelEval, name: str) -> float:
    """Smallest-over-DUTs max-over-columns relative norm of the candidate regressors left after
    projecting out the baseline's. ~0: the data cannot identify the candidate."""
    from station.diagnostics.model import _Design

    eff = get_effect(name)
    worst = 1.0
    best_any = 0.0
    for d, bf in zip(data, base.fits):
        nl0 = {eff.name: {p.name: p.init for p in eff.nonlinear}}
        design = _Design(d, [eff])
        mats, _ = design.matrices(nl0, bf.acc0_g)
        P = len(d.pos_labels)
        Xs = _baseline_design(d, bf)
        rel_cols = []
        for i in range(3):
            Z = d.block_mean(mats[i][:, P + 2:])
            if design.lag:
                base_mats, _ = _Design(d, []).matrices({}, bf.acc0_g)
                dl = (mats[i][:, P] - base_mats[i][:, P])[:, None]  # lagged minus measured dT
                Z = np.hstack([Z, d.block_mean(dl)])
            for c in range(Z.shape[1]):
                z = Z[:, c]
                nz = float(np.sqrt(np.sum(d.block_count * z * z)))
                if nz == 0:
                    continue
                zt = _residualize(Xs[i], z[:, None], d.block_count)[:, 0]
                rel_cols.append(float(np.sqrt(np.sum(d.block_count * zt * zt))) / nz)
        rel = max(rel_cols) if rel_cols else 0.0
        best_any = max(best_any, rel)
        worst = min(worst, rel)
    return best_any


def _contribution(data, base: ModelEval, cand: ModelEval) -> np.ndarray:
    """The candidate's fitted change of prediction (block means, all DUTs and axes), baseline
    projected out."""
    parts = []
    for d, bf, rb_, rc in zip(data, base.fits, base.resid, cand.resid):
        delta = block_resid(d, rb_) - block_resid(d, rc)  # = pred_cand - pred_base
        Xs = _baseline_design(d, bf)
        for i in range(3):
            parts.append(_residualize(Xs[i], delta[:, i:i + 1], d.block_count)[:, 0] * np.sqrt(d.block_count))
    return np.concatenate(parts)


def _cos(a: np.ndarray, b: np.ndarray) -> float:
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    return float(a @ b / (na * nb)) if na > 0 and nb > 0 else 0.0


TDSF_TEST = ("log a second orientation in which this axis reads a different Acc0 (turn the board over: "
             "+1 g and -1 g on the axis, e.g. the fast-thermal P/N turn or six-position) through the same "
             "temperatures; TDB and TDSF are then told apart by how the drift scales with Acc0")


def _params_json(data: list[DutData], fits: list[DutFit]) -> dict:
    """Fitted parameters with 1-sigma uncertainties in physical units, per DUT.

    Where TDSF is not identifiable (one orientation, or orientations with the same Acc0 on an axis)
    it is reported as null with the reason, and tdb_mg_per_c is the total drift of that orientation
    (also given as total_drift_mg_per_c): never a TDSF with a sigma that the data cannot support."""
    out = {}
    for d, f in zip(data, fits):
        dut: dict = {"baseline": {}, "effects": {}}
        tdsf_ok = tdsf_identifiable(f.acc0_g)
        for i, ax in enumerate(AXES):
            for name, b, s_ in zip(f.col_names[i], f.beta[i], f.beta_sigma[i]):
                entry = {"value": _sig(b), "sigma": _sig(s_, 3)}
                if "." in name:
                    eff, pname = name.split(".", 1)
                    if s_ == 0 and b == 0:
                        continue
                    dut["effects"].setdefault(eff, {}).setdefault(pname, {})[ax] = entry
                elif name == "tdsf_ppm_per_c" and not tdsf_ok[i]:
                    dut["baseline"].setdefault(name, {})[ax] = {
                        "value": None, "sigma": None, "identifiable": False,
                        "reason": "Acc0 of this axis is the same in every orientation of the log: only the total "
                                  "drift TDB + TDSF Acc0 is measured", "test_to_identify": TDSF_TEST}
                else:
                    dut["baseline"].setdefault(name, {})[ax] = entry
                    if name == "tdb_mg_per_c" and not tdsf_ok[i]:
                        dut["baseline"].setdefault("total_drift_mg_per_c", {})[ax] = dict(entry)
        for eff, vals in f.nl.items():
            for pname, v in vals.items():
                dut["effects"].setdefault(eff, {})[pname] = {
                    "value": _sig(v), "sigma": _sig(f.nl_sigma.get(eff, {}).get(pname, float("nan")), 3)}
        out[d.serial] = dut
    return out


def drift_identifiability(data: list[DutData], base: ModelEval) -> dict:
    """Per DUT and axis: is TDSF identifiable from the orientations in the log (see _params_json)?"""
    out = {}
    for d, f in zip(data, base.fits):
        ok = tdsf_identifiable(f.acc0_g)
        out[d.serial] = {ax: bool(ok[i]) for i, ax in enumerate(AXES)}
    return out


FEATURE_TEXT = {"ramp_rates": "two or more distinct temperature ramp rates"}


def ramp_rates(d: DutData) -> list[float]:
    """Distinct ramp rates (C/min) of a DUT's log: |dT/dt| over 5 min of the smoothed die
    temperature, histogram in half-octave bins; the bins holding >= 12 % of the ramping time."""
    t, T = d.time_s, d.temp_smooth_c
    if t.size < 10:
        return []
    dt = float(np.median(np.diff(t)))
    h = max(1, int(round(150.0 / dt)))
    if T.size <= 2 * h:
        return []
    rate = np.abs(T[2 * h:] - T[:-2 * h]) / (t[2 * h:] - t[:-2 * h]) * 60.0
    ramp = rate[rate > 0.25]
    if ramp.size < 0.02 * rate.size or ramp.size == 0:
        return []
    edges = np.arange(-2.0, 5.01, 0.5)
    hist, _ = np.histogram(np.log2(ramp), bins=edges)
    frac = hist / ramp.size
    centers = 2.0 ** (0.5 * (edges[:-1] + edges[1:]))
    return [round(float(c), 3) for c, f in zip(centers, frac) if f >= 0.12]


def data_features(data: list[DutData]) -> dict:
    """What the data contain that some identifications need (pooled over DUTs)."""
    rates = sorted({r for d in data for r in ramp_rates(d)})
    spread = math.log2(max(rates) / min(rates)) if rates else 0.0
    return {"ramp_rates": bool(spread >= 0.9), "ramp_rates_c_per_min": rates,
            "orientations": max(len(d.pos_labels) for d in data)}



TERMS = {"bias_t2": "curvature", "scale_t2": "curvature", "bias_t3": "cubic drift", "thermal_lag": "lag",
         "hysteresis": "hysteresis", "self_heating": "warm-up", "cross_axis": "cross-axis drift",
         "scale_nonlinearity": "nonlinearity drift"}
ALIAS_REL = 1e-4


def _span_residual(A: np.ndarray, B: np.ndarray) -> float:
    """Largest relative norm of a column of B left after projecting it on the span of A."""
    if A.shape[1] == 0 or B.shape[1] == 0:
        return 1.0
    coef, *_ = np.linalg.lstsq(A, B, rcond=None)
    r = B - A @ coef
    nb = np.linalg.norm(B, axis=0)
    ok = nb > 0
    return float(np.max(np.linalg.norm(r, axis=0)[ok] / nb[ok])) if ok.any() else 0.0


def alias_groups(data: list[DutData], base: ModelEval, names: list[str]) -> list[list[str]]:
    """Groups of candidates whose regressors span the same space on this data once the baseline is
    projected out (effects with nonlinear parameters are compared at their initial values only if
    they have none: a lag or width makes the regressor data-dependent, so those are never aliases)."""
    from station.diagnostics.model import _Design

    lin = [n for n in names if not get_effect(n).nonlinear and type(get_effect(n)).temperature is type(get_effect(n)).__mro__[-2].temperature]
    cols: dict[str, list[np.ndarray]] = {}
    for n in lin:
        parts = []
        for d, bf in zip(data, base.fits):
            mats, _ = _Design(d, [get_effect(n)]).matrices({}, bf.acc0_g)
            Xs = _baseline_design(d, bf)
            P = len(d.pos_labels)
            for i in range(3):
                Z = d.block_mean(mats[i][:, P + 2:])
                parts.append(_residualize(Xs[i], Z, d.block_count) if Z.shape[1] else Z)
        cols[n] = parts
    groups: list[list[str]] = []
    used: set[str] = set()
    for k, a in enumerate(lin):
        if a in used:
            continue
        g = [a]
        for b in lin[k + 1:]:
            if b in used:
                continue
            same = all(_span_residual(A, B) < ALIAS_REL and _span_residual(B, A) < ALIAS_REL
                       for A, B in zip(cols[a], cols[b]) if A.shape[1] and B.shape[1])
            if same:
                g.append(b)
                used.add(b)
        if len(g) > 1:
            groups.append(g)
            used.add(a)
    return groups


def _gate(cmp: Comparison, before: ModelEval, after: ModelEval) -> tuple[dict, bool]:
    gain = ((before.heldout_rms_mg - after.heldout_rms_mg) / before.heldout_rms_mg
            if before.heldout_rms_mg > 0 else 0.0)
    rec = {"effects": list(before.effects), "heldout_rms_mg": _r(after.heldout_rms_mg),
           "heldout_gain_rel": _r(gain), "delta_bic": _r(cmp.delta_bic, 2), "score": _r(cmp.lr, 3),
           "score_df": cmp.df, "score_p": float(f"{cmp.p:.3g}")}
    ok = bool(cmp.delta_bic < BIC_GATE and cmp.p < SCORE_P_GATE and gain >= HELDOUT_GAIN_GATE)
    return rec, ok


MASKED_PAIR_TOP = 3  # pairs among the 3 strongest in-sample candidates (3 extra fits at most)


def _masked_pair(data, rows: list[dict], admitted: list[str], partners: dict, current: ModelEval, get_eval):
    """Two effects of opposite sign can cancel on every held-out leg: each alone fits the training
    legs better (strong delta BIC) yet predicts the held-out legs worse, because it soaks up part of
    the other's signal with the wrong shape. When no single candidate passes the gate, the few
    candidates that are significant in sample but fail held-out are tried in pairs; a pair that
    passes the same gate (its dk counts both) is admitted together. Clean data rarely has even one
    such candidate, so this costs nothing there."""
    def vs_current(r):  # the candidate's comparison against exactly the current model, if made
        if not admitted:
            return r
        rec = r.get("given_admitted")
        return rec if rec and rec["effects"] == admitted else None

    pool = []
    for r in rows:
        if r["admitted"] or partners.get(r["effect"], set()) & set(admitted):
            continue
        rec = vs_current(r)
        if rec is None or rec.get("delta_bic") is None:
            continue
        if rec["delta_bic"] < BIC_GATE and rec["score_p"] < SCORE_P_GATE:
            pool.append((rec["delta_bic"], r["effect"]))
    pool = [n for _, n in sorted(pool)[:MASKED_PAIR_TOP]]
    best = None
    for i in range(len(pool)):
        for j in range(i + 1, len(pool)):
            a, b = pool[i], pool[j]
            if b in partners.get(a, set()):
                continue  # a confusable pair is one term, never two
            cand = get_eval(admitted + [a, b])
            rec, ok = _gate(compare(data, _spec(current), _spec(cand)), current, cand)
            if ok and (best is None or rec["delta_bic"] < best[2]["delta_bic"]):
                best = ((a, b), cand, rec)
    return best


def _admit_forward(data, base: ModelEval, rows: list[dict], confusable: list[dict], get_eval) -> tuple[list[str], list[dict]]:
    """Monotone forward staircase: at each step every candidate is gated against the model that holds
    exactly the effects admitted before it (no stand-ins); of those that pass, the one with the
    lowest delta BIC is admitted. A candidate
    with no evidence on its own (masked by an effect of opposite sign) is screened again against the
    current model (a cheap GLS test at its own nonlinear values) and, if significant, gated like the
    others. A confusable partner of an admitted effect is not tested on top of it."""
    admitted: list[str] = []
    steps: list[dict] = []
    current = base
    partners = {}
    for c in confusable:
        a, b = c["effects"]
        partners.setdefault(a, set()).add(b)
        partners.setdefault(b, set()).add(a)
    while True:
        passing = []
        for r in rows:
            name = r["effect"]
            if r["admitted"] or partners.get(name, set()) & set(admitted):
                continue
            if not admitted:
                if not r["evidence"]:
                    continue
                cand = get_eval([name])
                rec = {k: r[k] for k in ("heldout_rms_mg", "heldout_gain_rel", "delta_bic", "score", "score_df",
                                         "score_p")}
                rec["effects"] = []
            else:
                if not r["evidence"]:
                    screen = compare(data, _spec(current), _spec_plus(current, get_eval([name]), name))
                    if not (screen.p < SCORE_P_GATE and screen.delta_bic < BIC_GATE):
                        continue
                cand = get_eval(admitted + [name])
                rec, ok = _gate(compare(data, _spec(current), _spec(cand)), current, cand)
                r["given_admitted"] = rec
                if not ok:
                    continue
            passing.append((rec["delta_bic"], r, cand, rec))
        if not passing:
            pair = _masked_pair(data, rows, admitted, partners, current, get_eval)
            if pair is None:
                break
            (a, b), cand, rec = pair
            for name, other in ((a, b), (b, a)):
                r = next(x for x in rows if x["effect"] == name)
                admitted.append(name)
                r["admitted"] = True
                r["flags"] = [f for f in r["flags"] if f != "no_evidence"]
                r["flags"].append("masked:admitted_with:" + other)
                r["given_admitted"] = rec
            steps.append({**rec, "model": f"+{a} +{b}", "effects": list(admitted)})
            current = cand
            continue
        # of the candidates that pass, the strongest evidence goes in first (a transient or a term
        # held-out legs cannot fully show must not lose its place to one that soaks up part of it)
        _, r, cand, rec = min(passing, key=lambda x: x[0])
        name = r["effect"]
        admitted.append(name)
        r["admitted"] = True
        if admitted[:-1] and not r["evidence"]:
            r["flags"] = [f for f in r["flags"] if f != "no_evidence"]
            r["flags"].append("masked:evidence_given:" + ",".join(admitted[:-1]))
        steps.append({**rec, "model": "+" + name, "effects": list(admitted)})
        current = cand
    for r in rows:
        if r["admitted"]:
            continue
        adm_partner = partners.get(r["effect"], set()) & set(admitted)
        if adm_partner:
            r["flags"].append("stands_for_it:" + ",".join(sorted(adm_partner)))
        elif admitted and r["evidence"]:
            r["flags"].append("explained_by:" + ",".join(admitted))
    return admitted, steps


def diagnose(logs: list[DutLog] | list[str], add: list[str] | tuple = (), candidates: list[str] | None = None,
             effects_file: str | None = None, basis: str = "window", seg: Segmentation | None = None,
             ) -> DiagnosisReport:
    """Fit the baseline, rank candidate effects, refit with `add`; one DUT or a batch together.

    basis: "sample" (RMS of every sample's residual) or "window" (RMS of 1-minute means).
    """
    if effects_file:
        load_effects_file(effects_file)
    if not logs:
        raise StationError("no log given")
    logs = [read_log(x) if isinstance(x, str) else x for x in logs]
    seg = seg or Segmentation()
    add = list(dict.fromkeys(add or ()))
    for a in add:
        get_effect(a)
    if basis not in ("sample", "window"):
        raise StationError(f"unknown RMS basis {basis!r} (sample or window)")
    data = [prepare(lg, seg) for lg in logs]
    for d in data:
        span = float(np.max(d.temp_smooth_c) - np.min(d.temp_smooth_c))
        if span < MIN_TEMP_SPAN_C:
            raise StationError(f"{d.serial}: the temperature spans only {span:.1f} C; the thermal model needs "
                               f"at least {MIN_TEMP_SPAN_C:g} C (a ramp or temperature plateaus)")
        if d.block_starts.shape[0] < 20:
            raise StationError(f"{d.serial}: only {d.n} samples ({d.time_s[-1] - d.time_s[0]:.0f} s) in usable "
                               f"runs, too little data for held-out validation")
    names = list(candidates) if candidates is not None else list(REGISTRY)
    cache: dict[tuple, ModelEval] = {}

    def get_eval(effs: list[str]) -> ModelEval:
        key = tuple(effs)
        if key not in cache:
            cache[key] = evaluate(data, list(effs), basis, seg.n_folds)
        return cache[key]

    base = get_eval([])

    # identifiability first: a candidate the data cannot identify is not ranked
    unident, ident = [], []
    for name in names + [a for a in add if a not in names]:  # added effects are checked too
        rel = identifiability(data, base, name)
        if rel < UNIDENTIFIABLE_REL:
            e = get_effect(name)
            unident.append({"effect": name, "relative_residual_norm": _r(rel, 8),
                            "reason": "its regressors are a linear combination of the baseline's on this data",
                            "needs": e.needs, "test_to_identify": e.identify_hint})
        else:
            ident.append(name)
    ident = [n for n in ident if n in names]
    # aliases: identical regressors on this data are one term, ranked under the first name
    feats = data_features(data)
    aliases = []
    alias_of: dict[str, str] = {}
    for g in alias_groups(data, base, ident):
        why = "with one orientation" if feats["orientations"] == 1 else "on this data"
        term = TERMS.get(g[0], g[0])
        text = f"{term}: {g[0]}, same as {', '.join(g[1:])} {why}"
        aliases.append({"term": term, "effects": g, "ranked_as": g[0], "text": text,
                        "reason": "their regressors are identical on this data once the baseline is fitted"})
        for other in g[1:]:
            alias_of[other] = g[0]
    ranked = [n for n in ident if n not in alias_of]

    rows = []
    for name in ranked:
        cand = get_eval([name])
        cmp = compare(data, _spec(base), _spec(cand))
        gain = (base.heldout_rms_mg - cand.heldout_rms_mg) / base.heldout_rms_mg if base.heldout_rms_mg > 0 else 0.0
        row = {
            "effect": name,
            "heldout_rms_mg": _r(cand.heldout_rms_mg),
            "rms_mg": _r(cand.rms_mg),
            "heldout_gain_mg": _r(base.heldout_rms_mg - cand.heldout_rms_mg),
            "heldout_gain_rel": _r(gain),
            "delta_bic": _r(cmp.delta_bic, 2),
            "n_eff": cmp.n,
            "score": _r(cmp.lr, 3), "score_df": cmp.df, "score_p": float(f"{cmp.p:.3g}"),
            "predicted_rms_reduction_mg": _r(max(base.rms_mg - cand.rms_mg, 0.0)),
            "evidence": bool(cmp.delta_bic < BIC_GATE and cmp.p < SCORE_P_GATE and gain >= HELDOUT_GAIN_GATE),
            "admitted": False,
            "flags": [],
            "note": get_effect(name).note,
        }
        grp = next((a for a in aliases if a["ranked_as"] == name), None)
        if grp:
            row["term"] = grp["term"]
            row["aliases"] = grp["effects"][1:]
            row["same_as"] = grp["text"]
        rows.append(row)
    # confusable pairs among candidates with evidence
    contrib = {r["effect"]: _contribution(data, base, get_eval([r["effect"]])) for r in rows if r["evidence"]}
    confusable = []
    ev = [r["effect"] for r in rows if r["evidence"]]
    for a_i in range(len(ev)):
        for b_i in range(a_i + 1, len(ev)):
            a, b = ev[a_i], ev[b_i]
            c = _cos(contrib[a], contrib[b])
            ra = next(r for r in rows if r["effect"] == a)
            rb = next(r for r in rows if r["effect"] == b)
            if abs(c) > CONFUSABLE_COS and abs(ra["delta_bic"] - rb["delta_bic"]) < -BIC_GATE:
                confusable.append({"effects": [a, b], "cosine": _r(c, 4),
                                   "reason": "their fitted contributions are nearly collinear on this data",
                                   "to_separate": f"{get_effect(a).identify_hint}; {get_effect(b).identify_hint}"})
    # structural pairs: told apart only by a feature the data lacks (lag vs hysteresis: ramp rates)
    by_name = {r["effect"]: r for r in rows}
    for a in by_name:
        for b, feature in getattr(get_effect(a), "confusable_with", {}).items():
            if b not in by_name or feats.get(feature, True):
                continue
            if not (by_name[a]["evidence"] or by_name[b]["evidence"]):
                continue
            if any(set(c["effects"]) == {a, b} for c in confusable):
                continue
            confusable.append({
                "effects": [a, b], "cosine": _r(_cos(_contribution(data, base, get_eval([a])),
                                                     _contribution(data, base, get_eval([b]))), 4),
                "reason": (f"the data lack {FEATURE_TEXT.get(feature, feature)}, the test that separates them "
                           f"(held-out {by_name[a]['heldout_rms_mg']} vs {by_name[b]['heldout_rms_mg']} mg: any "
                           f"difference rests on the exact parametric shapes, not on the physics that tells them apart)"),
                "to_separate": "; ".join(dict.fromkeys([get_effect(a).identify_hint, get_effect(b).identify_hint]))})
    conf_names = {n for pair in confusable for n in pair["effects"]}
    for r in rows:
        if r["effect"] in conf_names:
            others = [x for pair in confusable if r["effect"] in pair["effects"] for x in pair["effects"] if x != r["effect"]]
            r["flags"].append("confusable_with:" + ",".join(sorted(set(others))))
        if not r["evidence"]:
            r["flags"].append("no_evidence")
    rows.sort(key=lambda r: (r["heldout_rms_mg"] if r["heldout_rms_mg"] is not None else 1e300))
    admitted, auto_steps = _admit_forward(data, base, rows, confusable, get_eval)

    # --add: error staircase
    def step_json(model: str, m: ModelEval) -> dict:
        return {"model": model, "effects": list(m.effects), "rms_mg": _r(m.rms_mg),
                "heldout_rms_mg": _r(m.heldout_rms_mg), "rms_per_sample_mg": _r(m.rms_sample_mg),
                "heldout_rms_per_sample_mg": _r(m.heldout_rms_sample_mg)}

    staircase = [step_json("baseline", base)]
    current = base
    for k in range(len(add)):
        effs = add[: k + 1]
        current = get_eval(effs)
        step = {**step_json("+" + effs[-1], current), "parameters": _params_json(data, current.fits)}
        warn = [u for u in unident if u["effect"] == effs[-1]]
        if warn:
            step["warning"] = (f"{effs[-1]} is not identifiable from this data (its parameters are arbitrary); "
                               f"{warn[0]['test_to_identify']}")
        if effs[-1] in alias_of:
            step["warning"] = (f"{effs[-1]} has the same regressor as {alias_of[effs[-1]]} on this data "
                               f"({next(a['text'] for a in aliases if effs[-1] in a['effects'])})")
        staircase.append(step)
    admitted_staircase = [step_json("baseline", base)] + [
        {**step_json(s_["model"], get_eval(s_["effects"])), "delta_bic": s_["delta_bic"], "score_p": s_["score_p"]}
        for s_ in auto_steps]
    base_noise = compare(data, _spec(base), _spec(base)).noise
    n_seg = [int(d.seg_bounds_s.shape[0]) for d in data]
    noise_model = {
        "residual": ("local level (bias random walk + white, IMA(1,1)) + AR(p <= 6 by BIC) of the 10 s block "
                     "means of the residual, per DUT and axis within constant-orientation runs, estimated on the "
                     "larger model of each comparison; p-values, delta BIC and parameter sigmas come from the "
                     "prewhitened (GLS) fits"),
        "baseline": base_noise,
        "heldout": (f"whole thermal legs ({', '.join(map(str, n_seg))} per DUT) in "
                    f"{', '.join(str(d.n_folds) for d in data)} folds, {seg.guard_s:g} s guard on each side"),
    }
    drift = {"tdsf_identifiable": drift_identifiability(data, base), "test_to_identify": TDSF_TEST}
    return DiagnosisReport(
        serials=[d.serial for d in data], rms_basis="per sample" if basis == "sample" else "1-minute means",
        baseline=base, ranking=rows, model=current, staircase=staircase, confusable=confusable,
        unidentifiable=unident, parameters=_params_json(data, current.fits), features=feats, data=data,
        candidates={k[0]: v for k, v in cache.items() if len(k) == 1},
        admitted=admitted, admitted_staircase=admitted_staircase, aliases=aliases, noise_model=noise_model,
        drift=drift, baseline_parameters=_params_json(data, base.fits))


__all__ = ["diagnose", "DiagnosisReport", "ModelEval", "evaluate", "compare", "ar_fit", "whiten", "tau_int",
           "BUILTIN_NAMES"]
