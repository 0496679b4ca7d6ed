"""martinez2022 eqs. 1, 10-13: drift model, compensation, drift error and its full-scale figure."""

import numpy as np
import pytest

from station.science.thermal_model import apply_drift, compensate, drift_error_fs_pct, drift_error_mg

TDB = np.array([0.47, 1.30, -0.92])  # Table 6-like
TDSF = np.array([-125.0, -113.0, -167.0])


def test_eq1_by_hand():
    # Acc = Acc0 + (T - 25)(TDB + TDSF Acc0): 0.5 g at 45 C, TDB 1 mg/C, TDSF -100 ppm/C
    assert apply_drift(0.5, 45.0, 1.0, -100.0) == pytest.approx(0.5 + 20 * (1e-3 - 100e-6 * 0.5), abs=1e-15)


def test_compensate_inverts_apply_drift_and_broadcasts():
    rng = np.random.default_rng(1)
    acc0 = rng.uniform(-1, 1, (500, 3))
    temp = rng.uniform(-10, 60, 500)
    acc = apply_drift(acc0, temp, TDB, TDSF)
    assert acc.shape == (500, 3)
    assert np.max(np.abs(acc - acc0)) > 0.04  # up to 35 C x 1.4 mg/C
    np.testing.assert_allclose(compensate(acc, temp, TDB, TDSF), acc0, atol=1e-14)
    # at the reference temperature nothing changes
    np.testing.assert_array_equal(compensate(acc0, np.full(500, 25.0), TDB, TDSF), acc0)


@pytest.mark.parametrize(
    "e_mg, fs_pct",
    [(103.10, 5.15), (23.11, 1.16), (15.72, 0.79), (42.77, 2.14), (12.18, 0.61), (6.85, 0.34)],
)
def test_full_scale_error_matches_table7(e_mg, fs_pct):
    # Table 7 figures: E_FS = E / 2000 mg (the +-1 g span); the paper truncates/rounds to 2 decimals
    assert abs(float(drift_error_fs_pct(e_mg)) - fs_pct) < 0.006


def test_drift_error_eq10_on_section_means():
    # chamber-like sections -10 -> 7.5 -> 25 -> 42.5 -> 60 C (range 70 C), one axis up (+1 g)
    temps = np.array([-10.0, 7.5, 25.0, 42.5, 60.0])
    acc0 = np.array([1.0, 0.0, 0.0])
    sec = apply_drift(np.tile(acc0, (5, 1)), temps, TDB, TDSF)
    e = drift_error_mg(sec, temps, full_range_c=70.0)
    # linear drift: every step gives |TD| x 70 C, so E = |TDB + TDSF Acc0| x 70 (eq. 11)
    td_mg = np.abs(TDB + TDSF * 1e-3 * acc0)
    np.testing.assert_allclose(e, td_mg * 70.0, rtol=1e-12)
    # and equals |Acc_hot - Acc_cold| (eq. 11) for a monotonic profile
    np.testing.assert_allclose(e, np.abs(sec[-1] - sec[0]) * 1e3, rtol=1e-12)
    # compensation with the true parameters removes it; with 10 % wrong TDB it leaves 10 %
    comp = compensate(sec, temps, TDB, TDSF)
    assert np.all(drift_error_mg(comp, temps, 70.0) < 1e-9)
    comp_bad = compensate(sec, temps, TDB * 0.9, TDSF)
    e_bad = drift_error_mg(comp_bad, temps, 70.0)
    np.testing.assert_allclose(e_bad, 0.1 * np.abs(TDB) * 70.0 / (1 + 0), rtol=0.05)


def test_drift_error_weighs_each_step_per_degree():
    # two steps of different size with the same slope give the same per-step error
    e = drift_error_mg(np.array([0.0, 0.010, 0.012]), np.array([20.0, 30.0, 32.0]), full_range_c=70.0)
    assert float(e) == pytest.approx(70.0, rel=1e-12)  # 1 mg/C x 70 C
    with pytest.raises(ValueError):
        drift_error_mg(np.array([0.0, 0.01]), np.array([20.0, 20.0]), 70.0)
