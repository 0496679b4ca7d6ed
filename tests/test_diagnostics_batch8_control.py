"""Model diagnostics on a batch of 8 DUTs fitted together: the control (no hidden effect) and the
single-ramp-rate case. Its own file so another test worker takes it beside
tests/test_diagnostics_batch8.py (each 8-DUT diagnosis is minutes of CPU)."""

from __future__ import annotations

import pytest

import diag_helpers as H
from station.diagnostics.ranking import diagnose


@pytest.fixture(scope="module")
def validation():
    return H.validation_cache()


@pytest.mark.slow
def test_batch_of_8_control_admits_nothing(validation):
    o = validation("none", n_duts=8)
    assert o.admitted == [] and o.doc["confusable"] == []


@pytest.mark.slow
def test_batch_of_8_single_rate_lag_is_confusable():
    logs, _ = H.sim_logs(("thermal_lag",), n_duts=8, profile=H.SINGLE_RATE)
    doc = diagnose(logs).to_json()
    assert {"thermal_lag", "hysteresis"} in [set(c["effects"]) for c in doc["confusable"]]
    # as for one DUT (tests/test_diagnostics.py): the pair is one term, one member goes in, its
    # partner is flagged as standing for the same signal, and nothing else soaks it up
    assert len(doc["admitted"]) == 1 and doc["admitted"][0] in {"thermal_lag", "hysteresis"}
    rows = {r["effect"]: r for r in doc["ranking"]}
    other = ({"thermal_lag", "hysteresis"} - set(doc["admitted"])).pop()
    assert any(f.startswith("stands_for_it:") for f in rows[other]["flags"])


