"""Do the printed uncertainties cover the truth? (docs/verdicts.md, "Uncertainty budget")

Simulated DUTs (drivers/sim, the default `realistic` noise: white + bias random walk + flicker, the
LIS3DSH's 1 C temperature steps, die lag behind the plate, self-heating) run the fast-thermal
profile open loop; `station.science.thermal_calibration.calibrate` fits each log; the truth is the
simulator's parameters (draw_population). Then the same world goes on: lamp off 2 min (program
step), lamp on at N until the DUT's own temperature rose 15 C (the sequencer's heat rule), 20 s
settle not judged; the board's output is compensated as the board does it (eq. 13 with its own
1 C-step reading, rounded to the LSB) with the FITTED coefficients and judged by
`station.science.verify.verify_compensated`. The true verified E is eq. 10 with fine sections over
-10..60 C of the true compensated output (true eq. 1 + the true bias_t2, minus the fitted
coefficients' compensation) at that position.

Two populations: linear parts (TDB, TDSF, verified E) and parts with quadratic bias drift
(bias_t2: verified E only, where the extrapolation from the 15 C heat to 70 C matters).

    .venv/bin/python benchmarks/coverage.py [--duts 24] [--seed 1]
    .venv/bin/python benchmarks/coverage.py --characterise     # the BiasWander numbers of offline_fit

Prints, per figure: n, fraction of |error| <= 2u, RMS(error/u), and the same with the spec's u_sys.
Not a timed test: ~1 s of CPU per 10 DUTs.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.sim.physics import NoiseModel, draw_population, noise_model  # noqa: E402
from drivers.sim.profiles import Step, run_profile, run_steps  # noqa: E402
from drivers.sim.world import SimWorld  # noqa: E402
from contracts.positions import GRAVITY_DIRECTIONS, POSITION_INDEX  # noqa: E402
from station.science.part_noise import wander_of_budget  # noqa: E402
from station.science.thermal_calibration import calibrate  # noqa: E402
from station.science.thermal_model import compensate  # noqa: E402
from station.science.verify import VerifyCriteria, verify_compensated  # noqa: E402
from contracts.types import AXES, T_REF_C  # noqa: E402

N_POS = POSITION_INDEX["N"]
P_POS = POSITION_INDEX["P"]
HEAT_C = 15.0
SETTLE_S = 20.0


def true_verified_e_mg(truth, tdb_fit, tdsf_fit, position: int, low_c: float = -10.0, high_c: float = 60.0) -> np.ndarray:
    """Eq. 10 with fine (0.01 C) sections over [low, high] of the true compensated output (3,)."""
    temp = np.linspace(low_c, high_c, 7001)
    acc0 = truth.acc0_g(GRAVITY_DIRECTIONS[position])
    dt = (temp - T_REF_C)[:, None]
    acc = acc0 + dt * (truth.tdb_mg_per_c * 1e-3 + truth.tdsf_ppm_per_c * 1e-6 * acc0)
    if "bias_t2" in truth.effects:
        acc = acc + np.asarray(truth.effects["bias_t2"]["c2_mg_per_c2"]) * 1e-3 * dt ** 2
    comp = compensate(acc, temp, tdb_fit, tdsf_fit)
    return np.sum(np.abs(np.diff(comp, axis=0)), axis=0) * 1e3


def true_bow_mg(truth, range_c: float = 70.0) -> np.ndarray:
    """|c2| R^2 / 8 of the true bias curvature (3,): what the residual report's bow estimates."""
    c2 = np.asarray(truth.effects.get("bias_t2", {}).get("c2_mg_per_c2", [0.0, 0.0, 0.0]), dtype=np.float64)
    return np.abs(c2) * range_c ** 2 / 8.0


def heat_window(temp_c: np.ndarray, time_s: np.ndarray, t_start: float, heat_c: float = HEAT_C,
                settle_s: float = SETTLE_S, n_edge: int = 8) -> slice:
    """Samples the station judges: after settle_s, until the DUT's own rise (median of the latest
    n_edge minus median of the first n_edge after the start) reaches heat_c (sequencer rule)."""
    k0 = int(np.searchsorted(time_s, t_start))
    first = float(np.median(temp_c[k0:k0 + n_edge]))
    k1 = len(temp_c)
    for k in range(k0 + n_edge, len(temp_c)):
        if time_s[k] - t_start >= settle_s and float(np.median(temp_c[k - n_edge + 1:k + 1])) - first >= heat_c:
            k1 = k + 1
            break
    ks = int(np.searchsorted(time_s, t_start + settle_s, side="right"))
    return slice(ks, k1)


def scaled_noise(scale: float, sensor: str = "LIS3DSH") -> NoiseModel:
    """The sensor class's realistic noise with white noise, random walk and flicker all x scale."""
    m = noise_model("realistic", sensor)
    return replace(m, name=f"{m.name} x{scale:g}", bias_rw_g_per_sqrt_s=m.bias_rw_g_per_sqrt_s * scale,
                   flicker_g=m.flicker_g * scale, white_scale=m.white_scale * scale)


def simulate(n_duts: int, seed: int, effects=(), noise_scale: float = 1.0, bow_mg: float | None = None,
             wander: str = "auto") -> list[dict]:
    """One population: per DUT its truth, calibration and verification (module doc). noise_scale
    multiplies every noise term of the class; bow_mg: every axis gets a bias curvature of this bow
    over 70 C (random sign) instead of the drawn one."""
    truths = draw_population(n_duts, seed, effects=effects + (("bias_t2",) if bow_mg else ()))
    if bow_mg:
        for i, t in enumerate(truths):
            sign = np.random.default_rng([seed, i, 0xB0]).choice([-1.0, 1.0], 3)
            t.effects["bias_t2"] = {"c2_mg_per_c2": (sign * bow_mg * 8.0 / 70.0 ** 2).tolist()}
    world = SimWorld(truths, seed=seed, noise=scaled_noise(noise_scale))
    logs = run_profile(world, "fast-thermal")
    t_prog = world.time_s
    cols = run_steps(world, [Step(120.0, N_POS, False, label="program"), Step(1500.0, N_POS, True, label="verify hot")])
    t_heat = t_prog + 120.0
    out = []
    for i, (truth, log) in enumerate(zip(truths, logs)):
        res = calibrate(log, wander=wander)
        tdb = np.array([res["axes"][a]["tdb_mg_per_c"] for a in AXES])
        tdsf = np.array([res["axes"][a]["tdsf_ppm_per_c"] for a in AXES])
        lsb_g = truth.ug_per_lsb * 1e-6
        acc_raw = cols["acc_counts"][i] * lsb_g
        temp = (cols["temp_counts"][i] - truth.t_lsb_at_25c) / truth.t_lsb_per_c + T_REF_C
        tdb32, tdsf32 = np.float32(tdb).astype(float), np.float32(tdsf).astype(float)  # as stored in NVM
        comp = np.rint(compensate(acc_raw, temp, tdb32, tdsf32) / lsb_g) * lsb_g
        w = heat_window(temp, cols["time_s"], t_heat)
        # as the daemon does (program_verify): the part's wander from its calibration's budget
        ver = verify_compensated(comp[w], temp[w], None, VerifyCriteria(), time_s=cols["time_s"][w],
                                 wander=wander_of_budget(res["uncertainty"]) or "auto").to_json()
        out.append({"truth": truth, "calibration": res, "verification": ver,
                    "e_true_mg": true_verified_e_mg(truth, tdb32, tdsf32, N_POS),
                    "cal_e_true_mg": np.maximum(true_verified_e_mg(truth, tdb, tdsf, P_POS),
                                                true_verified_e_mg(truth, tdb, tdsf, N_POS)),
                    "bow_true_mg": true_bow_mg(truth)})
    return out


def _row(name: str, err: np.ndarray, u: np.ndarray, u_sys: float = 0.0) -> dict:
    m = np.isfinite(err) & np.isfinite(u) & (u > 0)
    z = err[m] / u[m]
    us = np.hypot(u[m], u_sys)
    zs = err[m] / us
    return {"figure": name, "n": int(m.sum()), "within_2u": float(np.mean(np.abs(z) <= 2.0)),
            "rms_err_over_u": float(np.sqrt(np.mean(z * z))),
            "within_2u_with_usys": float(np.mean(np.abs(zs) <= 2.0)),
            "rms_err_over_u_with_usys": float(np.sqrt(np.mean(zs * zs))),
            "rms_err": float(np.sqrt(np.mean(err[m] ** 2))), "rms_u": float(np.sqrt(np.mean(u[m] ** 2)))}


def chord_truth(truth, cal: dict, k: int) -> tuple[float, float]:
    """The TDB (mg/C) and TDSF (ppm/C) of axis k that the fast method measures on this part: for a
    linear part its coefficients; for a part with a bias curvature c2 the chord over the
    calibration's own data, each orientation's TD_i moved by c2 * chord_x (offline_fit; the
    measurand eq. 13 compensates with, docs/verdicts.md "Curvature"), through the same two-point
    line (eqs. 8/9) over the orientations' true acc0."""
    c2 = truth.effects.get("bias_t2", {}).get("c2_mg_per_c2")
    if not c2:
        return float(truth.tdb_mg_per_c[k]), float(truth.tdsf_ppm_per_c[k])
    chord = cal["uncertainty"]["chord_x_c"]
    pts = []
    for od in cal["offline"]["orientations"][AXES[k]]:
        acc0 = od["acc0_g"]
        td = truth.tdb_mg_per_c[k] + truth.tdsf_ppm_per_c[k] * 1e-3 * acc0 + c2[k] * chord[str(od["orientation"])]
        pts.append((acc0, td))
    (a1, t1), (a2, t2) = pts[0], pts[-1]
    tdsf_mg = (t1 - t2) / (a1 - a2)
    return float(t1 - tdsf_mg * a1), float(tdsf_mg * 1e3)


def population_rows(pop: list[dict], name: str) -> list[dict]:
    """Coverage of every figure with a sigma, against the simulator's truth (module doc)."""
    cols: dict[str, tuple[list, list]] = {k: ([], []) for k in ("TDB mg/C", "TDSF ppm/C", "E_FS %FS", "bow mg",
                                                                   "verified E %FS")}
    for d in pop:
        cal, ver = d["calibration"], d["verification"]
        for k, a in enumerate(AXES):
            ax, r = cal["axes"][a], cal["residual"]["axes"][a]
            tdb_true, tdsf_true = chord_truth(d["truth"], cal, k)
            cols["TDB mg/C"][0].append(ax["tdb_mg_per_c"] - tdb_true)
            cols["TDB mg/C"][1].append(ax["tdb_sigma_mg_per_c"])
            if tdsf_true < 0 or ax["tdsf_ppm_per_c"] < 0:  # a clamped zero is no estimate
                cols["TDSF ppm/C"][0].append(ax["tdsf_ppm_per_c"] - tdsf_true)
                cols["TDSF ppm/C"][1].append(ax["tdsf_sigma_ppm_per_c"])
            cols["E_FS %FS"][0].append(_num(r["drift_error_fs_pct"]) - d["cal_e_true_mg"][k] / 20.0)
            cols["E_FS %FS"][1].append(_num(r["drift_error_fs_sigma_pct"]))
            cols["bow mg"][0].append(_num(r["bow_mg"]) - d["bow_true_mg"][k])
            cols["bow mg"][1].append(_num(r["bow_sigma_mg"]))
            cols["verified E %FS"][0].append(ver["e_after_fs_pct"][a] - d["e_true_mg"][k] / 20.0)  # 2000 mg = 100 %FS
            cols["verified E %FS"][1].append(ver["e_after_fs_sigma_pct"][a])
    return [dict(_row(f"{fig} ({name})", np.array(e, dtype=float), np.array(u, dtype=float)), population=name)
            for fig, (e, u) in cols.items()]


def _num(v) -> float:
    return float("nan") if v is None else float(v)


POPULATIONS: dict[str, dict] = {
    "0.4x noise": {"noise_scale": 0.4},
    "1x noise": {"noise_scale": 1.0},
    "3x noise": {"noise_scale": 3.0},
    "curved": {"effects": ("bias_t2",)},
}


def coverage(n_duts: int = 24, seed: int = 1, populations=tuple(POPULATIONS), wander: str = "auto") -> list[dict]:
    """The coverage rows of every population (module doc)."""
    rows: list[dict] = []
    for k, name in enumerate(populations):
        rows += population_rows(simulate(n_duts, seed + 1000 * k, wander=wander, **POPULATIONS[name]), name)
    return rows


def print_table(rows: list[dict]) -> None:
    print(f"{'figure':32s} {'n':>4s} {'|err|<=2u':>10s} {'RMS(err/u)':>11s} {'rms err':>10s} {'rms u':>10s}"
          f" {'<=2u w/ usys':>13s} {'RMS w/ usys':>12s}")
    for r in rows:
        print(f"{r['figure']:32s} {r['n']:4d} {r['within_2u']:10.1%} {r['rms_err_over_u']:11.2f} {r['rms_err']:10.4g}"
              f" {r['rms_u']:10.4g} {r['within_2u_with_usys']:13.1%} {r['rms_err_over_u_with_usys']:12.2f}")


def characterise(hours: float = 8.0, n_boards: int = 6, seed: int = 11) -> None:
    """The BiasWander constants of station/science/offline_fit.py: static logs, pooled per class."""
    from station.science.offline_fit import characterise_bias_wander

    for sensor in ("LIS3DSH", "ADXL355"):
        tr = draw_population(n_boards, seed, sensor=sensor)
        w = SimWorld(tr, seed=seed)
        cols = run_steps(w, [Step(hours * 3600.0, 0, False)])
        k = int(1800 * w.odr_hz)  # the first 30 min warm up (self-heating moves the temperature)
        ws = [characterise_bias_wander(cols["time_s"][k:], cols["acc_counts"][i][k:] * tr[i].ug_per_lsb * 1e-6)
              for i in range(n_boards)]
        print(f"{sensor}: white {np.mean([x.white_ug_per_sqrt_hz for x in ws]):.1f} ug/sqrt(Hz), random walk "
              f"{np.sqrt(np.mean([x.rw_g_per_sqrt_s ** 2 for x in ws])):.3g} g/sqrt(s), flicker "
              f"{np.sqrt(np.mean([x.flicker_g ** 2 for x in ws])):.3g} g ({n_boards} boards x {hours:g} h)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duts", type=int, default=24)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--characterise", action="store_true")
    ap.add_argument("--wander", choices=["auto", "class"], default="auto",
                    help="auto: each part's noise measured on it (the station's); class: the class constant")
    ap.add_argument("--population", action="append", choices=list(POPULATIONS), help="only these (repeatable)")
    args = ap.parse_args(argv)
    t0 = time.process_time()
    if args.characterise:
        characterise()
    else:
        print(f"{args.duts} simulated LIS3DSH DUTs x 3 axes per population (realistic noise scaled), seed {args.seed}")
        print_table(coverage(args.duts, args.seed, tuple(args.population or POPULATIONS), args.wander))
    print(f"[{time.process_time() - t0:.1f} s CPU]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
