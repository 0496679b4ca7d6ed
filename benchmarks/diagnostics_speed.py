"""Speed and memory of `station diagnose` against its targets on the 2-core station PC.

    .venv/bin/python benchmarks/diagnostics_speed.py              # every figure below
    .venv/bin/python benchmarks/diagnostics_speed.py --case one   # one of them (help, read, one, add, cli, batch)

The log: the simulator's `validation` profile with the `realistic` noise (bias random walk +
flicker) and a hidden hysteresis, cut to its first 117 k samples (10.4 h at 3.125 Hz; seed 1),
written as a design-5.1 CSV before any clock starts. Figures (wall time; CPU time beside it):

- help:  `station --help` (python -m cli), a fresh process                          (target <= 1 s)
- read:  contracts.logfile.read_log of the CSV (with every check), in a fresh process
- one:   diagnose() of that log, in a fresh process: ranking + admitted staircase  (target <= 2 s)
- add:   `--add` of two effects on that ranked state, same process (a model not fitted yet: the
         engineer's second click; a first click on a ranked candidate is already fitted) (target <= 0.5 s)
- cli:   `station diagnose LOG.csv` from the command line, the ranking cache empty (it writes it),
         the whole command: start, imports, read, diagnosis, report                  (target <= 2 s)
         then `station diagnose LOG.csv --add A --add B` (the same two effects), the ranking
         cache written by the first run (docs/diagnostics.md "Speed")               (target <= 0.5 s)
- batch: diagnose() of a batch of 8 such DUTs together, in a fresh process          (target <= 10 s)

Every row also shows numpy's own read of the same CSV (np.loadtxt), timed just before the row
in this run, and the row's wall time in multiples of it: the machine's speed at that moment, for
reference (a shared machine's load changes the figures, not the ratio as much). No figure is
asserted: this prints.

Each figure is taken in a fresh child process (its peak resident memory, ru_maxrss, is its own).
The children use one BLAS thread (OPENBLAS_NUM_THREADS=1), as `station diagnose` sets for itself
(cli/main.py ONE_BLAS_THREAD), unless the variable is already set. The ranking cache of the `cli`
rows lives in a temporary folder ($STATION_DIAGNOSE_CACHE), never in the user's.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

N_SAMPLES = 117_000
TARGETS_S = {"help": 1.0, "one": 2.0, "add": 0.5, "cli": 2.0, "cli_add": 0.5, "batch": 10.0}
CASES = ("help", "read", "one", "add", "cli", "batch")


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


def write_log(path: Path) -> Path:
    from contracts.logfile import write_log as write

    write(path, _logs(1)[0])
    return path


def numpy_read_s(path: Path) -> float:
    """numpy's read of the CSV (np.loadtxt, float64), in this process: the reference."""
    import numpy as np

    with open(path, encoding="utf-8") as f:
        skip = next(k for k, line in enumerate(f) if not line.startswith("#")) + 1  # `#` lines, header row
    t0 = time.perf_counter()
    np.loadtxt(path, delimiter=",", skiprows=skip)
    return time.perf_counter() - t0


def _rss_mb() -> float:
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)


def child(case: str, path: str) -> dict:
    """One figure, in this (fresh) process."""
    from contracts.logfile import read_log

    if case == "read":
        t0, c0 = time.perf_counter(), time.process_time()
        lg = read_log(path)
        return {"samples": len(lg), "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
                "peak_rss_mb": _rss_mb()}
    from station.diagnostics import ranking

    if case == "batch":
        logs = _logs(8)
    else:
        logs = [read_log(path)]
    t0, c0 = time.perf_counter(), time.process_time()
    rep = ranking.diagnose(logs)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    out = {"samples": sum(len(lg) for lg in logs), "duts": len(logs), "admitted": rep.admitted}
    if case == "add":
        # the engineer's second click: a model of two effects nothing fitted yet (a first click on a
        # ranked candidate is already fitted by the ranking and answers at once)
        add = [r["effect"] for r in rep.ranking if not r["admitted"]][:2]
        t0, c0 = time.perf_counter(), time.process_time()
        rep2 = ranking.with_added(rep, add)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        out["added"] = add
        out["staircase"] = [s["heldout_rms_mg"] for s in rep2.to_json()["staircase"]]
    out.update(wall_s=wall, cpu_s=cpu, peak_rss_mb=_rss_mb())
    return out


def _env(cache: Path | None = None) -> dict:
    env = dict(os.environ)
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    env.setdefault("MPLCONFIGDIR", tempfile.gettempdir())
    if cache is not None:
        env["STATION_DIAGNOSE_CACHE"] = str(cache)
    return env


def _run(argv: list[str], env: dict) -> tuple[float, float, subprocess.CompletedProcess]:
    """Wall and CPU (user + system) time of a child process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    res = subprocess.run(argv, capture_output=True, text=True, cwd=ROOT, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, res


def _child_case(case: str, path: Path) -> dict:
    wall, cpu, res = _run([sys.executable, __file__, "--child", case, "--log", str(path)], _env())
    if res.returncode:
        raise SystemExit(f"{case}: child failed:\n{res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def _cli(args: list[str], cache: Path) -> tuple[float, float]:
    wall, cpu, res = _run([sys.executable, "-m", "cli", *args], _env(cache))
    if res.returncode:
        raise SystemExit(f"station {' '.join(args)}: exit {res.returncode}:\n{res.stderr[-2000:]}")
    return wall, cpu


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", choices=[*CASES, "all"], default="all")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--log", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.log)))
        return 0
    cases = CASES if args.case == "all" else (args.case,)
    with tempfile.TemporaryDirectory(prefix="diag-speed-") as tmp:
        work = Path(tmp)
        path = write_log(work / "SIM0001.csv")
        numpy_read_s(path)  # the file in the page cache, numpy imported: every row reads it warm
        print(f"log {path.name}: {N_SAMPLES} samples, {path.stat().st_size / 1e6:.1f} MB; "
              f"BLAS threads {_env()['OPENBLAS_NUM_THREADS']}", flush=True)
        print(f"{'figure':<52}{'wall s':>8}{'CPU s':>7}{'numpy read s':>13}{'x numpy':>8}{'target s':>9}"
              f"{'peak RSS MB':>12}  notes")
        added: list[str] = []

        def row(label: str, key: str | None, wall: float, cpu: float, ref: float, rss=None, notes: str = "") -> None:
            target = f"{TARGETS_S[key]:.1f}" if key in TARGETS_S else "-"
            rss_s = f"{rss:.0f}" if rss is not None else "-"
            print(f"{label:<52}{wall:>8.2f}{cpu:>7.2f}{ref:>13.3f}{wall / ref:>8.1f}{target:>9}{rss_s:>12}  {notes}",
                  flush=True)

        for case in cases:
            if case == "help":
                ref = numpy_read_s(path)
                wall, cpu = _cli(["--help"], work / "cache-help")
                row("station --help", "help", wall, cpu, ref)
            elif case in ("read", "one", "batch"):
                ref = numpy_read_s(path)
                r = _child_case(case, path)
                label = {"read": "read_log (in-process, every check)",
                         "one": "diagnose() (in-process, after read_log)",
                         "batch": f"diagnose() of {r.get('duts')} DUTs together (in-process)"}[case]
                notes = f"admitted: {','.join(r['admitted']) or 'none'}" if "admitted" in r else ""
                row(label, case, r["wall_s"], r["cpu_s"], ref, r["peak_rss_mb"], notes)
            elif case == "add":
                ref = numpy_read_s(path)
                r = _child_case("add", path)
                added = r["added"]
                row(f"--add {' '.join(added)} (in-process, ranked)", "add", r["wall_s"], r["cpu_s"], ref,
                    r["peak_rss_mb"], f"held-out {r['staircase']} mg")
            elif case == "cli":
                cache = work / "cache"
                ref = numpy_read_s(path)
                wall, cpu = _cli(["diagnose", str(path)], cache)
                files = sorted(cache.glob("*.diag")) if cache.is_dir() else []
                row("station diagnose LOG.csv (CLI, ranking cache empty)", "cli", wall, cpu, ref,
                    notes=f"wrote {len(files)} cache file(s), {sum(f.stat().st_size for f in files) / 1e6:.0f} MB")
                if not added:  # the same two effects as the in-process figure would choose
                    added = _child_case("add", path)["added"]
                adds = [x for a in added for x in ("--add", a)]
                ref = numpy_read_s(path)
                wall, cpu = _cli(["diagnose", str(path), *adds], cache)
                row("station diagnose LOG.csv --add A --add B (CLI, cache warm)", "cli_add", wall, cpu, ref,
                    notes=f"A, B = {', '.join(added)}")
                ref = numpy_read_s(path)
                wall, cpu = _cli(["diagnose", str(path), *adds, "--no-cache"], cache)
                row("  the same with --no-cache (ranks again)", None, wall, cpu, ref)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
