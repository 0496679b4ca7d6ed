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
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.sim.physics import draw_population  # noqa: E402
from drivers.sim.profiles import Step, run_profile, run_steps  # noqa: E402
from drivers.sim.world import SimWorld  # noqa: E402
from contracts.positions import GRAVITY_DIRECTIONS, POSITION_INDEX  # noqa: E402
from station.science.thermal_calibration import calibrate  # noqa: E402
from station.science.thermal_model import compensate  # noqa: E402
from station.science.verify import VerifyCriteria, verify_compensated  # noqa: E402
from station.decisions.limits import U_SYS_TDB_MG_PER_C, U_SYS_TDSF_PPM_PER_C  # noqa: E402
from contracts.types import AXES, T_REF_C  # noqa: E402

N_POS = POSITION_INDEX["N"]
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


def simulate(n_duts: int, seed: int, effects=()) -> list[dict]:
    """One population: per DUT its truth, calibration and verification (module doc)."""
    truths = draw_population(n_duts, seed, effects=effects)
    world = SimWorld(truths, seed=seed)  # default noise: realistic
    logs = run_profile(world, "fast-thermal")
    t_prog = world.time_s
    cols = run_steps(world, [Step(120.0, N_POS, False, label="program"), Step(1500.0, N_POS, True, label="verify hot")])
    t_heat = t_prog + 120.0
    out = []
    for i, (truth, log) in enumerate(zip(truths, logs)):
        res = calibrate(log)
        tdb = np.array([res["axes"][a]["tdb_mg_per_c"] for a in AXES])
        tdsf = np.array([res["axes"][a]["tdsf_ppm_per_c"] for a in AXES])
        lsb_g = truth.ug_per_lsb * 1e-6
        acc_raw = cols["acc_counts"][i] * lsb_g
        temp = (cols["temp_counts"][i] - truth.t_lsb_at_25c) / truth.t_lsb_per_c + T_REF_C
        tdb32, tdsf32 = np.float32(tdb).astype(float), np.float32(tdsf).astype(float)  # as stored in NVM
        comp = np.rint(compensate(acc_raw, temp, tdb32, tdsf32) / lsb_g) * lsb_g
        w = heat_window(temp, cols["time_s"], t_heat)
        ver = verify_compensated(comp[w], temp[w], None, VerifyCriteria(), time_s=cols["time_s"][w]).to_json()
        out.append({"truth": truth, "calibration": res, "verification": ver,
                    "e_true_mg": true_verified_e_mg(truth, tdb32, tdsf32, N_POS)})
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


def coverage(n_duts: int = 24, seed: int = 1) -> list[dict]:
    """The coverage rows: TDB and TDSF (linear parts), verified E_FS (linear, curved, all)."""
    lin = simulate(n_duts, seed)
    cur = simulate(n_duts, seed + 1000, effects=("bias_t2",))
    eb, ub, ef, uf = [], [], [], []
    for d in lin:
        for k, a in enumerate(AXES):
            ax = d["calibration"]["axes"][a]
            eb.append(ax["tdb_mg_per_c"] - d["truth"].tdb_mg_per_c[k])
            ub.append(ax["tdb_sigma_mg_per_c"])
            ef.append(ax["tdsf_ppm_per_c"] - d["truth"].tdsf_ppm_per_c[k])
            uf.append(ax["tdsf_sigma_ppm_per_c"])

    def ver(pop):
        e, u = [], []
        for d in pop:
            v = d["verification"]
            for k, a in enumerate(AXES):
                e.append(v["e_after_fs_pct"][a] - d["e_true_mg"][k] / 20.0)  # 2000 mg = 100 %FS
                u.append(v["e_after_fs_sigma_pct"][a])
        return np.array(e), np.array(u)

    el, ul = ver(lin)
    ec, uc = ver(cur)
    return [
        _row("TDB mg/C", np.array(eb), np.array(ub), U_SYS_TDB_MG_PER_C),
        _row("TDSF ppm/C", np.array(ef), np.array(uf), U_SYS_TDSF_PPM_PER_C),
        _row("verified E %FS (linear)", el, ul),
        _row("verified E %FS (bias_t2)", ec, uc),
        _row("verified E %FS (all)", np.concatenate([el, ec]), np.concatenate([ul, uc])),
    ]


def print_table(rows: list[dict]) -> None:
    print(f"{'figure':28s} {'n':>4s} {'|err|<=2u':>10s} {'RMS(err/u)':>11s} {'rms err':>10s} {'rms u':>10s}"
          f" {'<=2u w/ usys':>13s} {'RMS w/ usys':>12s}")
    for r in rows:
        print(f"{r['figure']:28s} {r['n']:4d} {r['within_2u']:10.1%} {r['rms_err_over_u']:11.2f} {r['rms_err']:10.4g}"
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
    args = ap.parse_args(argv)
    t0 = time.process_time()
    if args.characterise:
        characterise()
    else:
        print(f"{args.duts} linear + {args.duts} bias_t2 simulated LIS3DSH DUTs x 3 axes, realistic noise, seed {args.seed}")
        print_table(coverage(args.duts, args.seed))
    print(f"[{time.process_time() - t0:.1f} s CPU]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
