"""Effect families on logs this project's simulator did not make (tests/diag_plant.py, issue 23).

Each hidden effect has its own code in the generator (not station/diagnostics/effects.py, not
drivers/sim): hysteresis of three shapes (relay with a switching threshold, backlash, smooth
approach) and a mixture of two (the family's Prandtl-Ishlinskii superposition), thermal lag of first and second order, quadratic and cubic bias, all under the
correlated noise of a LIS3DSH-class part (white + bias random walk + flicker). The diagnosis must
rank the effect first, admit it alone, name its shape, and bring the held-out error within 1.1x of
the control floor: the baseline's held-out error on the same log (same noise) without the effect.
Twenty clean logs admit nothing.
"""

from __future__ import annotations

import numpy as np
import pytest

import diag_plant as G
from station.diagnostics.effects import REGISTRY, Effect, register
from station.diagnostics.ranking import diagnose

FLOOR_RATIO = 1.1  # issue 23; measured 0.98-1.06 at seed 1, 0.91-1.02 at seed 3; at seed 2 1.00-1.13,
# where the true operator itself reaches only 1.10-1.11 (see the last test)
CASES = {
    # generator effect: (library effect, the shape's words, extra check on the fitted shape)
    "relay": ("hysteresis", "relay", ("width_c", 4.0, 0.15)),
    "backlash": ("hysteresis", "backlash", ("width_c", 10.0, 0.1)),
    "smooth": ("hysteresis", "smooth", ("width_c", 5.0, 0.1)),
    # a 3 C backlash and a 20 C smooth approach at once: no single operator has that loop
    "mixture": ("hysteresis", "superposition", None),
    "lag1": ("thermal_lag", "first-order", ("tau_s", 150.0, 0.1)),
    "lag2": ("thermal_lag", "second-order", None),
    "bias2": ("bias_t2", "quadratic", None),
    "bias3": ("bias_t3", "cubic", None),
}
SEED = 1


@pytest.fixture(scope="module")
def control_floor_mg() -> float:
    doc = diagnose([G.make_log(None, SEED)]).to_json()
    assert doc["admitted"] == []
    return doc["baseline"]["heldout_rms_mg"]


@pytest.mark.parametrize("generated", list(CASES))
def test_each_shape_is_ranked_first_admitted_named_and_at_the_floor(generated, control_floor_mg):
    effect, words, check = CASES[generated]
    rep = diagnose([G.make_log(generated, SEED)])
    doc = rep.to_json()
    first = doc["ranking"][0]
    assert first["effect"] == effect, [(r["effect"], r["heldout_rms_mg"]) for r in doc["ranking"][:3]]
    assert doc["admitted"] == [effect], doc["admitted"]
    assert first["shape"].startswith(words) or words in first["shape"], first["shape"]
    step = doc["admitted_staircase"][-1]
    assert step["shape"] == first["shape"]
    base = doc["baseline"]["heldout_rms_mg"]
    assert base > 1.4 * control_floor_mg, (base, control_floor_mg)  # the effect is plainly visible ...
    assert step["heldout_rms_mg"] <= FLOOR_RATIO * control_floor_mg, (step["heldout_rms_mg"], control_floor_mg)
    if check:  # ... and the family's nonlinear value is the generator's
        name, true, rel = check
        fitted = rep.model.fits[0].nl if rep.model.effects else rep.ranked.get_eval([effect]).fits[0].nl
        assert abs(fitted[effect][name] - true) <= rel * true, (fitted, true)
    if generated == "lag2":  # die 60 s and package 500 s in series: both time constants found
        nl = rep.ranked.get_eval([effect]).fits[0].nl[effect]
        die, pkg = sorted((nl["tau_s"], nl["tau2_s"]))
        assert 30.0 <= die <= 120.0 and 350.0 <= pkg <= 650.0, nl
    # every candidate left out says why, in words
    for r in doc["ranking"]:
        assert r["admitted"] or len(r.get("why", "")) > 20, r


def test_a_family_is_one_candidate_and_its_shape_costs_a_parameter():
    """The gate charges the family's shape choice: the LR test's df counts it (1 amplitude per axis
    + width + shape = 5 for hysteresis, 1 + tau + order = 2 for a first-order lag)."""
    doc = diagnose([G.make_log("relay", SEED)]).to_json()
    rows = {r["effect"]: r for r in doc["ranking"]}
    assert sum(1 for r in doc["ranking"] if r["effect"] == "hysteresis") == 1
    assert rows["hysteresis"]["score_df"] == 3 + 2
    assert rows["thermal_lag"]["score_df"] == 2


def test_twenty_clean_logs_admit_nothing():
    """False discoveries under correlated noise: 20 logs (seeds 100..119) without any effect."""
    admitted = {}
    for seed in range(100, 120):
        doc = diagnose([G.make_log(None, seed)]).to_json()
        if doc["admitted"]:
            admitted[seed] = doc["admitted"]
    assert admitted == {}


class _TrueOperator(Effect):
    """The generator's own operator of the true die temperature, as a user effect: the best any
    hysteresis model can do on this log (only its three amplitudes are fitted)."""

    linear = ("h_mg",)

    def __init__(self, name, z_of_die):
        self.name = name
        t_s, plate_c, _ = G.plate_profile()
        self._z = z_of_die(G.first_order_lag(plate_c, 40.0))

    def columns(self, ctx, nl):
        z = self._z[np.clip(np.round(ctx.time_s * G.RATE_HZ).astype(int), 0, self._z.size - 1)]
        return np.repeat(z[:, None, None], 3, axis=1)


@pytest.fixture
def true_operators():
    ops = {"relay": _TrueOperator("true_relay", lambda x: G.relay(x, 4.0)),
           "backlash": _TrueOperator("true_backlash", lambda x: G.backlash(x, 10.0))}
    for op in ops.values():
        register(op)
    yield ops
    for op in ops.values():
        REGISTRY.pop(op.name, None)


@pytest.mark.parametrize("generated", ["relay", "backlash"])
def test_the_family_predicts_held_out_legs_as_well_as_the_true_operator(generated, true_operators):
    """Seed 2's noise puts even the true operator at 1.10-1.11x the control floor (the amplitudes
    fitted under bias wander cost that much held out), so the floor ratio alone cannot judge the
    shape there: the family's held-out error must be that of the true operator."""
    log = G.make_log(generated, 2)
    fam = diagnose([log], candidates=["hysteresis"], add=["hysteresis"]).model.heldout_rms_mg
    true = diagnose([log], candidates=[true_operators[generated].name],
                    add=[true_operators[generated].name]).model.heldout_rms_mg
    assert fam <= 1.02 * true, (fam, true)
