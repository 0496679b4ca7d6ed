"""Diagnostics on data with a real MEMS part's noise (issue 11): bias random walk and flicker.

The simulator's `realistic` noise model (drivers/sim/physics.NoiseModel) adds the slow bias wander
every real accelerometer has; the diagnostics must not mistake it for a missing effect, must still
find the effects that are there, and must say what one orientation cannot tell. Logs are short
(a 5.5 h four-orientation cycle, or a 5.7 h single-orientation sweep) at 1 Hz to keep each test to
seconds; the 20-seed false-discovery table on the full validation profile is in
benchmarks/diagnostics_fdr.py.

Truth is independent of the code under test: the simulator's parameters (which effects are on)
and, for floors, the same DUT and noise realisation without the hidden effect (the control log:
effects draw from their own random streams, so the noise is identical).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import diag_helpers as H
from drivers.sim.physics import NOISE_MODELS, draw_population, noise_model
from drivers.sim.world import SimWorld
from station.diagnostics.ranking import diagnose
from contracts.types import StationError

ROOT = Path(__file__).resolve().parents[1]
ODR = 1.0


def _allan(x: np.ndarray, m: int) -> float:
    k = x.size // m
    y = x[: k * m].reshape(k, m).mean(axis=1)
    return float(np.sqrt(0.5 * np.mean(np.diff(y) ** 2)))


def test_realistic_noise_wanders_and_white_does_not():
    """Same DUT, seed and temperatures with the `white` and the `realistic` (lis3dsh) noise: the
    white noise and the thermal drift are identical sample for sample (the bias wander has its own
    random stream), and the difference is a bias wander whose Allan deviation at 1000 s is of the
    model's order (flicker floor up to the random walk's K sqrt(tau / 3))."""
    n = 40_000  # 3.6 h at 3.125 Hz
    x = {}
    for name in ("white", "realistic"):
        w = SimWorld(draw_population(1, 4), seed=4, noise=name)
        w.chamber_setpoint_c = 25.0
        x[name] = np.concatenate([w.advance(4000).acc_counts[0, :, 2] for _ in range(n // 4000)]) * 60e-6  # g
    diff = x["realistic"] - x["white"]
    m = NOISE_MODELS["lis3dsh"]
    white_1 = _allan(x["white"], 1)
    assert _allan(diff, 1) < 0.2 * white_1  # per sample: the same white noise
    wander = _allan(diff, 3125)
    assert 0.3 * m.flicker_g < wander < 3 * (m.flicker_g + m.bias_rw_g_per_sqrt_s * np.sqrt(1000 / 3)), wander
    assert _allan(diff, 3125) > 0.5 * _allan(x["white"] - x["white"].mean(), 3125) or wander > 30e-6
    assert noise_model("realistic", "ADXL355").name == "adxl355"
    with pytest.raises(StationError, match="unknown noise model"):
        noise_model("pink")


def test_simulate_cli_noise_option_recorded_in_truth(tmp_path):
    out = subprocess.run([sys.executable, "-m", "cli", "simulate", "--out", tmp_path, "--duts", "1",
                          "--noise", "adxl355", "--sensor", "ADXL355", "--quiet"], capture_output=True, text=True,
                         timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    doc = json.loads((tmp_path / "truth.json").read_text())
    assert doc["noise"]["name"] == "adxl355" and doc["noise"]["bias_rw_g_per_sqrt_s"] > 0
    head = [ln for ln in (tmp_path / "SIM0001.csv").read_text().splitlines()[:30] if ln.startswith("#")]
    assert "# noise: adxl355" in head
    bad = subprocess.run([sys.executable, "-m", "cli", "simulate", "--out", tmp_path, "--noise", "pink"],
                         capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert bad.returncode != 0 and "unknown noise model" in bad.stderr and "Traceback" not in bad.stderr


@pytest.mark.parametrize("seed", [11, 12])
def test_clean_realistic_logs_admit_nothing(seed):
    """No hidden effect, realistic noise: nothing admitted, and the output names the noise model."""
    logs, _ = H.sim_logs((), profile=H.SHORT_VALIDATION, seed=seed, noise="realistic", odr_hz=ODR)
    doc = diagnose(logs).to_json()
    assert doc["admitted"] == [], [(r["effect"], r["heldout_gain_rel"], r["delta_bic"], r["score_p"])
                                   for r in doc["ranking"]]
    assert all(not r["admitted"] for r in doc["ranking"])
    assert "random walk" in doc["noise_model"]["residual"] and "whole thermal legs" in doc["noise_model"]["heldout"]
    nm = doc["noise_model"]["baseline"][logs[0].serial]["z"]
    assert nm["random_walk"] is True  # the wander is seen in the residual


@pytest.fixture(scope="module")
def sweep():
    """Single-orientation chamber sweep (heating and cooling, 2 rates) with a quadratic bias and a
    hysteresis, realistic noise; diagnosed once, then refitted with the admitted effects."""
    logs, truths = H.sim_logs(("bias_t2", "hysteresis"), profile=H.SWEEP, seed=5, noise="realistic", odr_hz=ODR)
    rep = diagnose(logs, add=["bias_t2", "bias_t3"])  # the cubic bias-vs-temperature polynomial
    return logs, truths, rep.to_json()


def test_single_orientation_tdsf_not_identifiable_total_drift_reported(sweep):
    logs, truths, doc = sweep
    serial = truths[0].serial
    assert doc["drift"]["tdsf_identifiable"][serial] == {"x": False, "y": False, "z": False}
    assert "orientation" in doc["drift"]["test_to_identify"]
    base = doc["baseline_parameters"][serial]["baseline"]
    for ax in "xyz":
        assert base["tdsf_ppm_per_c"][ax]["value"] is None and base["tdsf_ppm_per_c"][ax]["sigma"] is None
        assert base["tdsf_ppm_per_c"][ax]["identifiable"] is False
        assert base["total_drift_mg_per_c"][ax]["value"] is not None
    # the total drift is TDB + TDSF Acc0 of the truth (the slope at 25 C; the curvature adds none there)
    t = truths[0]
    acc0 = t.acc0_g(np.array([1.0, 1.0, 1.0]) / np.sqrt(3.0))
    for i, ax in enumerate("xyz"):
        true_total = t.tdb_mg_per_c[i] + t.tdsf_ppm_per_c[i] * 1e-3 * acc0[i]
        got = base["total_drift_mg_per_c"][ax]
        assert abs(got["value"] - true_total) < 5 * got["sigma"] + 0.02, (ax, got, true_total)


def test_single_orientation_curvature_one_term_then_hysteresis_each_lowering_heldout(sweep):
    logs, truths, doc = sweep
    alias = next(a for a in doc["aliases"] if set(a["effects"]) == {"bias_t2", "scale_t2"})
    assert alias["term"] == "curvature" and "one orientation" in alias["text"]
    ranked = [r["effect"] for r in doc["ranking"]]
    assert "scale_t2" not in ranked  # one term, not two refused "confusable" ones
    assert doc["admitted"] == ["bias_t2", "hysteresis"]
    row = next(r for r in doc["ranking"] if r["effect"] == "bias_t2")
    assert row["aliases"] == ["scale_t2"] and row["term"] == "curvature"
    ho = [s["heldout_rms_mg"] for s in doc["admitted_staircase"]]
    assert [s["model"] for s in doc["admitted_staircase"]] == ["baseline", "+bias_t2", "+hysteresis"]
    assert ho[0] > ho[1] > ho[2], ho
    assert ho[2] < 0.1 * ho[0]


def test_admitted_model_beats_the_cubic_polynomial_on_heldout(sweep):
    """What PX4, ArduPilot and test templates fit: a cubic bias vs temperature (eq. 1 + bias_t2 +
    bias_t3 here, the same span). The automatically admitted model must predict held-out data better."""
    logs, truths, doc = sweep
    cubic = doc["staircase"][-1]
    assert cubic["effects"] == ["bias_t2", "bias_t3"]
    admitted = doc["admitted_staircase"][-1]["heldout_rms_mg"]
    assert admitted < 0.5 * cubic["heldout_rms_mg"], (admitted, cubic["heldout_rms_mg"])


def test_admitted_staircase_is_what_add_reproduces(sweep):
    logs, truths, doc = sweep
    again = diagnose(logs, add=doc["admitted"], candidates=["bias_t2"]).to_json()
    got = [(s["model"], s["heldout_rms_mg"]) for s in again["staircase"]]
    want = [(s["model"], s["heldout_rms_mg"]) for s in doc["admitted_staircase"]]
    assert got == want
