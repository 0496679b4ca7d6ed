"""The forward staircase: which candidate effects are admitted, and in what order.

Why a module of its own: ranking every candidate against the baseline alone is not enough (one
effect can explain another's signal, or an effect of opposite sign can mask it). The staircase gates
every candidate against the model holding exactly the effects admitted before it, so `admitted` is
a list that `--add` reproduces step by step, each step lowering the held-out error; and it flags
the candidates left out because an admitted effect explains them or stands for them.
"""

from __future__ import annotations

from station.diagnostics.evaluation import ModelEval, _spec, _spec_plus
from station.diagnostics.gate import SCORE_P_GATE, _gate, _masked_pair, at_bound
from station.diagnostics.noise_gls import compare


def _admit_forward(data, base: ModelEval, rows: list[dict], confusable: list[dict], get_eval) -> tuple[list[str], list[dict]]:
    """Monotone forward staircase: at each step every candidate is gated against the model that holds
    exactly the effects admitted before it (no stand-ins); of those that pass, the one with the
    lowest delta BIC (the strongest in-sample evidence) is admitted. A candidate
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
                    if not screen.p < SCORE_P_GATE:
                        continue
                cand = get_eval(admitted + [name])
                rec, ok = _gate(compare(data, _spec(current), _spec(cand)), current, cand)
                bound = at_bound(name, cand)
                if bound:
                    rec["at_bound"] = "; ".join(bound)
                r["given_admitted"] = rec
                if not ok or bound:
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
