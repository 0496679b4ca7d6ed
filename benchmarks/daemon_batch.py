"""64 simulated DUTs through the real daemon on fast-thermal: wall time, samples/s, CPU per sample.

    .venv/bin/python benchmarks/daemon_batch.py [--serial 48] [--can 16] [--speed 30 60 ...]

The simulated station (serial boards on ptys, CAN boards behind one slcan adapter, Modbus relay and
fixture on 127.0.0.1) runs in its own process, as real boards sit outside the daemon; the daemon is
`station serve --once --start-batch fast-thermal` with a SQLite file. For each speed factor it
prints the batch's wall time, the samples stored per wall second, the daemon's CPU seconds per
sample (user+sys from wait4), and how many DUTs match the simulator's truth (TDB 0.03 mg/C, TDSF
40 ppm/C). The highest speed with every DUT correct is the figure to quote. Prints, never asserts.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from db.database import Database  # noqa: E402
from db.repository import batch_detail, dut_by_serial  # noqa: E402
from test_daemon_e2e import TDB_TOL_MG_PER_C, TDSF_TOL_PPM_PER_C, _to_toml  # noqa: E402


def one(speed: float, n_serial: int, n_can: int, seed: int, real_plant: bool = True,
        cost_us: float | None = None) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        sim = subprocess.Popen([sys.executable, str(ROOT / "tests" / "sim_station_child.py"), str(tmp / "sim.json"),
                                "--serial", str(n_serial), "--can", str(n_can), "--speed", str(speed),
                                "--seed", str(seed), *(["--real-plant"] if real_plant else [])],
                               stdout=subprocess.PIPE, text=True, env=env, cwd=ROOT)
        try:
            assert sim.stdout.readline().strip() == "READY"
            spec = json.loads((tmp / "sim.json").read_text())
            cfg = spec["config"]
            cfg["database_url"] = f"sqlite:///{tmp / 'station.db'}"
            if cost_us is not None:
                cfg.setdefault("timing", {})["intake_cost_us_per_sample"] = cost_us
            (tmp / "station.toml").write_text(_to_toml(cfg))
            t0 = time.monotonic()
            log_file = open(tmp / "daemon.log", "w")
            daemon = subprocess.Popen([sys.executable, "-m", "cli", "serve", "--config", str(tmp / "station.toml"),
                                       "--no-web", "--start-batch", "fast-thermal", "--once"],
                                      stdout=subprocess.DEVNULL, stderr=log_file, text=True, env=env, cwd=ROOT)
            _, status, rusage = os.wait4(daemon.pid, 0)
            wall_s = time.monotonic() - t0
            daemon.returncode = os.waitstatus_to_exitcode(status)
            cpu_s = rusage.ru_utime + rusage.ru_stime
            log_file.close()
            log_text = (tmp / "daemon.log").read_text(errors="replace")
            alarms = [ln.split("OVERLOAD: ", 1)[1] for ln in log_text.splitlines() if "OVERLOAD: " in ln]
            refused = [ln for ln in log_text.splitlines() if "cannot follow this batch" in ln]
            db = Database(cfg["database_url"])
            detail = batch_detail(db, 1) or {}
            runs = detail.get("runs", [])
            n_samples = sum(r.get("n_samples", 0) for r in runs)
            correct = 0
            for r in runs:
                t = spec["truths"].get(r["slot"])
                dut = dut_by_serial(db, t["serial"]) if t else None
                th = (dut or {}).get("thermal") or {}
                if r["state"] == "done" and th and all(
                    abs(th[a]["tdb_mg_per_c"] - t["tdb_mg_per_c"][k]) < TDB_TOL_MG_PER_C
                    and abs(th[a]["tdsf_ppm_per_c"] - t["tdsf_ppm_per_c"][k]) < TDSF_TOL_PPM_PER_C
                    for k, a in enumerate("xyz")
                ):
                    correct += 1
            lost = {r["slot"]: int(r.get("lost_samples") or 0) for r in runs}
            db_bytes = (tmp / "station.db").stat().st_size
            db.dispose()
            return {"speed": speed, "state": detail.get("state"), "wall_s": wall_s, "daemon_cpu_s": cpu_s,
                    "samples": n_samples, "duts": len(runs), "correct": correct, "db_bytes": db_bytes,
                    "lost": lost, "alarms": alarms, "refused": refused[:1],
                    "faults": sorted({f'{r["slot"]} ({lost[r["slot"]]} lost): {r["fault_reason"][:90]}'
                                      for r in runs if r["state"] != "done"})}
        finally:
            sim.send_signal(signal.SIGTERM)
            try:
                sim.wait(20)
            except subprocess.TimeoutExpired:
                sim.kill()


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--serial", type=int, default=48)
    p.add_argument("--can", type=int, default=16)
    p.add_argument("--speed", type=float, nargs="+", default=[30.0, 60.0])
    p.add_argument("--seed", type=int, default=21)
    p.add_argument("--plant-waits", action="store_true",
                   help="the simulated plant holds its clock while the daemon is behind (hides an overload); "
                        "default: it never waits, and each board's transmit buffer holds about 1 s of its sending, as a real one's few KiB do")
    p.add_argument("--cost-us", type=float, default=None,
                   help="timing.intake_cost_us_per_sample for the daemon (a small figure forces a batch the "
                        "station would refuse, to watch the overload alarm)")
    args = p.parse_args()
    print(f"{args.serial} serial + {args.can} CAN simulated DUTs, fast-thermal, daemon = station serve --once")
    print(f"{'speed':>6} {'state':>9} {'wall s':>8} {'samples':>9} {'samples/s':>10} {'CPU us/sample':>14} "
          f"{'correct':>8} {'db MiB':>7} {'lost samples (slots with loss, worst slot)':>44}")
    for speed in args.speed:
        r = one(speed, args.serial, args.can, args.seed, not args.plant_waits, args.cost_us)
        sps = r["samples"] / r["wall_s"] if r["wall_s"] else 0.0
        us = 1e6 * r["daemon_cpu_s"] / r["samples"] if r["samples"] else float("nan")
        print(f"{speed:6g} {str(r['state']):>9} {r['wall_s']:8.1f} {r['samples']:9d} {sps:10.0f} {us:14.1f} "
              f"{r['correct']:>4}/{r['duts']:<3} {r['db_bytes'] / 2**20:7.1f} "
              f"{sum(r['lost'].values()):>12d} ({sum(v > 0 for v in r['lost'].values())}, "
              f"{max(r['lost'].values(), default=0)})", flush=True)
        for f in r["faults"]:
            print(f"       fault: {f}")
        for a in r["alarms"][:3]:
            print(f"       alarm: {a}")
        for a in r["refused"]:
            print(f"       refused: {a[-300:]}")


if __name__ == "__main__":
    main()
