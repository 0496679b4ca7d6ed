"""Speed and memory of `station diagnose` against its targets on the 2-core station PC.

    .venv/bin/python benchmarks/diagnostics_speed.py            # all three figures
    .venv/bin/python benchmarks/diagnostics_speed.py --case one # only the single-log figure

Cases (simulated validation-profile logs with the `realistic` noise: bias random walk + flicker,
cut to their first 10 h = 117 k samples at 3.125 Hz; seed 1):
- one:   full ranking + admitted staircase of one log with a hidden hysteresis   (target <= 2 s)
- add:   `--add` of two effects on the ranked state of that log (a model not fitted yet: the
         engineer's second click; the first click on a ranked candidate is already fitted) (target <= 0.5 s)
- batch: full ranking of a batch of 8 DUTs diagnosed together                      (target <= 10 s)

Each case runs in a fresh child process, so its peak resident memory (ru_maxrss) is its own; the
log is simulated before the clock starts.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

N_SAMPLES = 117_000
TARGETS_S = {"one": 2.0, "add": 0.5, "batch": 10.0}


def _logs(n_duts: int, effects=("hysteresis",)):
    import diag_helpers as H
    from contracts.logfile import DutLog

    logs, _ = H.validation_logs(effects, n_duts=n_duts, seed=1, noise="realistic")
    out = []
    for lg in logs:
        n = min(len(lg), N_SAMPLES)
        out.append(DutLog(time_s=lg.time_s[:n], acc_g=lg.acc_g[:n], temp_c=lg.temp_c[:n], meta=dict(lg.meta),
                          lamp=None if lg.lamp is None else lg.lamp[:n], position=lg.position[:n]))
    return out


def child(case: str) -> dict:
    from station.diagnostics import ranking

    logs = _logs(8 if case == "batch" else 1)
    t0, c0 = time.perf_counter(), time.process_time()
    rep = ranking.diagnose(logs)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    out = {"case": case, "samples": sum(len(lg) for lg in logs), "duts": len(logs), "admitted": rep.admitted}
    if case == "add":
        # the engineer's second click: a model of two effects nothing fitted yet (a first click on a
        # ranked candidate is already fitted by the ranking and answers at once)
        add = [r["effect"] for r in rep.ranking if not r["admitted"]][:2]
        t0, c0 = time.perf_counter(), time.process_time()
        refit = getattr(ranking, "with_added", None)
        rep2 = refit(rep, add) if refit else ranking.diagnose(logs, add=add)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        out["added"] = add
        out["staircase"] = [s["heldout_rms_mg"] for s in rep2.to_json()["staircase"]]
    out.update(wall_s=round(wall, 3), cpu_s=round(cpu, 3),
               peak_rss_mb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", choices=["one", "add", "batch", "all"], default="all")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child)))
        return 0
    cases = ["one", "add", "batch"] if args.case == "all" else [args.case]
    print(f"{'case':<7}{'DUTs':>5}{'samples':>9}{'wall s':>8}{'CPU s':>7}{'target s':>9}{'peak RSS MB':>12}  admitted")
    ok = True
    for case in cases:
        res = subprocess.run([sys.executable, __file__, "--child", case], capture_output=True, text=True, cwd=ROOT)
        if res.returncode:
            print(res.stderr[-2000:])
            return 1
        r = json.loads(res.stdout.strip().splitlines()[-1])
        met = r["wall_s"] <= TARGETS_S[case]
        ok &= met
        extra = f"  +{' +'.join(r['added'])}: held-out {r['staircase']}" if case == "add" else ""
        print(f"{case:<7}{r['duts']:>5}{r['samples']:>9}{r['wall_s']:>8.2f}{r['cpu_s']:>7.2f}{TARGETS_S[case]:>9.1f}"
              f"{r['peak_rss_mb']:>12.0f}  {','.join(r['admitted']) or 'none'}{extra}{'' if met else '  (over target)'}",
              flush=True)
    return 0 if ok else 2


if __name__ == "__main__":
    raise SystemExit(main())
