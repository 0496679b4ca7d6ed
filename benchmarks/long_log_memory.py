"""Peak memory and wall time of `station calibrate`, `sfem` and `diagnose` on one ~200 MB log (issue 40).

    .venv/bin/python benchmarks/long_log_memory.py                       # every command, logs in a temp dir
    .venv/bin/python benchmarks/long_log_memory.py --dir /tmp/longlogs   # logs kept there (reused next time)
    .venv/bin/python benchmarks/long_log_memory.py --case calibrate --mb 60
    .venv/bin/python benchmarks/long_log_memory.py --cwd /tmp/base       # another checkout's code, same logs

Why: the station's commands read one DUT's log; an endurance run (days in the chamber) makes one
file of hundreds of MB. The target is a peak resident memory of at most 400 MB on a 200 MB log
(a 2-core station PC that also runs the daemon), with the same results as before on the usual logs.

The logs: the station's own simulator (`station simulate`, LIS3DSH, realistic noise: bias random
walk and flicker), one DUT, the profile each command reads, repeated end to end in time until the
file holds `--mb` MB (a long endurance record: the same run again and again, the time column
carried on):

- calibrate: fast-thermal (P ambient, lamp on, turn to N, lamp off), ~90 min per run;
- sfem:      sfem-24 (24 positions at each chamber step, ref_x/y/z columns), ~5.5 h per run;
- diagnose:  validation (one thermal cycle per orientation, six orientations), ~10.6 h per run;
- narrow:    `station calibrate` again, on the station's narrowest log (no lamp, no references:
             the most rows per MB, ~3.7 M in 200 MB), tests/thermal_synth.py's fast-thermal
             record (a generator independent of the simulator) repeated the same way;
- cached:    `station diagnose` as a user runs it, the ranking cache on (in the logs' folder,
             `cache/`, emptied first): the first run ranks and writes the cache, then
             `--add bias_t2` reads it back and fits one model more.

Each command runs as a fresh child process (`python -m cli ...`, output to /dev/null, the ranking
cache of diagnose off); its peak resident memory is the child's own ru_maxrss (os.wait4). Prints,
never asserts: a shared machine's load moves the wall times.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

PROFILE_OF = {"calibrate": "fast-thermal", "sfem": "sfem-24", "diagnose": "validation", "narrow": "thermal-synth",
              "cached": "validation"}
COMMAND_OF = {"calibrate": "calibrate", "sfem": "sfem", "diagnose": "diagnose", "narrow": "calibrate",
              "cached": "diagnose"}
ARGS_OF = {"calibrate": ["--json"], "sfem": ["--json"], "diagnose": ["--json", "--no-cache"], "narrow": ["--json"],
           "cached": ["--json"]}
CASES = tuple(PROFILE_OF)
TARGET_RSS_MB = 400.0


def one_run_text(profile: str, seed: int, workdir: Path) -> tuple[list[str], list[str]]:
    """(header lines: metadata and column row, data lines) of one simulated DUT run of `profile`."""
    out = workdir / f"sim-{profile}"
    if profile == "thermal-synth":
        sys.path[:0] = [str(ROOT), str(ROOT / "tests")]
        import numpy as np
        from thermal_synth import fast_thermal

        from contracts.logfile import DutLog, write_log

        rec = fast_thermal(seed=seed, tdb_mg_per_c=(0.47, 0.07, -0.2), tdsf_ppm_per_c=(-125.0, -38.0, -58.0))
        out.mkdir(parents=True)
        write_log(out / "SYN0001.csv", DutLog(rec.time_s, rec.acc_g, rec.temp_c, position=rec.position.astype(np.int64),
                                              meta={"serial": "SYN0001", "sensor": "LIS3DSH"}))
    else:
        subprocess.run([sys.executable, "-m", "cli", "simulate", "--out", str(out), "--duts", "1", "--profile", profile,
                        "--seed", str(seed), "--quiet"], cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    lines = next(out.glob("*.csv")).read_text().splitlines()
    i = next(k for k, ln in enumerate(lines) if not ln.startswith("#"))
    return lines[: i + 1], lines[i + 1:]


def write_long_log(path: Path, profile: str, size_mb: float, seed: int = 1) -> int:
    """Write one DUT's log of about `size_mb` MB: one simulated run of `profile` repeated end to
    end, each repeat's times shifted past the previous one's last sample by one sample period.
    Returns the number of data rows."""
    with tempfile.TemporaryDirectory() as tmp:
        head, rows = one_run_text(profile, seed, Path(tmp))
    times = [float(r.split(",", 1)[0]) for r in rows]
    rest = [r.split(",", 1)[1] for r in rows]
    step_s = times[1] - times[0]
    period_s = times[-1] - times[0] + step_s
    run_bytes = sum(len(r) + 1 for r in rows)
    repeats = max(1, round(size_mb * 1e6 / run_bytes))
    head.insert(-1, f"# note: {repeats} runs of the simulated {profile} profile end to end (benchmarks/long_log_memory.py)")
    tmp_path = path.with_suffix(".tmp")
    with open(tmp_path, "w", encoding="utf-8") as f:
        f.write("\n".join(head) + "\n")
        for k in range(repeats):
            off = k * period_s
            f.write("\n".join(f"{t + off:.6f},{r}" for t, r in zip(times, rest)) + "\n")
    tmp_path.replace(path)
    return repeats * len(rows)


def measure(cmd: list[str], cwd: Path, env: dict[str, str]) -> tuple[float, float, int]:
    """(peak RSS MB, wall s, exit code) of one child process."""
    t0 = time.monotonic()
    with open(os.devnull, "w") as devnull:
        proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=devnull, stderr=subprocess.PIPE)
        assert proc.stderr is not None
        err = proc.stderr.read()
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.monotonic() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        sys.stderr.write(err.decode(errors="replace")[-2000:])
    return usage.ru_maxrss / 1024.0, wall, proc.returncode


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dir", type=Path, default=None, help="where the logs are written (kept; reused when present)")
    ap.add_argument("--mb", type=float, default=200.0, help="size of each log in MB (default 200)")
    ap.add_argument("--case", choices=CASES, action="append",
                    help="one case (repeatable; default all but `cached`, the slowest)")
    ap.add_argument("--cwd", type=Path, default=ROOT,
                    help="checkout whose code runs the commands (default this one; e.g. a git worktree of HEAD)")
    args = ap.parse_args()
    cases = args.case or [c for c in CASES if c != "cached"]  # the cache's runs: asked for by name
    tmp = None
    if args.dir is None:
        tmp = tempfile.TemporaryDirectory()
        folder = Path(tmp.name)
    else:
        folder = args.dir
        folder.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, STATION_DIAGNOSE_CACHE="off", PYTHONPATH=str(args.cwd.resolve()))
    print(f"code: {args.cwd.resolve()}   logs: {folder}   target: peak RSS <= {TARGET_RSS_MB:g} MB on a 200 MB log")
    try:
        for case in cases:
            path = folder / f"long-{PROFILE_OF[case]}-{args.mb:g}mb.csv"
            if not path.exists():
                t0 = time.monotonic()
                n = write_long_log(path, PROFILE_OF[case], args.mb)
                print(f"  wrote {path.name}: {n} rows in {time.monotonic() - t0:.1f} s")
            runs = [ARGS_OF[case]]
            run_env = env
            if case == "cached":  # the default command: the ranking cache written, then read by --add
                cache = folder / "cache"
                shutil.rmtree(cache, ignore_errors=True)
                run_env = dict(env, STATION_DIAGNOSE_CACHE=str(cache))
                runs.append(ARGS_OF[case] + ["--add", "bias_t2"])
            size = path.stat().st_size / 1e6
            for extra in runs:
                cmd = [sys.executable, "-m", "cli", COMMAND_OF[case], str(path), *extra]
                rss, wall, rc = measure(cmd, args.cwd, run_env)
                print(f"{case:<10} {size:7.1f} MB log  peak RSS {rss:8.1f} MB  wall {wall:7.1f} s  exit {rc}   "
                      f"(python -m cli {COMMAND_OF[case]} {path.name} {' '.join(extra)})", flush=True)
    finally:
        if tmp is not None:
            tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
