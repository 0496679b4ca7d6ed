"""Helpers for the diagnostics tests: simulated logs from drivers.sim and the honest noise floor.

The noise floor of a log is the residual a perfect model would leave: measured minus the true
model (the simulator's true parameters, Acc0 from the true bias/A matrix) evaluated on the
*measured* inputs (quantized, noisy temperature; time), i.e. white noise plus the effect of the
temperature sensor's noise and 1 C quantization. It is computed on the same samples, and on the
same basis (per sample or 1-minute means) as the model's RMS.
"""

from __future__ import annotations

import numpy as np

from drivers.sim.physics import DutTruth, draw_population
from drivers.sim.world import EnvConfig, SimWorld
from station.diagnostics.fit import window_rms
from station.diagnostics.model import DiagnosticModel
from station.diagnostics.ranking import diagnose
from station.diagnostics.segmentation import prepare
from contracts.logfile import DutLog
from contracts.positions import GRAVITY_DIRECTIONS

# (position, lamp_on, chamber_setpoint or None, chamber ramp C/min, seconds)
Step = tuple[int, bool, float | None, float, float]

# Multi-rate, multi-orientation profile: lamp heating/cooling (exponential: every rate from
# ~4 C/min down to 0) in five orientations (P, N, +x, +y, +z).
MULTI: list[Step] = [(p, lamp, None, 0.0, 1200.0) for p in (0, 1, 2, 4, 6) for lamp in (True, False)]

# Single ramp rate: a chamber triangle at 1 C/min between 20 and 50 C, in two orientations.
SINGLE_RATE: list[Step] = [
    (p, False, sp, 1.0, 1900.0) for p in (0, 1) for sp in (50.0, 20.0)
]


def sim_logs(effects=(), n_duts: int = 1, seed: int = 3, profile: list[Step] | None = None,
             truths: list[DutTruth] | None = None, noise: str = "white",
             odr_hz: float | None = None) -> tuple[list[DutLog], list[DutTruth]]:
    truths = truths or draw_population(n_duts, seed, effects=tuple(effects))
    world = SimWorld(truths, env=EnvConfig(), seed=seed, noise=noise, odr_hz=odr_hz)
    chunks = []
    for pos, lamp, sp, ramp, dur in profile or MULTI:
        world.position = pos
        world.lamp_on = lamp
        world.chamber_setpoint_c = sp
        if sp is not None:
            world.chamber_ramp_c_per_min = ramp
        chunks.append((world.advance(int(round(dur * world.odr_hz))), pos, lamp))
    logs = []
    for i, t in enumerate(truths):
        time_s = np.concatenate([c.time_s for c, _, _ in chunks])
        counts = np.concatenate([c.acc_counts[i] for c, _, _ in chunks])
        tc = np.concatenate([c.temp_counts[i] for c, _, _ in chunks])
        pos = np.concatenate([np.full(len(c), p) for c, p, _ in chunks])
        lamp = np.concatenate([np.full(len(c), int(l)) for c, _, l in chunks]).astype(np.int8)
        logs.append(DutLog(time_s=time_s, acc_g=counts * t.ug_per_lsb * 1e-6,
                           temp_c=25.0 + (tc - t.t_lsb_at_25c) / t.t_lsb_per_c,
                           meta={"serial": t.serial, "sensor": t.sensor}, lamp=lamp, position=pos.astype(np.int64)))
    return logs, truths


def true_model(truth: DutTruth) -> DiagnosticModel:
    """The simulator's truth as a DiagnosticModel (effect params in the library's names)."""
    axes = {ax: {"tdb_mg_per_c": float(truth.tdb_mg_per_c[i]), "tdsf_ppm_per_c": float(truth.tdsf_ppm_per_c[i])}
            for i, ax in enumerate("xyz")}
    nonlinear = {}
    for name, p in truth.effects.items():
        nonlinear[name] = {}
        for key, val in p.items():
            arr = np.asarray(val, float)
            if name == "cross_axis":
                for i, ax in enumerate("xyz"):
                    for j in range(3):
                        axes[ax][f"cross_axis.x_ppm_per_c[{j}]"] = float(arr[i, j]) if i != j else 0.0
            elif arr.ndim == 1 and arr.size == 3:
                for i, ax in enumerate("xyz"):
                    axes[ax][f"{name}.{key}"] = float(arr[i])
            else:
                nonlinear[name][key] = float(arr)
    return DiagnosticModel(serial=truth.serial, effects=list(truth.effects), axes=axes, nonlinear=nonlinear)


def noise_floor(log: DutLog, truth: DutTruth, basis: str = "sample") -> float:
    d = prepare(log)
    acc0 = truth.acc0_g(GRAVITY_DIRECTIONS[log.position])
    pred = true_model(truth).predict(log.time_s, acc0, log.temp_c)
    return window_rms(d, (log.acc_g - pred) * 1000.0, basis=basis)


def pooled_floor(logs, truths, basis="sample") -> float:
    num = den = 0.0
    for lg, t in zip(logs, truths):
        v = noise_floor(lg, t, basis)
        num += v * v * len(lg)
        den += len(lg)
    return float(np.sqrt(num / den))


def compare_params(params: dict, truths: list[DutTruth]) -> list[dict]:
    """Fitted effect parameters (DiagnosisReport.parameters / JSON "parameters") against the truth.

    One row per DUT, effect parameter and axis (axis None for shared nonlinear parameters):
    {"serial", "effect", "param", "axis", "fit", "sigma", "true"}.
    """
    rows = []
    for t in truths:
        fitted = params.get(t.serial, {}).get("effects", {})
        for name, p in t.effects.items():
            got = fitted.get(name, {})
            for key, val in p.items():
                arr = np.asarray(val, float)
                if name == "cross_axis":
                    for i, ax in enumerate("xyz"):
                        for j in range(3):
                            if i == j:
                                continue
                            e = got.get(f"{key}[{j}]", {}).get(ax, {})
                            rows.append({"serial": t.serial, "effect": name, "param": f"{key}[{i}][{j}]", "axis": ax,
                                         "fit": e.get("value"), "sigma": e.get("sigma"), "true": float(arr[i, j])})
                elif arr.ndim == 1 and arr.size == 3:
                    for i, ax in enumerate("xyz"):
                        e = got.get(key, {}).get(ax, {})
                        rows.append({"serial": t.serial, "effect": name, "param": key, "axis": ax,
                                     "fit": e.get("value"), "sigma": e.get("sigma"), "true": float(arr[i])})
                else:
                    e = got.get(key, {})
                    rows.append({"serial": t.serial, "effect": name, "param": key, "axis": None,
                                 "fit": e.get("value"), "sigma": e.get("sigma"), "true": float(arr)})
    return rows


def validation_logs(effects=(), n_duts: int = 1, seed: int = 3, noise: str = "white",
                    odr_hz: float | None = None) -> tuple[list[DutLog], list[DutTruth]]:
    """Logs of the simulator's `validation` profile (drivers/sim/profiles.py) and their truth."""
    from drivers.sim.profiles import run_profile

    truths = draw_population(n_duts, seed, effects=tuple(effects))
    return run_profile(SimWorld(truths, env=EnvConfig(), seed=seed, noise=noise, odr_hz=odr_hz), "validation"), truths


# A PX4/ArduPilot-style single-orientation sweep: the board flat (P) in a chamber from 25 C down to
# -17 C, up to 74 C and back, twice, at 2 then 1 C/min (two rates tell lag from hysteresis).
def _sweep() -> list[Step]:
    out: list[Step] = [(0, False, -17.0, 2.0, 42 / 2 * 60 + 600)]
    for rate in (2.0, 1.0):
        leg = 91.0 / rate * 60.0 + 600.0
        out += [(0, False, 74.0, rate, leg), (0, False, -17.0, rate, leg)]
    return out


SWEEP: list[Step] = _sweep()

# A short validation-like profile for fast tests: power-up, then one full cycle 25 -> 60 -> -10 -> 25 C
# in each of five orientations (P, +x, -y, +z, N) at 2 and 4 C/min: two ramp rates; cross-axis and
# scale nonlinearity identifiable and told apart (with four orientations Acc0_i^2 is an affine
# function of the three Acc0_j, so scale_nonlinearity would be nested in cross_axis).
def _short_validation() -> list[Step]:
    out: list[Step] = [(0, False, 25.0, 2.0, 1200.0)]
    for pos, rate in ((0, 2.0), (2, 4.0), (5, 2.0), (6, 4.0), (1, 4.0)):
        out += [(pos, False, 60.0, rate, 35 / rate * 60 + 600), (pos, False, -10.0, rate, 70 / rate * 60 + 600),
                (pos, False, 25.0, rate, 35 / rate * 60 + 300)]
    return out


SHORT_VALIDATION: list[Step] = _short_validation()


# ---- shared by tests/test_diagnostics.py and tests/test_diagnostics_batch8.py ------------------
FLOOR_FACTOR = 1.15


class Outcome:
    """What a test needs from one diagnosis (the full report holds ~100 MB of residuals)."""

    def __init__(self, logs, truths, rep):
        self.doc = rep.to_json()
        self.serials = rep.serials
        self.floor_window = pooled_floor(logs, truths, "window")
        self.floor_sample = pooled_floor(logs, truths, "sample")
        self.truths = truths
        self.models = rep.models()
        self.base_models = [DiagnosticModel.from_fit(d.serial, f, d.t_power_on_s)
                            for d, f in zip(rep.data, rep.baseline.fits)]
        self.logs = logs

    @property
    def ranking(self):
        return self.doc["ranking"]

    @property
    def admitted(self):
        return [r["effect"] for r in self.ranking if r["admitted"]]


def validation_cache():
    """diagnose(validation-profile logs with one hidden effect, add=[that effect]), cached."""
    cache: dict = {}

    def get(effect: str, n_duts: int = 1) -> Outcome:
        key = (effect, n_duts)
        if key not in cache:
            effs = () if effect == "none" else (effect,)
            logs, truths = validation_logs(effs, n_duts=n_duts)
            cache[key] = Outcome(logs, truths, diagnose(logs, add=list(effs)))
        return cache[key]

    return get


def assert_found_and_floor(o: "Outcome", effect: str):
    names = [r["effect"] for r in o.ranking]
    assert names[0] == effect, (effect, [(r["effect"], r["heldout_rms_mg"]) for r in o.ranking[:3]])
    assert o.admitted[0] == effect and o.ranking[0]["flags"] == []
    assert effect not in {c for p in o.doc["confusable"] for c in p["effects"]}
    base = o.doc["baseline"]["heldout_rms_mg"]
    step = o.doc["staircase"][-1]
    assert step["model"] == f"+{effect}" and step["effects"] == [effect]
    # the effect is plainly visible to the baseline ...
    assert base > 3.0 * o.floor_window, (base, o.floor_window)
    # ... and adding it brings the held-out RMS to the noise floor (held-out = whole legs: a single
    # warm-up transient cannot be predicted for the fold that holds out the power-on leg)
    if effect != "self_heating":
        assert step["heldout_rms_mg"] <= FLOOR_FACTOR * o.floor_window, (step["heldout_rms_mg"], o.floor_window)
        assert step["heldout_rms_per_sample_mg"] <= FLOOR_FACTOR * o.floor_sample
    else:
        assert step["heldout_rms_mg"] < 0.97 * base  # the gate: held-out lower by >= 3 %
    assert step["rms_mg"] <= step["heldout_rms_mg"] * 1.05  # in-sample never much worse than held-out
    assert o.doc["admitted_staircase"][-1]["heldout_rms_mg"] < base
