"""Every hidden effect of the simulator, with the realistic noise on (issue 11): ranked first,
admitted, the admitted staircase monotone, and the held-out RMS after it within 10 % of the
control log's floor (the same DUT, seed and noise realisation without the effect: its baseline
held-out RMS). Short five-orientation cycles at 1 Hz (diag_helpers.SHORT_VALIDATION); the same
table on the full 15.7 h validation profile: benchmarks/diagnostics_fdr.py --effects.

Two effects cannot reach the floor on held-out whole legs, for reasons of the data, not the model:
- self_heating is a single warm-up transient at power-on: the fold that holds out the first leg
  has no transient to learn from. Shown: ranked first, admitted, held-out lowered.
- cross_axis on this short profile: x_xz is told from TDSF_x only by the +z cycle (two legs at
  4 C/min), so a fold holding one of them out learns it from half a cycle. It reaches the floor on
  the full validation profile (benchmark); here: ranked first, admitted, held-out lowered > 20x.
"""

from __future__ import annotations

import pytest

import diag_helpers as H
from drivers.sim.physics import HIDDEN_EFFECTS
from station.diagnostics.ranking import diagnose

SEED = 3
ODR = 1.0
FLOOR_FACTOR = 1.10
FLOOR_LIMITED_BY_DATA = {"self_heating", "cross_axis"}


@pytest.fixture(scope="module")
def control_floor() -> float:
    logs, _ = H.sim_logs((), profile=H.SHORT_VALIDATION, seed=SEED, noise="realistic", odr_hz=ODR)
    return diagnose(logs, candidates=[]).to_json()["baseline"]["heldout_rms_mg"]


@pytest.mark.parametrize("effect", HIDDEN_EFFECTS)
def test_hidden_effect_found_admitted_and_at_the_control_floor(effect, control_floor):
    logs, _ = H.sim_logs((effect,), profile=H.SHORT_VALIDATION, seed=SEED, noise="realistic", odr_hz=ODR)
    doc = diagnose(logs).to_json()
    assert doc["ranking"][0]["effect"] == effect, [(r["effect"], r["heldout_rms_mg"]) for r in doc["ranking"][:3]]
    assert doc["admitted"] == [effect], doc["admitted"]
    st = doc["admitted_staircase"]
    ho = [s["heldout_rms_mg"] for s in st]
    assert all(a > b for a, b in zip(ho, ho[1:])), ho  # monotone
    assert [s["model"] for s in st] == ["baseline", f"+{effect}"]
    if effect in FLOOR_LIMITED_BY_DATA:
        assert ho[-1] < 0.95 * ho[0]
    else:
        assert ho[0] > 3 * control_floor  # the effect is plainly visible ...
        assert ho[-1] <= FLOOR_FACTOR * control_floor, (ho, control_floor)  # ... and adding it reaches the floor
