"""Tests that catch specific mutations of the science, each against an INDEPENDENT truth (hand
computation or known inputs), not against the code's own output:

(a) eq. 10 (station/science/thermal_model.drift_error_mg) taking the MAX over sections instead of
    the MEAN: martinez2022 eq. 10 is E = sum_i |Acc_i - Acc_i+1| FullRange/dT_i / (n - 1), so steps of
    different slope must average;
(b) a per-axis verification pass that ignores min_rise (station/science/verify.py);
(c) E's sigma without the coefficient term (station/science/residual.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from station.science.residual import residual_report
from station.science.thermal_model import drift_error_mg
from station.science.verify import VerifyCriteria, verify_compensated
from thermal_synth import fast_thermal


def test_a_eq10_is_the_mean_over_sections_of_different_slopes():
    # three sections: 0 C -> 10 C rises 10 mg (1 mg/C), 10 C -> 30 C rises 4 mg (0.2 mg/C)
    temps = np.array([0.0, 10.0, 30.0])
    acc = np.array([[0.000, 0.0, 0.000], [0.010, 0.0, -0.002], [0.014, 0.0, -0.002]])
    # by hand, over a 70 C full range: x (10 * 70/10 + 4 * 70/20) / 2 = (70 + 14) / 2 = 42 mg
    #                                  z (2 * 70/10 + 0) / 2 = 7 mg; y flat = 0
    e = drift_error_mg(acc, temps, 70.0)
    assert e == pytest.approx([42.0, 0.0, 7.0], abs=1e-9)


def test_b_an_axis_whose_heat_rose_less_than_min_rise_does_not_pass():
    rng = np.random.default_rng(11)
    n = 1500
    temp = np.round(np.linspace(30.0, 36.0, n) + rng.normal(0.0, 0.3, n))  # rose ~6 C, 1 C steps
    comp = np.array([-0.577, 0.577, -0.577]) + rng.normal(0.0, 0.5e-3, (n, 3))  # perfectly compensated
    r = verify_compensated(comp, temp, [50.0, 50.0, 50.0], VerifyCriteria(min_rise_c=10.0), wander=None)
    assert r.rise_c < 10.0
    for name, ax in r.axes.items():
        assert not ax.passed, (name, ax)
    assert not r.passed


@pytest.mark.parametrize("rho", [0.0, 0.5, -0.8])
def test_c_drift_error_sigma_carries_the_coefficient_covariance(rho):
    rec = fast_thermal(seed=4)
    sb = np.array([0.05, 0.02, 0.01])  # mg/C
    sf = np.array([40.0, 10.0, 30.0])  # ppm/C
    rep = residual_report(rec.time_s, rec.acc_g, rec.temp_c, rec.truth.tdb_mg_per_c, rec.truth.tdsf_ppm_per_c,
                          sb, sf, tdb_tdsf_corr=[rho] * 3, operating_range_c=70.0)
    for k, ax in enumerate("xyz"):
        r = rep["axes"][ax]
        # by hand: the coefficient error leaves R |dTDB + dTDSF a| at a = +-1 g (the worse sign)
        coef = 70.0 * math.sqrt(sb[k] ** 2 + (sf[k] * 1e-3) ** 2 + 2.0 * abs(rho * sb[k] * sf[k] * 1e-3))
        curv = r["drift_error_curvature_sigma_mg"]  # the curvature's sigma times its parabola's variation
        assert 70.0 ** 2 / 2.0 <= curv / r["curvature_sigma_mg_per_c2"] <= 70.0 ** 2 + 1e-9
        assert r["drift_error_sigma_mg"] == pytest.approx(math.hypot(curv, coef), rel=1e-9)
        assert r["drift_error_sigma_mg"] >= coef
        assert r["drift_error_fs_sigma_pct"] == pytest.approx(r["drift_error_sigma_mg"] / 20.0, rel=1e-9)
