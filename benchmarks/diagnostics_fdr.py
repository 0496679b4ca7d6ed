"""False-discovery and hidden-effect table of `station diagnose` with the realistic noise.

    python benchmarks/diagnostics_fdr.py [--seeds 20] [--odr HZ] [--effects]
    python benchmarks/diagnostics_fdr.py --speed       # 10-hour validation log, wall and CPU time

Part 1 (always): N simulated validation-profile logs (drivers/sim/profiles.py `validation`, one DUT,
15.7 h) with NO hidden effect and the `realistic` noise model (bias random walk + flicker), seeds
0..N-1. Prints, per seed, what was admitted, the best candidate's held-out gain, delta BIC and
p-value, and the diagnose time; then how many logs admitted nothing (the target: >= 19 of 20).

Part 2 (--effects): every hidden effect of the simulator on its own (seed 3): ranked first?
admitted? held-out after the admitted staircase vs the control floor (the same DUT and noise
without the effect: baseline held-out RMS).

--odr: sample rate of the simulated logs (default: the sensor's 3.125 Hz; 1 Hz is ~3x faster and
keeps the noise model's random walk per sqrt(s)).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import diag_helpers as H  # noqa: E402
from drivers.sim.physics import HIDDEN_EFFECTS  # noqa: E402
from station.diagnostics.ranking import diagnose  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--odr", type=float, default=None)
    ap.add_argument("--effects", action="store_true", help="also the hidden-effect table")
    ap.add_argument("--speed", action="store_true", help="only time a 10-hour validation log (117 k samples)")
    args = ap.parse_args()
    if args.speed:
        return speed()

    print(f"false discoveries: validation profile, no hidden effect, realistic noise, odr {args.odr or 'sensor'}")
    print(f"{'seed':>4}  {'admitted':<22}{'best candidate':<20}{'gain %':>8}{'dBIC':>9}{'p':>10}{'base mg':>9}{'time s':>8}")
    clean = 0
    for seed in range(args.seeds):
        logs, _ = H.validation_logs((), seed=seed, noise="realistic", odr_hz=args.odr)
        t0 = time.perf_counter()
        doc = diagnose(logs).to_json()
        dt = time.perf_counter() - t0
        best = max(doc["ranking"], key=lambda r: r["heldout_gain_rel"] or -1)
        clean += not doc["admitted"]
        print(f"{seed:>4}  {','.join(doc['admitted']) or 'none':<22}{best['effect']:<20}"
              f"{100 * best['heldout_gain_rel']:>8.1f}{best['delta_bic']:>9.1f}{best['score_p']:>10.2g}"
              f"{doc['baseline']['heldout_rms_mg']:>9.4f}{dt:>8.1f}", flush=True)
    print(f"nothing admitted in {clean} of {args.seeds} clean logs")

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
