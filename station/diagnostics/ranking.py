"""Rank candidate effects against the baseline, admit the ones the data supports, refit (design 7).

Statistics, for one DUT or a batch (sums over DUTs: each DUT has its own parameters, the effect
structure is shared). Real MEMS parts have a wandering bias (random walk, flicker), so the residual
of a perfect model is not white and its minutes are not independent; every figure accounts for it:

- held-out RMS: blocked K-fold over whole thermal legs (a heating or cooling ramp with its hold,
  i.e. a profile step; segmentation.Segmentation), each predicted by a fit that saw neither the leg nor a
  guard of 10 min on each side of it. Never short interleaved chunks, never at random.
- noise model of the residual: AR(p) (p <= 6 by BIC) of the 10 s block means, per DUT and axis over
  the whole log (levels carry across orientation changes), estimated on the residual of the larger model of each
  comparison (so an effect missing from the smaller model is not mistaken for noise). A bias
  random walk shows up as phi ~ 1; the AR filter prewhitens data and regressors (GLS).
- likelihood-ratio test (reported as score / score_p): LR = sum n ln(SSR_small / SSR_big) of the
  prewhitened GLS fits ~ chi2(dk), dk = extra linear and nonlinear parameters.
- delta BIC = sum n ln(SSR_big / SSR_small) + dk ln(N), N = prewhitened block count.
- uncertainties: GLS covariance sigma^2 (X~' X~)^-1 of the prewhitened fit.
- admission gate (model before -> model with the effect): LR p < 0.001, held-out RMS lower by
  >= 3 %, the held-out legs agree (those predicted worse lose at most half of
  what the better ones gain) and no nonlinear parameter at its bound (gate.py). The forward staircase gates every candidate against the model
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

This module is the entry point (diagnose, DiagnosisReport); the parts live beside it:
segmentation.py (blocks, windows, held-out legs), design.py and fit.py (the fit), evaluation.py (a
model structure over all DUTs), noise_gls.py (noise model, prewhitened GLS, LR and delta BIC),
identifiability.py (unidentifiable, aliases, confusable, data features), gate.py (admission gate,
masked pairs), staircase.py (forward staircase), report_values.py (rounding, parameter table) and
model.py (the saved model).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from station.diagnostics.effects import REGISTRY, get_effect, load_effects_file
from station.diagnostics.evaluation import ModelEval, _spec, evaluate
from station.diagnostics.gate import EVIDENCE_TIE, _gate, at_bound, why_not
from station.diagnostics.identifiability import (
    CONFUSABLE_COS, FEATURE_TEXT, TERMS, UNIDENTIFIABLE_REL, _contribution, _cos, alias_groups, data_features,
    drift_identifiability, identifiability,
)
from station.diagnostics.leftover import leftover
from station.diagnostics.model import DiagnosticModel
from station.diagnostics.noise_gls import compare
from station.diagnostics.noise_view import noise_view
from station.diagnostics.report_values import TDSF_TEST, _params_json, _r
from station.diagnostics.segmentation import DutData, Segmentation, prepare
from station.diagnostics.staircase import _admit_forward
from contracts.logfile import DutLog, read_log
from contracts.types import StationError

MIN_TEMP_SPAN_C = 3.0


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
    leftover: dict = field(default_factory=dict)
    candidates: dict[str, ModelEval] = field(repr=False, default_factory=dict)
    ranked: "Ranked | None" = field(repr=False, default=None)
    _noise: dict = field(repr=False, default_factory=dict)

    def noise(self, k: int = 0) -> dict:
        """DUT k's noise view (noise_view.noise_view), computed once per report: the CLI's text and
        JSON, the web JSON and the Allan plot all read it."""
        if k not in self._noise:
            self._noise[k] = noise_view(self, k)
        return self._noise[k]

    def to_json(self) -> dict:
        return {
            "serials": self.serials,
            "leftover": self.leftover,
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



@dataclass
class Ranked:
    """Everything `--add` does not change: the prepared logs, the ranking, the admitted staircase and
    every model fitted so far (so adding effects refits only the new structures)."""

    data: list[DutData]
    seg: Segmentation
    basis: str
    cache: dict
    base: ModelEval
    rows: list[dict]
    confusable: list[dict]
    unident: list[dict]
    aliases: list[dict]
    alias_of: dict
    feats: dict
    admitted: list[str]
    auto_steps: list[dict]
    noise_model: dict = field(default_factory=dict)
    drift: dict = field(default_factory=dict)
    leftovers: dict = field(default_factory=dict)  # effects tuple -> leftover JSON

    def leftover(self, effs: list[str]) -> dict:
        """The honest leftover of a model (leftover.py), computed once per effect list."""
        key = tuple(effs)
        if key not in self.leftovers:
            m = self.get_eval(list(effs))
            doc = leftover(self.data, m.fits, m.heldout_block, list(effs))
            if doc["above_floor"] and list(effs) == self.admitted:
                doc["statement"] += " No other candidate in the library passed the gate on top of it."
            self.leftovers[key] = doc
        return self.leftovers[key]

    def get_eval(self, effs: list[str]) -> ModelEval:
        key = tuple(effs)
        if key not in self.cache:
            # effects already fitted in the model one step smaller start where that fit ended
            prefix = self.cache.get(key[:-1]) if len(key) > 1 else None
            start = [f.nl for f in prefix.fits] if prefix is not None else None
            self.cache[key] = evaluate(self.data, list(effs), self.basis, self.seg.n_folds, nl_start=start)
        return self.cache[key]


_RANKED: "OrderedDict[tuple, Ranked]" = OrderedDict()
RANKED_CACHE_SIZE = 4  # logs whose ranking is kept for --add (a 10 h log: ~20 MB each)


def _log_key(logs: list[DutLog], names: list[str], basis: str, seg: Segmentation) -> tuple:
    """The log content (hash of every array) and the model question asked of it."""
    h = hashlib.sha256()
    for lg in logs:
        for arr in (lg.time_s, lg.acc_g, lg.temp_c, lg.position, lg.lamp):
            if arr is not None:
                h.update(np.ascontiguousarray(arr))  # the array's bytes, without a copy of them
        h.update(repr(sorted((k, str(v)) for k, v in lg.meta.items())).encode())
    effs = tuple((n, type(REGISTRY[n]).__qualname__, id(REGISTRY[n])) for n in names)
    return h.hexdigest(), effs, basis, repr(seg)


def diagnose(logs: list[DutLog] | list[str], add: list[str] | tuple = (), candidates: list[str] | None = None,
             effects_file: str | None = None, basis: str = "window", seg: Segmentation | None = None,
             consume_logs: bool = False) -> DiagnosisReport:
    """Fit the baseline, rank candidate effects, refit with `add`; one DUT or a batch together.

    basis: "sample" (RMS of every sample's residual) or "window" (RMS of 1-minute means).
    The ranked state of the last few logs is kept in memory (keyed by the logs' content and the
    candidate set), so asking again with other `add` effects refits only the new models.
    consume_logs: the logs' arrays may be overwritten while they are prepared (segmentation.prepare
    consume): `station diagnose` reads them for this call alone, and a long log then costs no second
    copy of itself. The logs are not to be used afterwards.
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
    names = list(candidates) if candidates is not None else list(REGISTRY)
    key = _log_key(logs, names, basis, seg)
    ranked = _RANKED.get(key)
    if ranked is None:
        from station.diagnostics import disk_cache  # an earlier `station diagnose` run's ranking (off by default)

        ranked = disk_cache.load(logs, names, basis, seg, Ranked)
        if ranked is None:
            ranked = _rank(logs, names, basis, seg, consume_logs)
            disk_cache.store(ranked, logs, names, basis, seg)
        _RANKED[key] = ranked
        while len(_RANKED) > RANKED_CACHE_SIZE:
            _RANKED.popitem(last=False)
    else:
        _RANKED.move_to_end(key)
    return _report(ranked, add)


def with_added(report: DiagnosisReport, add: list[str]) -> DiagnosisReport:
    """The same diagnosis with other effects added (the engineer's click): only new models are fitted."""
    for a in add:
        get_effect(a)
    return _report(report.ranked, list(dict.fromkeys(add)))


def _rank(logs: list[DutLog], names: list[str], basis: str, seg: Segmentation, consume: bool = False) -> Ranked:
    data = [prepare(lg, seg, consume) for lg in logs]
    for d in data:
        ts = d.temp_smooth_c
        span = float(np.max(ts) - np.min(ts))
        if span < MIN_TEMP_SPAN_C:
            raise StationError(f"{d.serial}: the temperature spans only {span:.1f} C; the thermal model needs "
                               f"at least {MIN_TEMP_SPAN_C:g} C (a ramp or temperature plateaus)")
        if d.block_starts.shape[0] < 20:
            raise StationError(f"{d.serial}: only {d.n} samples ({d.time_s[-1] - d.time_s[0]:.0f} s) in usable "
                               f"runs, too little data for held-out validation")
    st = Ranked(data=data, seg=seg, basis=basis, cache={}, base=None, rows=[], confusable=[], unident=[],  # type: ignore[arg-type]
                aliases=[], alias_of={}, feats={}, admitted=[], auto_steps=[])
    get_eval = st.get_eval
    base = st.base = get_eval([])

    # identifiability first: a candidate the data cannot identify is not ranked
    unident, ident = [], []
    for name in names:
        rel = identifiability(data, base, name)
        if rel < UNIDENTIFIABLE_REL:
            e = get_effect(name)
            unident.append({"effect": name, "relative_residual_norm": _r(rel, 8),
                            "reason": "its regressors are a linear combination of the baseline's on this data",
                            "needs": e.needs, "test_to_identify": e.identify_hint})
        else:
            ident.append(name)
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
        gate_rec, passes = _gate(cmp, base, cand)
        bound = at_bound(name, cand)
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
            "legs_better": gate_rec["legs_better"], "legs": gate_rec["legs"],
            "heldout_loss_share": gate_rec["heldout_loss_share"], "legs_p": gate_rec["legs_p"],
            "evidence": passes and not bound,
            "admitted": False,
            "flags": ["at_bound:" + "; ".join(bound)] if bound else [],
            "note": get_effect(name).note,
            "shape": _shape_text(name, cand),
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
            if abs(c) > CONFUSABLE_COS and abs(ra["delta_bic"] - rb["delta_bic"]) < EVIDENCE_TIE:
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

    for r in rows:
        if not r["admitted"]:
            r["why"] = why_not(r, _r(base.heldout_rms_mg))
    st.rows, st.confusable, st.unident, st.aliases, st.alias_of, st.feats = rows, confusable, unident, aliases, alias_of, feats
    st.admitted, st.auto_steps = admitted, auto_steps
    base_noise = compare(data, _spec(base), _spec(base)).noise
    n_seg = [int(d.seg_bounds_s.shape[0]) for d in data]
    noise_model = {
        "residual": ("local level (bias random walk + white, IMA(1,1)) + AR(p <= 6 by BIC) of the 10 s block "
                     "means of the residual, per DUT and axis over the whole log (the plate's moves are gaps, not "
                     "restarts: levels carry across orientation changes), estimated on the "
                     "larger model of each comparison; p-values, delta BIC and parameter sigmas come from the "
                     "prewhitened (GLS) fits"),
        "baseline": base_noise,
        "heldout": (f"whole thermal legs ({', '.join(map(str, n_seg))} per DUT) in "
                    f"{', '.join(str(d.n_folds) for d in data)} folds, {seg.guard_s:g} s guard on each side"),
    }
    drift = {"tdsf_identifiable": drift_identifiability(data, base), "test_to_identify": TDSF_TEST}
    st.noise_model, st.drift = noise_model, drift
    return st


def _shape_text(name: str, m: ModelEval) -> str:
    """The fitted shape of an effect in words (per DUT when a batch's DUTs differ)."""
    eff = get_effect(name)
    per_dut = [eff.shape(f.nl.get(name, {})) for f in m.fits]
    if len(set(per_dut)) == 1:
        return per_dut[0]
    return "; ".join(f"{d.serial}: {s_}" for d, s_ in zip(m.data, per_dut))


def _report(st: Ranked, add: list[str]) -> DiagnosisReport:
    data, base, get_eval = st.data, st.base, st.get_eval
    unident, aliases, alias_of = list(st.unident), st.aliases, st.alias_of
    for a in add:  # added effects are checked too
        if a not in {u["effect"] for u in unident} and not any(r["effect"] == a for r in st.rows) \
                and a not in alias_of and identifiability(data, base, a) < UNIDENTIFIABLE_REL:
            e = get_effect(a)
            unident.append({"effect": a, "relative_residual_norm": None,
                            "reason": "its regressors are a linear combination of the baseline's on this data",
                            "needs": e.needs, "test_to_identify": e.identify_hint})

    def step_json(model: str, m: ModelEval) -> dict:
        return {"model": model, "effects": list(m.effects), "rms_mg": _r(m.rms_mg),
                "heldout_rms_mg": _r(m.heldout_rms_mg), "rms_per_sample_mg": _r(m.rms_sample_mg),
                "heldout_rms_per_sample_mg": _r(m.heldout_rms_sample_mg)}

    base.with_sigma()
    staircase = [step_json("baseline", base)]
    current = base
    for k in range(len(add)):
        effs = add[: k + 1]
        current = get_eval(effs).with_sigma()
        step = {**step_json("+" + effs[-1], current), "parameters": _params_json(data, current.fits),
                "shape": _shape_text(effs[-1], current)}
        warn = [u for u in unident if u["effect"] == effs[-1]]
        if warn:
            step["warning"] = (f"{effs[-1]} is not identifiable from this data (its parameters are arbitrary); "
                               f"{warn[0]['test_to_identify']}")
        if effs[-1] in alias_of:
            step["warning"] = (f"{effs[-1]} has the same regressor as {alias_of[effs[-1]]} on this data "
                               f"({next(a['text'] for a in aliases if effs[-1] in a['effects'])})")
        staircase.append(step)
    admitted_staircase = [step_json("baseline", base)] + [
        {**step_json(s_["model"], get_eval(s_["effects"])), "delta_bic": s_["delta_bic"], "score_p": s_["score_p"],
         "shape": _shape_text(s_["effects"][-1], get_eval(s_["effects"]))}
        for s_ in st.auto_steps]
    return DiagnosisReport(
        serials=[d.serial for d in data], rms_basis="per sample" if st.basis == "sample" else "1-minute means",
        baseline=base, ranking=st.rows, model=current, staircase=staircase, confusable=st.confusable,
        unidentifiable=unident, parameters=_params_json(data, current.fits), features=st.feats, data=data,
        candidates={k[0]: v for k, v in st.cache.items() if len(k) == 1},
        admitted=st.admitted, admitted_staircase=admitted_staircase, aliases=aliases, noise_model=st.noise_model,
        drift=st.drift, baseline_parameters=_params_json(data, base.fits), ranked=st,
        leftover=st.leftover(add if add else st.admitted))


__all__ = ["diagnose", "with_added", "DiagnosisReport", "Ranked"]
