"""station/science/residual.py against the simulator's truth: fast-thermal logs of simulated DUTs
(open loop, drivers/sim), calibrated with `calibrate`, whose "residual" report must find the true
quadratic bias drift (bias_t2, c2 in mg/C^2) of curved DUTs and none in linear ones.

Measured (seed 3, 3 DUTs each): curved |c2 - truth| <= 0.0009 mg/C^2 (sigma 0.0002-0.0005);
linear |c2| <= 0.0013, bow <= 0.8 mg, E_FS <= 0.16 %.
"""

from __future__ import annotations

import numpy as np
import pytest

from drivers.sim.physics import draw_population
from drivers.sim.profiles import run_profile
from drivers.sim.world import SimWorld
from station.science.thermal_calibration import calibrate
from contracts.types import AXES


@pytest.fixture(scope="module")
def reports():
    out = {}
    for effects in ((), ("bias_t2",)):
        truths = draw_population(3, 3, effects=effects)
        logs = run_profile(SimWorld(truths, seed=3), "fast-thermal")
        out[effects] = [(t, calibrate(log)) for t, log in zip(truths, logs)]
    return out


def test_curvature_of_curved_duts_matches_the_truth(reports):
    for truth, res in reports[("bias_t2",)]:
        c2_true = truth.effects["bias_t2"]["c2_mg_per_c2"]
        for k, ax in enumerate(AXES):
            r = res["residual"]["axes"][ax]
            assert r["curvature_mg_per_c2"] == pytest.approx(c2_true[k], abs=0.002), (truth.serial, ax)
            # the bow and E follow from c2 over the 70 C operating range: |c2| R^2 / 8, and for E
            # the parabola the chord compensation leaves, its vertex in the data (R^2/2 .. R^2)
            assert r["bow_mg"] == pytest.approx(abs(r["curvature_mg_per_c2"]) * 70.0 ** 2 / 8)
            assert 70.0 ** 2 / 2 - 1e-9 <= r["drift_error_mg"] / abs(r["curvature_mg_per_c2"]) <= 70.0 ** 2 + 1e-9
            assert r["drift_error_fs_pct"] == pytest.approx(r["drift_error_mg"] / 2000.0 * 100.0)
        assert max(res["residual"]["axes"][ax]["bow_mg"] for ax in AXES) > 3.5


def test_linear_duts_show_no_curvature_and_a_small_residual_drift(reports):
    for truth, res in reports[()]:
        for ax in AXES:
            r = res["residual"]["axes"][ax]
            assert abs(r["curvature_mg_per_c2"]) < 0.002
            assert r["bow_mg"] < 1.5 and r["drift_error_fs_pct"] < 0.3
            assert r["drift_error_sigma_mg"] > 0 and r["ramp_residual_rms_mg"] < 0.5
            # noise density of the simulated LIS3DSH: 0.5 mg rms per sample at 3.125 Hz (+-10 %)
            expected = truth.noise_g / np.sqrt(3.125 / 2) * 1e6
            assert r["noise_ug_per_sqrt_hz"] == pytest.approx(expected, rel=0.15)
