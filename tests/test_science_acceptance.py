"""Acceptance checks of issue 2 ("What must be shown") on the real pipeline: simulator -> logs ->
station.science, compared with the simulator's hidden truth.

- Fast-thermal on 32 simulated LIS3DSH DUTs (martinez2022 Table 6 population): TDB within
  0.03 mg/C and TDSF within 40 ppm/C of the truth on >= 95 % of axes, streaming and offline each;
  streaming and offline TD_i within 1 % of each other (Table 5).
- Six-position chamber test of the same DUTs, compensated with their fast-thermal parameters:
  drift error E (eqs. 10-12) before/after, average and maximum (Table 7); compensated average
  < 25 % of the uncompensated one.
- SFEM on simulated sfem-24 data (sensors2023 Table 1 plan): every parameter within its
  noise-limited tolerance (the fit's own 1-sigma), |a| - 1 g RMSE before/after (Table 6).

The module-level functions are also what benchmarks/science_report.py prints.

How the fast-thermal run is driven: the simulator's fast-thermal steps (P ambient, P hot, N hot,
N ambient) with the station sequencer's rule (design 2): a step lasts at least its nominal time
and moves on when every DUT has logged the segment that step is for, or when its timeout ends.
The open-loop profile (`station simulate`, fixed durations) is run too and reported, because its
25 min P-hot step is marginal for the slowest DUTs (see `open_loop_fast_thermal`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest

from drivers.sim.physics import DutTruth, draw_population
from drivers.sim.profiles import CHAMBER_STEPS_C, Step, fast_thermal_steps, run_profile, run_steps, step_table
from drivers.sim.world import SimWorld
from contracts.logfile import DutLog
from contracts.positions import GRAVITY_DIRECTIONS, POSITION_INDEX, SIX_POSITION
from station.science.sfem_model import decompose_a
from station.science.sfem_record import fit_sfem_record
from station.science.streaming import StreamingCalibrator
from station.science.thermal_calibration import calibrate
from station.science.thermal_model import compensate, drift_error_fs_pct, drift_error_mg
from contracts.types import AXES, StationError

N_DUTS = 32
SEED = 2022
TDB_TOL_MG_PER_C = 0.03
TDSF_TOL_PPM_PER_C = 40.0
PASS_FRACTION = 0.95
TD_REL_TOL = 0.01
TD_NOISE_K = 3.0  # sigmas of the streaming TD_i noise where 1 % of TD_i is below it
FULL_RANGE_C = 70.0  # -10 .. 60 C chamber steps (martinez2022 4.4)
HOLD_TAIL_S = 5 * 60  # each chamber hold: its last 5 min make the thermal section
EXTEND_S = 30.0  # sequencer: a step not yet complete is extended in 30 s slices ...
STEP_TIMEOUT_S = 15 * 60  # ... up to this much beyond its nominal time
SFEM_SIGMA_K = 4.0


# ------------------------------------------------------------------------------------------------
# fast-thermal


def _logs_from_cols(world: SimWorld, cols: dict[str, np.ndarray], profile: str) -> list[DutLog]:
    ref = GRAVITY_DIRECTIONS[cols["position"]]
    logs = []
    for i, truth in enumerate(world.duts):
        ident = world.identity(i)
        logs.append(
            DutLog(
                time_s=cols["time_s"].copy(),
                acc_g=ident.acc_g(cols["acc_counts"][i]),
                temp_c=ident.temp_c(cols["temp_counts"][i]),
                meta={"serial": truth.serial, "sensor": truth.sensor, "profile": profile, "source": "simulator"},
                lamp=cols["lamp"].copy(),
                position=cols["position"].copy(),
                ref_dir=ref.copy(),
            )
        )
    return logs


def closed_loop_fast_thermal(truths: list[DutTruth], seed: int) -> tuple[list[DutLog], list[float]]:
    """The fast-thermal steps run as the station's sequencer runs them (see module doc).

    Each DUT's own streaming calibrator (the MCU algorithm, fed live) says when its segment of the
    step is logged. Returns the logs and the duration actually given to each step.
    """
    world = SimWorld(truths, seed=seed, noise="white")
    cals = [StreamingCalibrator() for _ in truths]
    parts: list[dict[str, np.ndarray]] = []
    durations = []

    def run(step: Step) -> None:
        cols = run_steps(world, [step])
        parts.append(cols)
        for i, cal in enumerate(cals):
            ident = world.identity(i)
            cal.update_batch(cols["time_s"], ident.acc_g(cols["acc_counts"][i]), ident.temp_c(cols["temp_counts"][i]))

    for k, step in enumerate(fast_thermal_steps()):
        run(step)
        spent = step.duration_s
        while any(len(c.segments) < k + 1 for c in cals) and spent < step.duration_s + STEP_TIMEOUT_S:
            run(Step(EXTEND_S, step.position, step.lamp_on, step.chamber_setpoint_c, step.chamber_ramp_c_per_min, step.label))
            spent += EXTEND_S
        durations.append(spent)
    per_dut = ("acc_counts", "temp_counts")  # (n_duts, n, ...): samples on axis 1
    cols = {key: np.concatenate([p[key] for p in parts], axis=1 if key in per_dut else 0) for key in parts[0]}
    return _logs_from_cols(world, cols, "fast-thermal"), durations


@dataclass
class ThermalAcceptance:
    truths: list[DutTruth]
    results: list[dict | None]  # calibrate() output per DUT, None when it could not calibrate
    errors: list[str | None]
    step_durations_s: list[float] = field(default_factory=list)

    def axis_errors(self, method: str) -> tuple[np.ndarray, np.ndarray]:
        """|TDB error| (mg/C) and |TDSF error| (ppm/C) per axis; inf where the DUT has no result."""
        eb, es = [], []
        for truth, res in zip(self.truths, self.results):
            for k, ax in enumerate(AXES):
                if res is None:
                    eb.append(np.inf)
                    es.append(np.inf)
                    continue
                a = res[method]["axes"][ax]
                eb.append(abs(a["tdb_mg_per_c"] - truth.tdb_mg_per_c[k]))
                es.append(abs(a["tdsf_ppm_per_c"] - truth.tdsf_ppm_per_c[k]))
        return np.array(eb), np.array(es)

    def pass_fraction(self, method: str) -> float:
        eb, es = self.axis_errors(method)
        return float(np.mean((eb < TDB_TOL_MG_PER_C) & (es < TDSF_TOL_PPM_PER_C)))

    def td_pairs(self) -> np.ndarray:
        """(streaming TD_i, offline TD_i, streaming noise floor) in mg/C per (DUT, axis, orientation).

        The floor is 3 sigma of the streaming TD_i's own noise: two 1000-sample means of white
        noise noise_g, differenced over the orientation's temperature step (its two segments):
        3 sqrt(2) noise / sqrt(1000) / dT. Below ~0.2 mg/C, 1 % of TD_i is smaller than that.
        """
        out = []
        for truth, res in zip(self.truths, self.results):
            if res is None:
                continue
            n_avg = res["config"]["average_samples"]
            seg_t: dict[int, list[float]] = {}
            for seg in res["segments"]:
                seg_t.setdefault(seg["orientation"], []).append(seg["temp_mean_c"])
            for ax in AXES:
                off = {o["orientation"]: o["td_mg_per_c"] for o in res["offline"]["orientations"][ax]}
                for o in res["streaming"]["orientations"][ax]:
                    temps = seg_t.get(o["orientation"], [0.0])
                    d_t = max(temps) - min(temps)
                    floor = TD_NOISE_K * np.sqrt(2.0) * truth.noise_g * 1e3 / np.sqrt(n_avg) / d_t if d_t > 0 else np.inf
                    out.append((o["td_mg_per_c"], off.get(o["orientation"], np.nan), floor))
        return np.array(out).reshape(-1, 3)

    def params(self, method: str) -> list[tuple[np.ndarray, np.ndarray] | None]:
        out = []
        for res in self.results:
            if res is None:
                out.append(None)
                continue
            ax = res[method]["axes"]
            out.append((np.array([ax[a]["tdb_mg_per_c"] for a in AXES]), np.array([ax[a]["tdsf_ppm_per_c"] for a in AXES])))
        return out


def _calibrate_all(truths, logs, durations=()) -> ThermalAcceptance:
    results, errors = [], []
    for log in logs:
        try:
            results.append(calibrate(log))
            errors.append(None)
        except StationError as exc:
            results.append(None)
            errors.append(str(exc))
    return ThermalAcceptance(truths, results, errors, list(durations))


def population(n: int = N_DUTS, seed: int = SEED) -> list[DutTruth]:
    return draw_population(n, seed, sensor="LIS3DSH")


def fast_thermal_acceptance(n: int = N_DUTS, seed: int = SEED) -> ThermalAcceptance:
    truths = population(n, seed)
    logs, durations = closed_loop_fast_thermal(truths, seed)
    return _calibrate_all(truths, logs, durations)


def open_loop_fast_thermal(n: int = N_DUTS, seed: int = SEED) -> ThermalAcceptance:
    """`station simulate --profile fast-thermal`: fixed step durations, no sequencer."""
    truths = population(n, seed)
    logs = run_profile(SimWorld(truths, seed=seed, noise="white"), "fast-thermal")
    return _calibrate_all(truths, logs, [s.duration_s for s in fast_thermal_steps()])


# ------------------------------------------------------------------------------------------------
# six-position chamber test (martinez2022 4.4, Table 7)


def six_position_sections(truths: list[DutTruth], seed: int) -> list[dict[str, list[tuple[np.ndarray, np.ndarray]]]]:
    """Per DUT, per six-position orientation: the (acc (n,3), temp (n,)) samples of the last
    HOLD_TAIL_S of each chamber hold, in time order."""
    logs = run_profile(SimWorld(truths, seed=seed + 1, noise="white"), "six-position")
    table = step_table("six-position")
    out = []
    for log in logs:
        per_pos: dict[str, list] = {name: [] for name in SIX_POSITION}
        for s in table:
            # the position column guards the window's end against a one-sample rounding of the step
            sel = (log.time_s >= s["t_end_s"] - HOLD_TAIL_S) & (log.time_s < s["t_end_s"]) & (log.position == POSITION_INDEX[s["position"]])
            per_pos[s["position"]].append((log.acc_g[sel], log.temp_c[sel]))
        out.append(per_pos)
    return out


def drift_errors(sections, params) -> tuple[np.ndarray, np.ndarray]:
    """E (eq. 10, mg over the 70 C range) per DUT, orientation and axis: uncompensated and compensated
    with params[i] = (TDB mg/C, TDSF ppm/C) (eq. 13 per sample). Rows of DUTs without params: nan."""
    before, after = [], []
    for per_pos, p in zip(sections, params):
        for name in SIX_POSITION:
            acc_m = np.array([a.mean(axis=0) for a, _ in per_pos[name]])
            temp_m = np.array([t.mean() for _, t in per_pos[name]])
            before.append(drift_error_mg(acc_m, temp_m, FULL_RANGE_C))
            if p is None:
                after.append(np.full(3, np.nan))
                continue
            comp_m = np.array([compensate(a, t, p[0], p[1]).mean(axis=0) for a, t in per_pos[name]])
            after.append(drift_error_mg(comp_m, temp_m, FULL_RANGE_C))
    return np.array(before), np.array(after)


# ------------------------------------------------------------------------------------------------
# SFEM on sfem-24


def effective_truth(truth: DutTruth, temp_c: float) -> tuple[np.ndarray, np.ndarray]:
    """A and b the SFEM sees at temp_c: the 25 C truth with eq. 1's drift folded in.

    raw = Acc0 + dT (TDB + TDSF Acc0) = D (b + inv(A) g) + dT TDB, D = diag(1 + dT TDSF), so
    b_T = D b + dT TDB and A_T = A inv(D).
    """
    dt = temp_c - 25.0
    d = 1.0 + dt * truth.tdsf_ppm_per_c * 1e-6
    b_t = d * truth.bias_g + dt * truth.tdb_mg_per_c * 1e-3
    return truth.A / d[None, :], b_t


@dataclass
class SfemCase:
    serial: str
    temp_c: float
    rmse_before_mg: float
    rmse_after_mg: float
    z: dict[str, np.ndarray]  # |error| / sigma per parameter group
    err: dict[str, np.ndarray]  # error per parameter group
    sigma: dict[str, np.ndarray]
    tol: dict[str, np.ndarray]  # SFEM_SIGMA_K sigma + floor


# small absolute floors (5 ug, 5 ppm, 5 urad) for what no fit sigma covers: the 60 ug LSB and the
# last tenths of a degree of the soak a 1 C thermometer cannot resolve
SFEM_FLOORS = {"b": 5e-6, "scale": 5e-6, "alpha": 5e-6, "rotvec_rad": 5e-6, "A": 5e-6}


def sfem_acceptance(truths: list[DutTruth], seed: int) -> list[SfemCase]:
    logs = run_profile(SimWorld(truths, seed=seed + 2, noise="white"), "sfem-24")
    cases = []
    for truth, log in zip(truths, logs):
        rec = fit_sfem_record(log.time_s, log.acc_g, log.temp_c, log.ref_dir, log.position)
        fit = rec.main
        # the true die temperature of a settled chamber hold: set point + settled self-heating (the
        # 1 C-step thermometer's mean is off by up to ~0.05 C, x TDB up to 1.4 mg/C, not fit noise)
        setpoint = min(CHAMBER_STEPS_C, key=lambda t: abs(t + truth.self_heat_c - fit.temp_c))
        a_t, b_t = effective_truth(truth, setpoint + truth.self_heat_c)
        rot_t, alpha_t, scale_t = decompose_a(a_t)
        est = {"b": fit.b, "scale": fit.scale, "alpha": fit.nonorthogonality, "rotvec_rad": fit.misalignment_rotvec_rad, "A": fit.A}
        tru = {"b": b_t, "scale": scale_t, "alpha": alpha_t, "rotvec_rad": rot_t, "A": a_t}
        err = {k: est[k] - tru[k] for k in est}
        sig = {k: fit.sigma[k] for k in est}
        tol = {k: SFEM_SIGMA_K * sig[k] + SFEM_FLOORS[k] for k in est}
        z = {k: np.abs(err[k]) / sig[k] for k in est}
        cases.append(SfemCase(truth.serial, float(fit.temp_c), fit.rmse_before_mg, fit.rmse_after_mg, z, err, sig, tol))
    return cases


# ------------------------------------------------------------------------------------------------
# tests


@pytest.fixture(scope="module")
def thermal() -> ThermalAcceptance:
    return fast_thermal_acceptance()


@pytest.mark.slow
def test_fast_thermal_32_duts_within_tolerance_both_methods(thermal):
    assert len(thermal.truths) == N_DUTS
    assert all(r is not None for r in thermal.results), [e for e in thermal.errors if e]
    for method in ("streaming", "offline"):
        eb, es = thermal.axis_errors(method)
        frac = thermal.pass_fraction(method)
        print(f"{method}: {frac:.1%} of {eb.size} axes pass; worst TDB err {eb.max():.4f} mg/C, worst TDSF err {es.max():.1f} ppm/C")
        assert frac >= PASS_FRACTION, (method, frac)


@pytest.mark.slow
def test_fast_thermal_streaming_and_offline_td_agree_table5(thermal):
    """Table 5: TD_i of both methods within 1 %; where 1 % of TD_i is below the streaming method's
    own 3-sigma noise (|TD_i| below ~0.2 mg/C), within that noise instead."""
    pairs = thermal.td_pairs()
    assert pairs.shape[0] == N_DUTS * 3 * 2 and np.all(np.isfinite(pairs))
    diff = np.abs(pairs[:, 0] - pairs[:, 1])
    rel = diff / np.abs(pairs[:, 1])
    small = TD_REL_TOL * np.abs(pairs[:, 1]) < pairs[:, 2]
    print(
        f"TD_i streaming vs offline: max rel diff {rel[~small].max():.3%} over {np.sum(~small)} TD_i; "
        f"{np.sum(small)} TD_i below {pairs[small, 2].max() / TD_REL_TOL if small.any() else 0:.3f} mg/C: "
        f"max |diff| {diff[small].max() if small.any() else 0:.4f} mg/C"
    )
    assert np.all(rel[~small] < TD_REL_TOL), np.sort(rel[~small])[-5:]
    assert np.all(diff[small] < pairs[small, 2]), (diff[small], pairs[small, 2])


@pytest.mark.slow
def test_open_loop_profile_is_reported():
    """The fixed-duration profile: every DUT either calibrates or says why in one line."""
    ol = open_loop_fast_thermal(8)
    for res, err in zip(ol.results, ol.errors):
        assert (res is None) != (err is None)
        if err is not None:
            assert "\n" not in err and "segment" in err


@pytest.mark.slow
def test_six_position_drift_error_compensated_below_quarter(thermal):
    sections = six_position_sections(thermal.truths, SEED)
    for method in ("offline", "streaming"):
        before, after = drift_errors(sections, thermal.params(method))
        assert np.all(np.isfinite(after))
        avg_b, avg_a = before.mean(), after.mean()
        print(
            f"{method}: E avg {avg_b:.2f} -> {avg_a:.2f} mg ({drift_error_fs_pct(avg_b):.2f} -> {drift_error_fs_pct(avg_a):.2f} %FS), "
            f"max {before.max():.2f} -> {after.max():.2f} mg"
        )
        assert avg_b > 20.0  # the population drifts like the paper's (42.77 mg average uncompensated)
        assert avg_a < 0.25 * avg_b
        assert after.max() < before.max()


@pytest.mark.slow
def test_sfem_24_parameters_within_noise_limited_tolerance():
    cases = sfem_acceptance(population(), SEED)
    assert len(cases) == N_DUTS
    for c in cases:
        for k in c.err:
            assert np.all(np.abs(c.err[k]) < c.tol[k]), (c.serial, k, c.err[k], c.sigma[k])
    before = np.array([c.rmse_before_mg for c in cases])
    after = np.array([c.rmse_after_mg for c in cases])
    print(f"|a|-1g RMSE before {before.mean():.2f} mg, after {after.mean():.4f} mg (max {after.max():.4f})")
    assert 20.0 < before.mean() < 80.0  # sensors2023 Table 6: ~45 mg uncalibrated
    assert np.all(after < 0.2)  # Table 6: ~0.2 mg calibrated; here the noise floor of the means
