"""The admission gate: does adding an effect to a model earn its place?

Why a module of its own: the same tests (likelihood-ratio p-value under the correlated-noise model,
held-out gain, the held-out legs' agreement, no parameter at its bound; delta BIC only for a log of
few legs) decide whether a candidate has evidence against the baseline and whether it is admitted on
top of the effects already in; keeping them and the gate together means the ranking, the forward
staircase and the masked-pair rule cannot drift apart. The masked-pair rule lives here too: two
effects of opposite sign that hide each other held out are gated, and admitted, together.
"""

from __future__ import annotations

import math

import numpy as np

from station.diagnostics.effects import get_effect
from station.diagnostics.evaluation import ModelEval, _spec
from station.diagnostics.fit import SHAPE_MARGIN
from station.diagnostics.noise_gls import Comparison, compare
from station.diagnostics.report_values import _r

# The gate (issue 38): the in-sample evidence under the correlated-noise model (LR p), the held-out
# gain, and the held-out legs' agreement. Delta BIC is reported, no longer a gate: its ln(N) charge
# per parameter refused effects whose held-out error fell 14 % on 17 of 18 legs with LR p 6e-8 (a
# saturating drift in time, 5 parameters), while the legs' agreement is what keeps a term fitted to
# the noise out (benchmarks/diagnostics_fdr.py: the false discoveries on clean logs).
EVIDENCE_TIE = SHAPE_MARGIN  # two candidates whose delta BIC differ by less than this: equally strong in sample
HELDOUT_GAIN_GATE = 0.03
SCORE_P_GATE = 1e-3
LOSS_SHARE_GATE = 0.5  # the legs predicted worse may lose at most half of what the better ones gain
LOCAL_LOSS_SHARE = 0.1  # ... or, for a local effect, the others lose < 10 % of what it gains
MIN_LEGS = 8  # fewer held-out legs (a 90-minute log has 6) cannot show agreement on their own ...
FEW_LEGS_BIC_GATE = -SHAPE_MARGIN  # ... so the in-sample information criterion must agree too (-30)
LEGS_P_GATE = 0.02  # sign-flip p of the legs' gains: not the noise of a few legs
SIGN_FLIP_DRAWS = 20000  # random sign assignments beyond 16 legs (a fixed seed) ...
SIGN_FLIP_BATCH = 2000  # ... drawn this many at a time


def sign_flip_p(diff: np.ndarray) -> float:
    """One-sided sign-flip test of sum(diff) > 0: the share of sign assignments whose sum reaches
    the observed one. Under "the term fits the noise" a leg is as likely to be predicted worse as
    better by the same amount (the legs' common noise cancels in the difference of two models on the
    same leg), so the legs' gains are exchangeable in sign. Exact up to 16 legs, else 20 000 draws
    with a fixed seed (the same answer every run). A few legs can never make it small: 5 legs give
    at best 1/32."""
    d = np.asarray(diff, float)
    d = d[d != 0]
    n = d.size
    if n == 0 or d.sum() <= 0:
        return 1.0
    obs = d.sum()
    if n <= 16:
        signs = 1 - 2 * ((np.arange(2**n)[:, None] >> np.arange(n)[None, :]) & 1)
        return float(np.mean(signs @ d >= obs - 1e-12 * abs(obs)))
    # the 20 000 draws a batch at a time (the same stream of draws: a long log has hundreds of legs,
    # and all draws at once were 20 000 x legs x 17 bytes, 120 MB on a 200 MB log)
    rng = np.random.default_rng(0)
    hits = 0
    for _ in range(SIGN_FLIP_DRAWS // SIGN_FLIP_BATCH):
        signs = np.where(rng.random((SIGN_FLIP_BATCH, n)) < 0.5, -1, 1)
        hits += int(np.count_nonzero(signs @ d >= obs - 1e-12 * abs(obs)))
    return hits / SIGN_FLIP_DRAWS


def leg_agreement(before: ModelEval, after: ModelEval) -> tuple[int, int, float, float]:
    """Do the held-out legs agree? (legs predicted better, legs, loss share, sign-flip p): per
    held-out thermal leg of every DUT the mean square of its held-out residual before and after;
    the loss share is what the legs predicted worse lose, as a fraction of what the better ones
    gain; the sign-flip p whether the gains could be the noise of a few legs (sign_flip_p). An
    effect that generalises lowers the error on the legs that carry it and costs little elsewhere;
    a term fitted to the noise wins some legs and loses about as much on others."""
    diffs = []
    for d, hb, ha in zip(after.data, before.heldout_block, after.heldout_block):
        ok = ~(np.isnan(hb).any(axis=1) | np.isnan(ha).any(axis=1))
        w = d.block_count[ok]
        leg = d.block_chunk[ok]
        nl = int(leg.max()) + 1 if leg.size else 0
        sb = np.bincount(leg, weights=w * np.sum(hb[ok] ** 2, axis=1), minlength=nl)
        sa = np.bincount(leg, weights=w * np.sum(ha[ok] ** 2, axis=1), minlength=nl)
        has = np.bincount(leg, weights=w, minlength=nl) > 0
        diffs.append((sb - sa)[has] / max(float(w.sum()), 1.0))
    diff = np.concatenate(diffs) if diffs else np.zeros(0)
    gain = float(diff[diff > 0].sum())
    loss = float(-diff[diff < 0].sum())
    return (int(np.count_nonzero(diff > 0)), int(diff.size), (loss / gain if gain > 0 else math.inf),
            sign_flip_p(diff))


def legs_agree(loss_share: float, legs_p: float, legs: int, delta_bic: float) -> bool:
    """The held-out legs agree the effect generalises: the legs predicted worse lose at most half of
    what the better ones gain, and either the gains are many legs' (sign-flip p) or nearly nothing
    is lost anywhere (a local effect, a warm-up or a step, shows on the few legs that hold it and
    costs the others < 10 % of that: the sign-flip test of one leg's gain can never pass). The local
    reading needs MIN_LEGS legs: on six legs "nothing lost elsewhere" happens by chance. With fewer
    legs than that neither test can speak (5 legs give a sign-flip p of 1/32 at best), so the
    in-sample information criterion stands in for them (delta BIC < FEW_LEGS_BIC_GATE), and the few
    legs must all but agree (the others lose < LOCAL_LOSS_SHARE)."""
    if loss_share > LOSS_SHARE_GATE:
        return False
    if legs < MIN_LEGS:
        return delta_bic < FEW_LEGS_BIC_GATE and loss_share <= LOCAL_LOSS_SHARE
    return legs_p < LEGS_P_GATE or loss_share <= LOCAL_LOSS_SHARE


def _gate(cmp: Comparison, before: ModelEval, after: ModelEval) -> tuple[dict, bool]:
    gain = ((before.heldout_rms_mg - after.heldout_rms_mg) / before.heldout_rms_mg
            if before.heldout_rms_mg > 0 else 0.0)
    better, legs, loss_share, legs_p = leg_agreement(before, after)
    rec = {"effects": list(before.effects), "heldout_rms_mg": _r(after.heldout_rms_mg),
           "heldout_gain_rel": _r(gain), "delta_bic": _r(cmp.delta_bic, 2), "score": _r(cmp.lr, 3),
           "score_df": cmp.df, "score_p": float(f"{cmp.p:.3g}"),
           "legs_better": better, "legs": legs, "heldout_loss_share": _r(loss_share, 3),
           "legs_p": float(f"{legs_p:.3g}")}
    ok = bool(cmp.p < SCORE_P_GATE and gain >= HELDOUT_GAIN_GATE
              and legs_agree(loss_share, legs_p, legs, cmp.delta_bic))
    return rec, ok


AT_BOUND_REL = 0.02  # within 2 % of a bound's span (in log space for a log parameter): "at its bound"


def at_bound(name: str, m: ModelEval) -> list[str]:
    """The nonlinear parameters of `name` that the fit left at a bound, in words: the data pushed
    the term's shape (a time constant, a width) to the edge of what is physical, so the term fits
    something other than the effect it names (self_heating at its longest warm-up mimicking a slow
    drift; a lag at its shortest being no lag)."""
    eff = get_effect(name)
    out = []
    for d, f in zip(m.data, m.fits):
        nl = f.nl.get(name, {})
        for p in eff.active(nl):
            if p.name not in nl:
                continue
            v = nl[p.name]
            if p.log and p.lower > 0 and v > 0:
                lo, hi, x = np.log(p.lower), np.log(p.upper), np.log(v)
            else:
                lo, hi, x = p.lower, p.upper, v
            span = hi - lo
            if span <= 0:
                continue
            which = "lower" if x - lo <= AT_BOUND_REL * span else "upper" if hi - x <= AT_BOUND_REL * span else None
            if which:
                bound = p.lower if which == "lower" else p.upper
                who = f"{d.serial}: " if len(m.data) > 1 else ""
                out.append(f"{who}{p.name} = {v:.3g} {p.unit} at its {which} bound ({bound:g} {p.unit})".replace("  ", " "))
    return out


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
        if rec["score_p"] < SCORE_P_GATE:
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



def why_not(row: dict, base_heldout_mg: float | None) -> str:
    """Why a ranked candidate was not admitted, in words (the page's ranking table shows it).

    A candidate whose held-out error is lower than the baseline's is the case an engineer asks
    about, so its sentence starts with that figure and then names every part of the gate it fails."""
    flags = row.get("flags", [])
    for f in flags:
        if f.startswith("stands_for_it:"):
            return (f"cannot be told apart from {f.split(':', 1)[1]} on this data; that one was admitted and "
                    f"stands for it")
        if f.startswith("explained_by:"):
            rec = row.get("given_admitted") or {}
            extra = ""
            if rec.get("heldout_rms_mg") is not None:
                extra = (f": on top of it the held-out error is {rec['heldout_rms_mg']} mg "
                         f"(delta BIC {rec.get('delta_bic')}, p {rec.get('score_p')})")
            return f"explained by {f.split(':', 1)[1]}, admitted before it{extra}"
    dbic, p, gain = row.get("delta_bic"), row.get("score_p"), row.get("heldout_gain_rel")
    held = row.get("heldout_rms_mg")
    better, legs, share = row.get("legs_better"), row.get("legs"), row.get("heldout_loss_share")
    lead = ""
    if gain is not None and gain > 0 and held is not None:
        lead = f"its held-out error is {100 * gain:.0f} % lower ({base_heldout_mg} -> {held} mg), but "
    parts = []
    bound = [f.split(":", 1)[1] for f in flags if f.startswith("at_bound:")]
    if bound:
        parts.append(f"its fit sits at the edge of what the effect allows ({bound[0]}): the data push it towards a "
                     f"shape this effect cannot take, so it fits something else")
    if gain is None or gain < HELDOUT_GAIN_GATE:
        if gain is not None and gain > 0:
            parts.append(f"that is less than the {100 * HELDOUT_GAIN_GATE:g} % the gate asks")
        else:
            parts.append(f"it does not predict the held-out legs better ({base_heldout_mg} -> {held} mg)")
    legs_p = row.get("legs_p")
    if gain is not None and gain > 0 and share is not None and legs_p is not None and legs is not None \
            and legs >= MIN_LEGS and not legs_agree(share, legs_p, legs, math.inf):
        parts.append(f"the held-out legs do not agree: it predicts {better} of {legs} legs better and loses on the "
                     f"others {abs(100 * share):.0f} % of what it gains there (at most {100 * LOSS_SHARE_GATE:g} %), "
                     f"sign-flip p {legs_p} (needs < {LEGS_P_GATE:g}, or the others losing < {100 * LOCAL_LOSS_SHARE:g} %): the gain may be the noise of a few legs, not a "
                     f"shape that repeats" if share is not None and math.isfinite(share) else
                     f"the held-out legs do not agree (sign-flip p {legs_p}, needs < {LEGS_P_GATE:g})")
    if legs is not None and legs < MIN_LEGS and (dbic is None or dbic >= FEW_LEGS_BIC_GATE):
        parts.append(f"with only {legs} held-out legs (fewer than {MIN_LEGS}) the legs cannot show that it "
                     f"generalises, so the information criterion must, and delta BIC {dbic} is not below "
                     f"{FEW_LEGS_BIC_GATE:g}")
    elif legs is not None and legs < MIN_LEGS and share is not None and share > LOCAL_LOSS_SHARE:
        parts.append(f"the held-out legs predicted worse lose {abs(100 * share):.0f} % of what the better ones gain "
                     f"(with so few legs at most {100 * LOCAL_LOSS_SHARE:g} %)")
    if p is None or p >= SCORE_P_GATE:
        parts.append(f"the in-sample evidence is too weak once the sensor's wandering bias is accounted for "
                     f"(likelihood-ratio p {p if p is None else f'{p:.3g}'}, needs < {SCORE_P_GATE:g}; delta BIC "
                     f"{dbic}): the noise model explains the same pattern")
    if not parts:
        return "passes the gate alone but not on top of the effects admitted before it"
    text = lead + "; ".join(parts)
    return text[0].upper() + text[1:]


__all__ = ["EVIDENCE_TIE", "LOSS_SHARE_GATE", "HELDOUT_GAIN_GATE", "SCORE_P_GATE", "why_not", "at_bound", "leg_agreement"]
