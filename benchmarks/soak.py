"""Soak: one daemon runs N consecutive batches; after each, its RSS, open fds, threads and GC objects.

    .venv/bin/python benchmarks/soak.py [--batches 20] [--duts 8] [--speed 480] [--profile fast-thermal]
    .venv/bin/python benchmarks/soak.py --batches 3          # smoke check, about 35 s

The simulated station of benchmarks/daemon_batch.py (tests/sim_station_child.py: serial boards on
ptys, CAN boards behind an slcan adapter, Modbus lamp relay, fixture, thermometer on 127.0.0.1) runs
in its own process, so /proc/self measures the daemon alone: the daemon (station.daemon.supervisor
Station, as `station serve` builds it, no web) runs in this process on a SQLite file in a temp dir.
The same K boards (3/4 serial, 1/4 CAN) are tested again in every batch, each batch starting when
the last one ended.

After each batch one line: wall s, RSS MB (VmRSS of /proc/self/status), open fds
(/proc/self/fd), OS threads (Threads of /proc/self/status), objects tracked by the GC after
gc.collect(), and how many DUTs are exact: run done, a verdict other than error, and TDB/TDSF
within daemon_batch.py's tolerance of the simulator's truth (the same check: the stored result of
dut_by_serial, here required to be this batch's run).

The first batches warm caches (imports done lazily, SQLAlchemy statement caches, numpy/scipy
buffers, the allocator's arenas), so growth is measured from batch 5 (batch 1 with fewer than 6
batches: then it is printed, not judged) to the last batch. Exit 1 when RSS or open fds grow more
than 5 % over that span; the ten object types whose count grew most (and new fds / threads, by
target / name) are printed to name a leak. A DUT that is not exact is reported, not judged.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from db.repository import batch_detail, dut_by_serial  # noqa: E402
from test_daemon_e2e import TDB_TOL_MG_PER_C, TDSF_TOL_PPM_PER_C  # noqa: E402  (what daemon_batch.py judges by)

BASELINE_BATCH = 5
MAX_GROWTH_PCT = 5.0


def proc_status(field: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise KeyError(field)


def fd_targets() -> list[str]:
    out = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            out.append(os.readlink(f"/proc/self/fd/{fd}"))
        except OSError:  # the listdir's own fd, closed by now
            pass
    return out


def type_counts() -> Counter:
    return Counter(f"{type(o).__module__}.{type(o).__qualname__}" for o in gc.get_objects())


def exact_duts(db, batch_id: int, truths: dict) -> tuple[int, int, list[str], Counter]:
    """(exact, DUTs, why each other one is not, verdict counts) of one batch, from the database."""
    runs = (batch_detail(db, batch_id) or {}).get("runs", [])
    bad: list[str] = []
    verdicts: Counter = Counter()
    for r in runs:
        verdicts[r.get("verdict") or "-"] += 1
        t = truths.get(r["slot"])
        dut = dut_by_serial(db, t["serial"]) if t else None
        th = (dut or {}).get("thermal") or {}
        if r["state"] != "done" or r.get("verdict") in (None, "error"):
            bad.append(f"{r['slot']} {r['state']} {r.get('verdict')} {(r.get('fault_reason') or '')[:60]}")
        elif (dut or {}).get("result_run_id") != r["id"] or not th:
            bad.append(f"{r['slot']}: no stored result of this run")
        elif not all(abs(th[a]["tdb_mg_per_c"] - t["tdb_mg_per_c"][k]) < TDB_TOL_MG_PER_C
                     and abs(th[a]["tdsf_ppm_per_c"] - t["tdsf_ppm_per_c"][k]) < TDSF_TOL_PPM_PER_C
                     for k, a in enumerate("xyz")):
            bad.append(f"{r['slot']}: TDB/TDSF off the truth")
    return len(runs) - len(bad), len(runs), bad, verdicts


def pct(a: float, b: float) -> float:
    return 100.0 * (b - a) / a if a else float("nan")


async def soak(args, cfg_dict: dict, truths: dict) -> int:
    from station.config import parse_config
    from station.daemon.storage import open_database
    from station.daemon.supervisor import Station

    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)  # as `station serve` without --verbose
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    cfg = parse_config(cfg_dict, "<soak>")
    db = open_database(cfg.database_url, station=cfg.name, journal_path=cfg.journal_path)
    station = Station(cfg, db=db)
    rows: list[dict] = []
    snap: dict[int, tuple[Counter, list[str], list[str]]] = {}
    base = BASELINE_BATCH if args.batches > BASELINE_BATCH else 1
    try:
        await station.start()
        faulted = [s for s in station.slots_status() if s["state"] == "faulted"]
        for s in faulted:
            print(f"slot {s['slot']} faulted at start: {s['fault_reason']}", flush=True)
        print(f"{'batch':>5} {'state':>9} {'wall s':>7} {'RSS MB':>7} {'fds':>4} {'thr':>4} {'gc objects':>10} "
              f"{'exact':>6}  verdicts")
        for n in range(1, args.batches + 1):
            t0 = time.monotonic()
            bid = station.start_batch(args.profile, None, "soak", by="benchmarks/soak.py")
            state = (await station.wait_batch(bid, timeout_s=args.batch_timeout))["state"]
            await station.flush_db()
            wall = time.monotonic() - t0
            ok, total, bad, verdicts = exact_duts(db, bid, truths)
            gc.collect()
            row = {"batch": n, "state": state, "wall_s": wall, "rss_mb": proc_status("VmRSS") / 1024,
                   "fds": len(os.listdir("/proc/self/fd")), "threads": proc_status("Threads"),
                   "gc_objects": len(gc.get_objects()), "exact": ok, "duts": total}
            rows.append(row)
            if n in (base, args.batches):
                snap[n] = (type_counts(), fd_targets(), sorted(t.name for t in threading.enumerate()))
            print(f"{n:5d} {state:>9} {wall:7.1f} {row['rss_mb']:7.1f} {row['fds']:4d} {row['threads']:4d} "
                  f"{row['gc_objects']:10d} {ok:>2}/{total:<3}  "
                  + " ".join(f"{k} {v}" for k, v in sorted(verdicts.items())), flush=True)
            for b in bad:
                print(f"      not exact: {b}", flush=True)
    finally:
        await station.close("soak done")
        db.dispose()
    if len(rows) < args.batches:
        return 1
    a, b = rows[base - 1], rows[-1]
    span = f"batch {base} -> {b['batch']}"
    print(f"\ngrowth {span}: RSS {a['rss_mb']:.1f} -> {b['rss_mb']:.1f} MB ({pct(a['rss_mb'], b['rss_mb']):+.1f} %), "
          f"fds {a['fds']} -> {b['fds']} ({pct(a['fds'], b['fds']):+.1f} %), threads {a['threads']} -> {b['threads']}, "
          f"gc objects {a['gc_objects']} -> {b['gc_objects']} ({pct(a['gc_objects'], b['gc_objects']):+.1f} %)")
    if b["batch"] > a["batch"]:
        per = (b["rss_mb"] - a["rss_mb"]) / (b["batch"] - a["batch"])
        print(f"RSS per batch: {per:+.2f} MB")
    (ca, fa, ta), (cb, fb, tb) = snap[base], snap[args.batches]
    grew = sorted(((cb[k] - ca[k], k) for k in cb if cb[k] > ca[k]), reverse=True)[:10]
    print(f"top object types that grew ({span}):")
    for d, k in grew:
        print(f"  {d:+9d}  {k} ({ca[k]} -> {cb[k]})")
    new_fds = Counter(fb) - Counter(fa)
    if new_fds:
        print("new fds: " + ", ".join(f"{n}x {t}" for t, n in new_fds.most_common(10)))
    new_threads = Counter(tb) - Counter(ta)
    if new_threads:
        print("new threads: " + ", ".join(f"{n}x {t}" for t, n in new_threads.most_common(10)))
    not_exact = sum(r["duts"] - r["exact"] for r in rows)
    if not_exact:
        print(f"{not_exact} DUT result(s) not exact over {len(rows)} batches (reported, not judged)")
    if base == 1:
        print(f"fewer than {BASELINE_BATCH + 1} batches: growth printed, not judged (warm-up)")
        return 0
    too_much = [w for w, g in (("RSS", pct(a["rss_mb"], b["rss_mb"])), ("fds", pct(a["fds"], b["fds"])))
                if g > MAX_GROWTH_PCT]
    if too_much:
        print(f"FAIL: {' and '.join(too_much)} grew more than {MAX_GROWTH_PCT:g} % ({span})")
        return 1
    print(f"OK: RSS and fds within {MAX_GROWTH_PCT:g} % ({span})")
    return 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--batches", type=int, default=20)
    p.add_argument("--duts", type=int, default=8, help="simulated boards: 3/4 serial, 1/4 CAN (default 8)")
    p.add_argument("--speed", type=float, default=480.0, help="simulated seconds per wall second (default 480)")
    p.add_argument("--profile", default="fast-thermal")
    p.add_argument("--seed", type=int, default=21)
    p.add_argument("--batch-timeout", type=float, default=900.0, help="wall seconds one batch may take")
    args = p.parse_args()
    if args.batches < 1 or args.duts < 1:
        p.error("--batches and --duts must be >= 1")
    n_can = args.duts // 4
    n_serial = args.duts - n_can
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        sim = subprocess.Popen([sys.executable, str(ROOT / "tests" / "sim_station_child.py"), str(tmp / "sim.json"),
                                "--serial", str(n_serial), "--can", str(n_can), "--speed", str(args.speed),
                                "--seed", str(args.seed)], stdout=subprocess.PIPE, text=True, env=env, cwd=ROOT)
        try:
            if sim.stdout.readline().strip() != "READY":
                print("the simulated station did not start", file=sys.stderr)
                return 2
            spec = json.loads((tmp / "sim.json").read_text())
            cfg = spec["config"]
            cfg["database_url"] = f"sqlite:///{tmp / 'station.db'}"
            print(f"soak: {args.batches} x {args.profile}, {n_serial} serial + {n_can} CAN simulated DUTs, "
                  f"speed x{args.speed:g}, one daemon in this process (pid {os.getpid()}), SQLite in {tmp}", flush=True)
            return asyncio.run(soak(args, cfg, spec["truths"]))
        finally:
            sim.send_signal(signal.SIGTERM)
            try:
                sim.wait(20)
            except subprocess.TimeoutExpired:
                sim.kill()


if __name__ == "__main__":
    sys.exit(main())
