"""The admission gate: does adding an effect to a model earn its place?

Why a module of its own: the same three thresholds (delta BIC, likelihood-ratio p-value, held-out
gain) decide whether a candidate has evidence against the baseline and whether it is admitted on
top of the effects already in; keeping them and the gate together means the ranking, the forward
staircase and the masked-pair rule cannot drift apart. The masked-pair rule lives here too: two
effects of opposite sign that hide each other held out are gated, and admitted, together.
"""

from __future__ import annotations

from station.diagnostics.evaluation import ModelEval, _spec
from station.diagnostics.fit import SHAPE_MARGIN
from station.diagnostics.noise_gls import Comparison, compare
from station.diagnostics.report_values import _r

BIC_GATE = -SHAPE_MARGIN  # "very strong" is -10 for an exact likelihood; a margin for the approximate noise model
HELDOUT_GAIN_GATE = 0.03
SCORE_P_GATE = 1e-3


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



def why_not(row: dict, base_heldout_mg: float | None) -> str:
    """Why a ranked candidate was not admitted, in words (the page's ranking table shows it)."""
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
    strong = dbic is not None and dbic < BIC_GATE and p is not None and p < SCORE_P_GATE
    if strong and (gain is None or gain < HELDOUT_GAIN_GATE):
        return (f"fits in sample (delta BIC {dbic}, p {p:.3g}) but does not predict the held-out legs: held-out "
                f"error {base_heldout_mg} -> {held} mg, needs at least {100 * HELDOUT_GAIN_GATE:g} % lower")
    parts = []
    if dbic is None or dbic >= BIC_GATE:
        parts.append(f"too weak in sample (delta BIC {dbic}, needs < {BIC_GATE:g})")
    if p is None or p >= SCORE_P_GATE:
        parts.append(f"likelihood-ratio p {p if p is None else f'{p:.3g}'} under the correlated-noise model "
                     f"(needs < {SCORE_P_GATE:g})")
    if gain is None or gain < HELDOUT_GAIN_GATE:
        parts.append(f"held-out error {base_heldout_mg} -> {held} mg (needs {100 * HELDOUT_GAIN_GATE:g} % lower)")
    if not parts:
        return "passes the gate alone but not on top of the effects admitted before it"
    return "; ".join(parts)


__all__ = ["BIC_GATE", "HELDOUT_GAIN_GATE", "SCORE_P_GATE", "why_not"]
