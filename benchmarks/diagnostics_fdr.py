"""False-discovery and hidden-effect table of `station diagnose` with the realistic noise.

    python benchmarks/diagnostics_fdr.py [--seeds 20] [--odr HZ] [--effects] [--jobs 2]
    python benchmarks/diagnostics_fdr.py --suite --jobs 2    # 48 clean logs: 3 plants x 2 noise levels x 8 seeds
    python benchmarks/diagnostics_fdr.py --profiles validation,fast-thermal,plant2 --noise 1,2 --seeds 8
    python benchmarks/diagnostics_fdr.py --speed       # 10-hour validation log, wall and CPU time

Part 1 (always): clean logs (one DUT, NO hidden effect), one per profile x noise level x seed
(seeds 0..N-1). Prints, per log, what was admitted, the best candidate's held-out gain, delta BIC
and p-value, and the diagnose time; then how many logs admitted nothing and the total number of
admitted effects ("admitted effects in N clean logs: k; target <= 1"). Profiles:
- validation: the simulator's `validation` profile (drivers/sim/profiles.py; 15.7 h, six cycles);
- fast-thermal: the simulator's `fast-thermal` profile (89 min, lamp heating, P and N);
- plant2: tests/diag_plant2.py, an independent plant (its own physics and noise code: six
  orientations, four ramp rates, plate moves logged at position -1; 10.6 h).
Noise levels (--noise): `1` (= `realistic`: the simulator's model of the sensor class, LIS3DSH;
plant2's own white 0.7 mg + 4 ug/sqrt(s) random walk + 40 ug flicker) and `2` (every noise term
doubled: white, random walk, flicker). The default is the original table: validation, realistic,
20 seeds. --suite: validation,fast-thermal,plant2 x 1,2 x 8 seeds = 48 logs.

Part 2 (--effects): every hidden effect of the simulator on its own (seed 3): ranked first?
admitted? held-out after the admitted staircase vs the control floor (the same DUT and noise
without the effect: baseline held-out RMS). tests/diag_plant2.py's effects: diagnostics_effects.py.

--odr: sample rate of the logs (default: the sensor's 3.125 Hz; 1 Hz is ~3x faster and keeps the
noise models' random walk per sqrt(s)). --jobs N: N logs at a time (processes, one BLAS thread
each); 2 cores make the 48-log suite about twice as fast.
"""

from __future__ import annotations

import argparse
import dataclasses
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import diag_helpers as H  # noqa: E402
from drivers.sim.physics import HIDDEN_EFFECTS  # noqa: E402
from station.diagnostics.ranking import diagnose  # noqa: E402

PROFILES = ("validation", "fast-thermal", "plant2")
SUITE = {"profiles": "validation,fast-thermal,plant2", "noise": "1,2", "seeds": 8}


def _noise_scale(level: str) -> float:
    return 1.0 if level in ("realistic", "1", "1x") else float(level.rstrip("x"))


def clean_log(profile: str, level: str, seed: int, odr_hz: float | None):
    """One clean log (no hidden effect) of a profile at a noise level."""
    scale = _noise_scale(level)
    if profile == "plant2":
        import diag_plant2 as G

        log, _ = G.make_log((), seed, rate_hz=odr_hz or G.RATE_HZ, noise_scale=scale, keep_arrays=False)
        return log
    from drivers.sim.physics import draw_population, noise_model
    from drivers.sim.profiles import run_profile
    from drivers.sim.world import EnvConfig, SimWorld

    truths = draw_population(1, seed)
    nm = "realistic"  # exactly H.validation_logs's world at 1x
    if scale != 1.0:
        base = noise_model("realistic", truths[0].sensor)
        nm = dataclasses.replace(base, name=f"{base.name}-x{scale:g}", white_scale=scale * base.white_scale,
                                 bias_rw_g_per_sqrt_s=scale * base.bias_rw_g_per_sqrt_s, flicker_g=scale * base.flicker_g,
                                 note=f"{base.name} with every noise term x{scale:g}")
    return run_profile(SimWorld(truths, env=EnvConfig(), seed=seed, noise=nm, odr_hz=odr_hz), profile)[0]


def _fdr_one(job: tuple) -> dict:
    profile, level, seed, odr = job
    t_gen = time.perf_counter()
    try:
        lg = clean_log(profile, level, seed, odr)
        t0 = time.perf_counter()
        doc = diagnose([lg]).to_json()
    except Exception as exc:  # report the log, keep the table going
        return {"job": job, "error": f"{type(exc).__name__}: {exc}", "dt": time.perf_counter() - t_gen}
    dt = time.perf_counter() - t0
    ranked = [r for r in doc["ranking"] if r.get("heldout_gain_rel") is not None]
    best = max(ranked, key=lambda r: r["heldout_gain_rel"]) if ranked else None
    return {"job": job, "admitted": list(doc["admitted"]), "best": best and {k: best.get(k) for k in (
        "effect", "heldout_gain_rel", "delta_bic", "score_p")}, "base": doc["baseline"]["heldout_rms_mg"],
        "dt": dt, "n": len(lg)}


def _map(fn, jobs: list, n_jobs: int):
    """Results in job order, printed as they come when run in processes."""
    if n_jobs <= 1:
        for j in jobs:
            yield fn(j)
        return
    os.environ["OPENBLAS_NUM_THREADS"] = os.environ["OMP_NUM_THREADS"] = "1"  # the spawned workers inherit it
    with mp.get_context("spawn").Pool(n_jobs) as pool:
        yield from pool.imap(fn, jobs, chunksize=1)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=None, help="seeds per profile and noise level (default 20; --suite 8)")
    ap.add_argument("--odr", type=float, default=None)
    ap.add_argument("--effects", action="store_true", help="also the hidden-effect table")
    ap.add_argument("--speed", action="store_true", help="only time a 10-hour validation log (117 k samples)")
    ap.add_argument("--profiles", default=None, help=f"comma-separated, of {', '.join(PROFILES)} (default validation)")
    ap.add_argument("--noise", default=None, help="comma-separated noise levels: 1 (realistic), 2 (every term x2)")
    ap.add_argument("--suite", action="store_true", help="48 clean logs: " + ", ".join(f"{k} {v}" for k, v in SUITE.items()))
    ap.add_argument("--jobs", type=int, default=1, help="logs diagnosed at a time (processes)")
    args = ap.parse_args()
    if args.speed:
        return speed()
    profiles = (args.profiles or (SUITE["profiles"] if args.suite else "validation")).split(",")
    levels = (args.noise or (SUITE["noise"] if args.suite else "realistic")).split(",")
    seeds = args.seeds if args.seeds is not None else (SUITE["seeds"] if args.suite else 20)
    for p in profiles:
        if p not in PROFILES:
            ap.error(f"unknown profile {p!r} (known: {', '.join(PROFILES)})")
    for lv in levels:
        try:
            _noise_scale(lv)
        except ValueError:
            ap.error(f"unknown noise level {lv!r} (1, realistic, 2, ...)")

    jobs = [(p, lv, s, args.odr) for p in profiles for lv in levels for s in range(seeds)]
    print(f"false discoveries: {len(jobs)} clean logs (no hidden effect): {', '.join(profiles)} x noise "
          f"{', '.join(levels)} x seeds 0..{seeds - 1}, odr {args.odr or 'sensor'}, --jobs {args.jobs}")
    print(f"{'profile':<13}{'noise':>10}{'seed':>5}  {'admitted':<22}{'best candidate':<20}{'gain %':>8}{'dBIC':>9}"
          f"{'p':>10}{'base mg':>9}{'time s':>8}")
    clean = n_admitted = errors = 0
    t_all = time.perf_counter()
    for r in _map(_fdr_one, jobs, args.jobs):
        p, lv, seed, _ = r["job"]
        if "error" in r:
            errors += 1
            print(f"{p:<13}{lv:>10}{seed:>5}  ERROR {r['error'][:150]}", flush=True)
            continue
        b = r["best"] or {"effect": "-", "heldout_gain_rel": float("nan"), "delta_bic": float("nan"), "score_p": float("nan")}
        clean += not r["admitted"]
        n_admitted += len(r["admitted"])
        print(f"{p:<13}{lv:>10}{seed:>5}  {','.join(r['admitted']) or 'none':<22}{b['effect']:<20}"
              f"{100 * b['heldout_gain_rel']:>8.1f}{b['delta_bic']:>9.1f}{b['score_p']:>10.2g}"
              f"{r['base']:>9.4f}{r['dt']:>8.1f}", flush=True)
    n_ok = len(jobs) - errors
    print(f"nothing admitted in {clean} of {n_ok} clean logs" + (f" ({errors} failed to diagnose)" if errors else ""))
    print(f"admitted effects in {n_ok} clean logs: {n_admitted}; target <= 1")
    print(f"time: {time.perf_counter() - t_all:.0f} s wall")

    if args.effects:
        print()
        print("hidden effects (seed 3, realistic noise): held-out after the admitted staircase vs control floor")
        logs, _ = H.validation_logs((), seed=3, noise="realistic", odr_hz=args.odr)
        floor = diagnose(logs, candidates=[]).to_json()["baseline"]["heldout_rms_mg"]
        print(f"control floor (baseline held-out, no effect): {floor:.4f} mg")
        print(f"{'effect':<20}{'ranked first':<20}{'admitted':<28}{'staircase held-out mg':<30}{'ratio':>7}")
        for e in HIDDEN_EFFECTS:
            logs, _ = H.validation_logs((e,), seed=3, noise="realistic", odr_hz=args.odr)
            doc = diagnose(logs).to_json()
            st = [s["heldout_rms_mg"] for s in doc["admitted_staircase"]]
            mono = all(a > b for a, b in zip(st, st[1:]))
            print(f"{e:<20}{doc['ranking'][0]['effect']:<20}{','.join(doc['admitted']) or 'none':<28}"
                  f"{' -> '.join(f'{x:.3f}' for x in st) + ('' if mono else ' (NOT monotone)'):<30}"
                  f"{st[-1] / floor:>7.3f}", flush=True)
    return 0


def speed() -> int:
    """Wall and CPU time of diagnose() on the first 10 h (117 k samples at 3.125 Hz) of a clean
    validation log with the realistic noise, 8 built-in candidates (the target: <= 2 s)."""
    import numpy as np

    from contracts.logfile import DutLog

    logs, _ = H.validation_logs((), seed=1, noise="realistic")
    lg = logs[0]
    n = min(len(lg), 117_000)
    cut = DutLog(time_s=lg.time_s[:n], acc_g=lg.acc_g[:n], temp_c=lg.temp_c[:n], meta=dict(lg.meta),
                 lamp=None if lg.lamp is None else lg.lamp[:n], position=lg.position[:n])
    t0, c0 = time.perf_counter(), time.process_time()
    doc = diagnose([cut]).to_json()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    print(f"diagnose of a {n}-sample ({n / 3.125 / 3600:.1f} h) validation log, {len(doc['ranking'])} ranked "
          f"candidates: {wall:.1f} s wall, {cpu:.1f} s CPU (OPENBLAS_NUM_THREADS={np.__config__ and __import__('os').environ.get('OPENBLAS_NUM_THREADS', 'unset')})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
