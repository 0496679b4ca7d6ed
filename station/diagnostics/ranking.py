"""Rank candidate effects against the baseline, admit the ones the data supports, refit (design 7).

Statistics, for one DUT or a batch (sums over DUTs: each DUT has its own parameters, the effect
structure is shared):

- held-out RMS: blocked K-fold. Every constant-orientation run is cut into contiguous chunks
  (default 10 min) assigned to K = 5 folds in turn; each chunk is predicted by a fit that never saw
  it. Samples are autocorrelated, so nothing is ever split at random.
- effective sample count: residual block means (10 s) are autocorrelated; per axis and DUT,
  n_eff = n_blocks / tau_int with tau_int = 1 + 2 sum rho_k (Sokal's automatic window).
- score (Lagrange multiplier) test of the candidate's regressors against the baseline residual,
  with the score's variance from chunk sums (cluster-robust, so autocorrelation within a chunk is
  accounted for): LM = s' V^-1 s ~ chi2(df). Nonlinear parameters are set to the candidate's fit.
- delta BIC = sum_axes n_eff ln(SSR_cand / SSR_base) + dk ln(N_eff): the usual BIC with the
  effective count in place of the sample count, so 30 000 autocorrelated samples do not pretend to
  be 30 000 independent ones (which would admit anything).
- admission gate: delta BIC < -10 (strong evidence) and held-out RMS lower by >= 3 % and
  the score test p < 0.001. Data with no missing effect admits nothing.
- unidentifiable: a candidate whose regressors are (numerically) a linear combination of the
  baseline's (relative residual norm < 1e-3, variance inflation > 1e6), e.g. cross_axis or
  scale_nonlinearity from two orientations; reported with the test that would identify it.
- confusable: two candidates that both pass the evidence test and whose fitted contributions are
  nearly collinear (|cos| > 0.9 after the baseline is projected out); and structural pairs that
  only a data feature separates (Effect.confusable_with: thermal_lag and hysteresis need >= 2
  distinct ramp rates, since a lag scales with the rate and hysteresis does not) when the data
  lack it and either has evidence. Both are flagged and neither is admitted automatically.
- forward admission: the best candidate with evidence is admitted; each further one must pass the
  same gate against the model holding the ones before it (a confusable pair's best member stands
  in for the pair), so an effect that only soaks up part of another is "explained_by" it. A
  candidate with no evidence of its own (masked by an effect of opposite sign) is score-tested
  again against the model holding the admitted ones and, if significant, refitted and gated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2

from station.diagnostics.effects import BUILTIN_NAMES, REGISTRY, get_effect, load_effects_file
from station.diagnostics.model import (
    DiagnosticModel, DutData, DutFit, Segmentation, _tau_int, fit_dut, heldout_residual, predict_dut, prepare,
    window_rms,
)
from station.logfile import DutLog, read_log
from station.types import AXES, StationError

BIC_GATE = -10.0
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


def score_test(data, base: ModelEval, cand: ModelEval):
    """Cluster-robust LM statistic, df, p-value, and the one-step predicted SSR fraction removed."""
    lm_total, df_total, proj_total, ssr_total = 0.0, 0, 0.0, 0.0
    for d, bf, cf, r in zip(data, base.fits, cand.fits, base.resid):
        Xs = _baseline_design(d, bf)
        Zs = candidate_regressors(d, bf, cf)
        rb = block_resid(d, r)
        w = d.block_count
        for i in range(3):
            Z = Zs[i]
            keep = np.any(Z != 0, axis=0)
            Z = Z[:, keep]
            if Z.shape[1] == 0:
                continue
            Zt = _residualize(Xs[i], Z, w)
            e = rb[:, i]
            s_blocks = Zt * (w * e)[:, None]
            s = s_blocks.sum(axis=0)
            # cluster sums over held-out chunks (each ~10 min): robust to autocorrelation inside
            clusters = d.block_chunk
            uc, inv = np.unique(clusters, return_inverse=True)
            S = np.zeros((uc.size, Z.shape[1]))
            np.add.at(S, inv, s_blocks)
            # cluster-robust variance needs the regressor spread over many clusters; a transient
            # confined to a few chunks (self_heating) gets the autocorrelation-inflated model-based
            # variance instead: Var(w_b e_b) = sigma^2 w_b for block means, sigma^2 = mean(w e^2)
            energy = np.bincount(inv, weights=np.sum(w[:, None] * Zt * Zt, axis=1))
            n_clusters_eff = energy.sum() ** 2 / max(float(np.sum(energy**2)), 1e-300)
            if n_clusters_eff >= max(10.0, 4.0 * Z.shape[1]):
                V = S.T @ S
            else:
                V = (np.sum(w * e * e) / w.size) * ((Zt.T * w) @ Zt) * tau_int(e)
            lm = float(s @ np.linalg.pinv(V) @ s)
            lm_total += lm
            df_total += Z.shape[1]
            G = (Zt.T * w) @ Zt
            proj_total += float(s @ np.linalg.pinv(G) @ s)
            ssr_total += float(np.sum(w * e * e))
    p = float(chi2.sf(lm_total, df_total)) if df_total else 1.0
    frac = proj_total / ssr_total if ssr_total > 0 else 0.0
    return lm_total, df_total, p, min(max(frac, 0.0), 1.0)


def delta_bic(data, base: ModelEval, cand: ModelEval) -> tuple[float, float]:
    """BIC(candidate) - BIC(baseline) with effective sample counts (see module doc)."""
    ll = 0.0
    n_eff_total = 0.0
    for d, rb_, rc in zip(data, base.resid, cand.resid):
        neff = n_eff_axes(d, rc)
        sb = _ssr_block(d, rb_)
        sc = _ssr_block(d, rc)
        ll += float(np.sum(neff * np.log(np.maximum(sc, 1e-300) / np.maximum(sb, 1e-300))))
        n_eff_total += float(neff.sum())
    dk = cand.n_params - base.n_params
    return ll + dk * math.log(max(n_eff_total, 2.0)), n_eff_total


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


def _params_json(data: list[DutData], fits: list[DutFit]) -> dict:
    """Fitted parameters with 1-sigma uncertainties in physical units, per DUT."""
    out = {}
    for d, f in zip(data, fits):
        dut: dict = {"baseline": {}, "effects": {}}
        for i, ax in enumerate(AXES):
            for name, b, s in zip(f.col_names[i], f.beta[i], f.beta_sigma[i]):
                entry = {"value": _sig(b), "sigma": _sig(s, 3)}
                if "." in name:
                    eff, pname = name.split(".", 1)
                    if s == 0 and b == 0:
                        continue
                    dut["effects"].setdefault(eff, {}).setdefault(pname, {})[ax] = entry
                else:
                    dut["baseline"].setdefault(name, {})[ax] = entry
        for eff, vals in f.nl.items():
            for pname, v in vals.items():
                dut["effects"].setdefault(eff, {})[pname] = {
                    "value": _sig(v), "sigma": _sig(f.nl_sigma.get(eff, {}).get(pname, float("nan")), 3)}
        out[d.serial] = dut
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



def _gate_given(data, current: ModelEval, cond: list[str], name: str, basis: str, n_folds: int):
    """Refit with `name` added to the admitted effects `cond` and put it through the admission gate
    (information criterion, score test, held-out gain). Returns (eval, record, passed)."""
    cand = evaluate(data, cond + [name], basis, n_folds)
    _, _, p, _ = score_test(data, current, cand)
    dbic, _ = delta_bic(data, current, cand)
    gain = ((current.heldout_rms_mg - cand.heldout_rms_mg) / current.heldout_rms_mg
            if current.heldout_rms_mg > 0 else 0.0)
    record = {"effects": list(cond), "heldout_rms_mg": _r(cand.heldout_rms_mg), "delta_bic": _r(dbic, 2),
              "score_p": float(f"{p:.3g}"), "heldout_gain_rel": _r(gain)}
    return cand, record, bool(dbic < BIC_GATE and p < SCORE_P_GATE and gain >= HELDOUT_GAIN_GATE)

def _admit_forward(data, base: ModelEval, rows: list[dict], evals: dict, conf_names: set, basis: str,
                   n_folds: int) -> list[str]:
    """Forward admission: the best candidate with evidence is admitted; every further one must pass
    the same gate against the model that already holds the admitted ones (so a candidate that only
    soaks up part of an admitted effect, e.g. bias_t3 beside a true bias_t2, is not admitted)."""
    admitted: list[str] = []
    cond: list[str] = []  # effects in the model every further candidate is tested against
    current = base
    for r in rows:
        name = r["effect"]
        if not r["evidence"]:
            continue
        if name in conf_names:
            # not admitted, but its best-ranked member stands in for the pair while the others are
            # tested, so that a third effect does not get admitted for soaking up the pair's signal
            if not any(c in conf_names for c in cond):
                if not cond:
                    current = evals[name]
                else:
                    current = evaluate(data, cond + [name], basis, n_folds)
                cond.append(name)
            continue
        if not cond:
            admitted.append(name)
            cond.append(name)
            current = evals[name]
            r["admitted"] = True
            continue
        cand, r["given_admitted"], passed = _gate_given(data, current, cond, name, basis, n_folds)
        if passed:
            admitted.append(name)
            cond.append(name)
            current = cand
            r["admitted"] = True
        else:
            r["flags"].append("explained_by:" + ",".join(cond))
    # Masking: two effects of opposite sign can hide each other, so a candidate with no evidence on
    # its own is score-tested again against the current model (cheap); only if that is significant
    # is it refitted with the admitted ones and put through the same gate.
    changed = bool(cond)
    while changed:
        changed = False
        for r in rows:
            name = r["effect"]
            if r["evidence"] or r["admitted"] or name in conf_names or name in cond or r.get("given_admitted"):
                continue
            _, _, p0, _ = score_test(data, current, evals[name])
            if not p0 < SCORE_P_GATE:
                continue
            cand, r["given_admitted"], passed = _gate_given(data, current, cond, name, basis, n_folds)
            if passed:
                admitted.append(name)
                cond.append(name)
                current = cand
                r["admitted"] = True
                r["flags"] = [f for f in r["flags"] if f != "no_evidence"] + ["masked:evidence_given:" + ",".join(cond[:-1])]
                changed = True
                break
    return admitted


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
        if d.block_starts.shape[0] < 4 * seg.n_folds:
            raise StationError(f"{d.serial}: only {d.n} samples ({d.time_s[-1] - d.time_s[0]:.0f} s) in usable "
                               f"runs, too little data for held-out validation")
    names = list(candidates) if candidates is not None else list(REGISTRY)
    base = evaluate(data, [], basis, seg.n_folds)

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

    evals: dict[str, ModelEval] = {}
    rows = []
    ident = [n for n in ident if n in names]
    for name in ident:
        cand = evaluate(data, [name], basis, seg.n_folds)
        evals[name] = cand
        lm, df, p, frac = score_test(data, base, cand)
        dbic, neff = delta_bic(data, base, cand)
        gain = (base.heldout_rms_mg - cand.heldout_rms_mg) / base.heldout_rms_mg if base.heldout_rms_mg > 0 else 0.0
        rows.append({
            "effect": name,
            "heldout_rms_mg": _r(cand.heldout_rms_mg),
            "rms_mg": _r(cand.rms_mg),
            "heldout_gain_mg": _r(base.heldout_rms_mg - cand.heldout_rms_mg),
            "heldout_gain_rel": _r(gain),
            "delta_bic": _r(dbic, 2),
            "n_eff": _r(neff, 1),
            "score": _r(lm, 3), "score_df": df, "score_p": float(f"{p:.3g}"),
            "predicted_rms_reduction_mg": _r(base.rms_mg * (1.0 - math.sqrt(1.0 - frac))),
            "evidence": bool(dbic < BIC_GATE and p < SCORE_P_GATE and gain >= HELDOUT_GAIN_GATE),
            "admitted": False,
            "flags": [],
            "note": get_effect(name).note,
        })
    # confusable pairs among candidates with evidence
    contrib = {r["effect"]: _contribution(data, base, evals[r["effect"]]) for r in rows if r["evidence"]}
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
    feats = data_features(data)
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
                "effects": [a, b], "cosine": _r(_cos(_contribution(data, base, evals[a]),
                                                     _contribution(data, base, evals[b])), 4),
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
    _admit_forward(data, base, rows, evals, conf_names, basis, seg.n_folds)

    # --add: error staircase
    staircase = [{"model": "baseline", "effects": [], "rms_mg": _r(base.rms_mg),
                  "heldout_rms_mg": _r(base.heldout_rms_mg), "rms_per_sample_mg": _r(base.rms_sample_mg),
                  "heldout_rms_per_sample_mg": _r(base.heldout_rms_sample_mg)}]
    current = base
    for k in range(len(add)):
        effs = add[: k + 1]
        if len(effs) == 1 and effs[0] in evals:
            current = evals[effs[0]]
        else:
            current = evaluate(data, effs, basis, seg.n_folds)
        step = {"model": "+" + effs[-1], "effects": list(effs), "rms_mg": _r(current.rms_mg),
                "heldout_rms_mg": _r(current.heldout_rms_mg),
                "rms_per_sample_mg": _r(current.rms_sample_mg),
                "heldout_rms_per_sample_mg": _r(current.heldout_rms_sample_mg),
                "parameters": _params_json(data, current.fits)}
        warn = [u for u in unident if u["effect"] == effs[-1]]
        if warn:
            step["warning"] = (f"{effs[-1]} is not identifiable from this data (its parameters are arbitrary); "
                               f"{warn[0]['test_to_identify']}")
        staircase.append(step)
    return DiagnosisReport(
        serials=[d.serial for d in data], rms_basis="per sample" if basis == "sample" else "1-minute means",
        baseline=base, ranking=rows, model=current, staircase=staircase, confusable=confusable,
        unidentifiable=unident, parameters=_params_json(data, current.fits), features=feats, data=data,
        candidates=evals)


__all__ = ["diagnose", "DiagnosisReport", "ModelEval", "evaluate", "score_test", "delta_bic", "tau_int",
           "BUILTIN_NAMES"]
