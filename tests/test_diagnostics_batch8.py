"""Model diagnostics on a batch of 8 DUTs fitted together, hidden effects (see tests/test_diagnostics.py for the
single-DUT cases and what every test asserts). Its own file so a second test worker can take it:
8 x 15 h of validation data per case is the slowest science in the suite."""

from __future__ import annotations

import pytest

import diag_helpers as H
from drivers.sim.physics import HIDDEN_EFFECTS


@pytest.fixture(scope="module")
def validation():
    return H.validation_cache()


# Two effects of different kinds stand for the batch mechanics in CI (shared structure, per-DUT
# parameters): one with a nonlinear parameter fitted per DUT (thermal_lag's tau) and one linear
# term (bias_t2). Every effect is proven on one DUT in tests/test_diagnostics.py; the 8-DUT sweep
# over all of them (about 3 CPU-minutes each) is the benchmark
#     .venv/bin/python benchmarks/diagnostics_report.py --duts 8
BATCH8_EFFECTS = ("thermal_lag", "bias_t2")
assert set(BATCH8_EFFECTS) <= set(HIDDEN_EFFECTS)


@pytest.mark.slow
@pytest.mark.parametrize("effect", BATCH8_EFFECTS)
def test_batch_of_8_hidden_effect_ranks_first_and_reaches_the_floor(validation, effect):
    o = validation(effect, n_duts=8)
    assert len(o.serials) == 8
    H.assert_found_and_floor(o, effect)
    rows = H.compare_params(o.doc["model"]["parameters"], o.truths)
    assert {r["serial"] for r in rows} == set(o.serials)
