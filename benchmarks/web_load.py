"""Latency of GET /api/batches/{id} at a fixed request rate while 64 simulated DUTs stream.

    .venv/bin/python benchmarks/web_load.py [--rate 100] [--requests 3000] [--serial 48] [--can 16]
                                            [--speed 60] [--sse 1]

A whole simulated station (48 serial boards on pseudo-terminals + 16 CAN boards behind an slcan
adapter, lamp relay and fixture on Modbus TCP, all on this machine), the real daemon with SQLite
and the web app on a loopback port (tests/web_support.LiveStation). A fast-thermal batch runs on
every slot; the simulated boards run in a child process (as real boards are outside the daemon;
--sim-in-daemon puts them in the daemon's event loop instead). Once all of them stream, a separate client process (its own interpreter, so it does not
share the daemon's GIL) sends GET /api/batches/{id} open-loop at --rate requests/s from 16 threads
on keep-alive connections (each request is due at its scheduled time; "scheduled -> answer" also
counts any wait for a free client thread) while --sse clients
listen to /api/events like an open operator page. Prints p50/p90/p99/max latency, the achieved
rate, errors, and the samples/s the daemon ingested meanwhile. No assertion: a figure, not a test.
Loopback only.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))


# --- client process -------------------------------------------------------------------------------

def client_main(url: str, batch_id: int, token: str, rate: float, n: int, sse: int) -> None:
    import httpx

    stop = threading.Event()
    sse_events = [0] * sse

    def listen(i: int) -> None:
        try:
            with httpx.Client(timeout=httpx.Timeout(10, read=30)) as c:
                with c.stream("GET", url + "/api/events", params={"token": token}) as r:
                    for line in r.iter_lines():
                        if line.startswith("data: "):
                            sse_events[i] += 1
                        if stop.is_set():
                            return
        except Exception:  # noqa: BLE001 - a figure only
            pass

    for i in range(sse):
        threading.Thread(target=listen, args=(i,), daemon=True).start()

    def run() -> dict:
        # Open loop with blocking http.client on keep-alive connections, one per worker thread
        # (much lighter than an asyncio HTTP client, so the client's own CPU does not add latency).
        import http.client
        from urllib.parse import urlsplit

        u = urlsplit(url)
        path = f"/api/batches/{batch_id}"
        headers = {"Authorization": f"Bearer {token}"}
        workers = 16
        lat, late, starts, errors, sizes = [], [], [], [], []
        lock = threading.Lock()
        t0 = time.perf_counter() + 0.2

        def worker(k: int) -> None:
            conn = http.client.HTTPConnection(u.hostname, u.port, timeout=30)
            for i in range(k, n, workers):
                sched = t0 + i / rate
                delay = sched - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
                start = time.perf_counter()
                try:
                    conn.request("GET", path, headers=headers)
                    resp = conn.getresponse()
                    body = resp.read()
                    end = time.perf_counter()
                    with lock:
                        starts.append(start - sched)
                        if resp.status != 200:
                            errors.append(f"HTTP {resp.status}")
                        else:
                            lat.append(end - start)
                            late.append(end - sched)
                            sizes.append(len(body))
                except (OSError, http.client.HTTPException) as exc:
                    with lock:
                        errors.append(type(exc).__name__)
                    conn.close()
                    conn = http.client.HTTPConnection(u.hostname, u.port, timeout=30)
            conn.close()

        threads = [threading.Thread(target=worker, args=(k,)) for k in range(workers)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wall = time.perf_counter() - t0
        return {"lat": lat, "late": late, "errors": errors, "wall": wall, "bytes": sum(sizes) / max(1, len(sizes)),
                "start_delay": starts}

    out = run()
    stop.set()
    out["sse_events"] = sse_events
    print(json.dumps(out))


# --- station side ---------------------------------------------------------------------------------

def pct(values: list[float], q: float) -> float:
    import numpy as np

    return float(np.percentile(np.asarray(values), q)) if values else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rate", type=float, default=100.0, help="requests per second (default 100)")
    ap.add_argument("--requests", type=int, default=3000, help="requests in all (default 3000)")
    ap.add_argument("--serial", type=int, default=48)
    ap.add_argument("--can", type=int, default=16)
    ap.add_argument("--speed", type=float, default=60.0, help="simulated seconds per wall second (default 60, as the demo)")
    ap.add_argument("--sse", type=int, default=1, help="SSE clients listening meanwhile (default 1)")
    ap.add_argument("--sim-in-daemon", action="store_true",
                    help="run the simulated boards in the daemon's own event loop (default: a child process, "
                         "like real boards outside the daemon)")
    ap.add_argument("--client", nargs=3, metavar=("URL", "BATCH", "N"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.client:
        url, batch, n = args.client
        client_main(url, int(batch), os.environ["STATION_TOKEN"], args.rate, int(n), args.sse)
        return

    import httpx

    from web_support import TOKENS, LiveStation, auth, wait_for

    n_duts = args.serial + args.can
    print(f"web_load: {args.serial} serial + {args.can} CAN simulated DUTs, speed x{args.speed:g}, "
          f"{args.requests} x GET /api/batches/{{id}} at {args.rate:g}/s, {args.sse} SSE client(s)", flush=True)
    with tempfile.TemporaryDirectory() as tmp, \
            LiveStation(Path(tmp), n_serial=args.serial, n_can=args.can, speed=args.speed, fixture=True,
                        sse_interval_s=0.5, sim_process=not args.sim_in_daemon) as live:
        with httpx.Client(base_url=live.url, timeout=30) as c:
            slots = c.get("/api/slots", headers=auth("operator")).json()
            ok = [s for s in slots if s["state"] == "identified"]
            print(f"web_load: {len(ok)}/{len(slots)} slots identified", flush=True)
            r = c.post("/api/batches", json={"profile": "fast-thermal", "operator": "bench"}, headers=auth("operator"))
            r.raise_for_status()
            bid = r.json()["id"]

            def streaming():
                st = c.get(f"/api/batches/{bid}", headers=auth("operator")).json()
                return st if all((s.get("samples") or 0) > 0 for s in st["slots"]) else None

            st0 = wait_for(streaming, 120, interval_s=0.5, what="every DUT streaming")
            lags: list[float] = []
            lag_stop = threading.Event()

            async def lag_monitor():  # how late the daemon's event loop wakes a 10 ms sleep
                import asyncio

                loop = asyncio.get_running_loop()
                while not lag_stop.is_set():
                    t = loop.time()
                    await asyncio.sleep(0.01)
                    lags.append(loop.time() - t - 0.01)

            import asyncio

            asyncio.run_coroutine_threadsafe(lag_monitor(), live.loop)
            s0, t_start = sum(s["samples"] for s in st0["slots"]), time.monotonic()
            env = {**os.environ, "STATION_TOKEN": TOKENS["operator"]}
            proc = subprocess.run(
                [sys.executable, __file__, "--client", live.url, str(bid), str(args.requests),
                 "--rate", str(args.rate), "--sse", str(args.sse)],
                env=env, capture_output=True, text=True, timeout=args.requests / args.rate + 120)
            elapsed = time.monotonic() - t_start
            lag_stop.set()
            st1 = c.get(f"/api/batches/{bid}", headers=auth("operator")).json()
        if proc.returncode != 0:
            print(proc.stderr, file=sys.stderr)
            raise SystemExit(f"web_load: client failed ({proc.returncode})")
        res = json.loads(proc.stdout.strip().splitlines()[-1])
        odr_hz = float(live.sim.odr_hz) if hasattr(live.sim, "odr_hz") else float(live.sim.world.odr_hz)
    s1 = sum(s["samples"] for s in st1["slots"])
    faulted = [s["slot"] for s in st1["slots"] if s["state"] == "faulted"]
    lat_ms = [x * 1000 for x in res["lat"]]
    late_ms = [x * 1000 for x in res["late"]]
    print(f"batch {bid}: state {st1['state']}, step {st1['step'].get('name')}, faulted slots: {len(faulted)} {faulted[:8]}")
    print(f"requests: {len(lat_ms)} ok, {len(res['errors'])} errors {sorted(set(res['errors']))[:5]}, "
          f"achieved {len(lat_ms) / res['wall']:.1f} req/s over {res['wall']:.1f} s, {res['bytes'] / 1024:.1f} KiB per answer")
    print(f"latency ms (send -> answer):     p50 {pct(lat_ms, 50):6.1f}  p90 {pct(lat_ms, 90):6.1f}  "
          f"p99 {pct(lat_ms, 99):6.1f}  max {max(lat_ms):6.1f}")
    print(f"latency ms (scheduled -> answer): p50 {pct(late_ms, 50):6.1f}  p90 {pct(late_ms, 90):6.1f}  "
          f"p99 {pct(late_ms, 99):6.1f}  max {max(late_ms):6.1f}")
    lag_ms = [x * 1000 for x in lags] or [float("nan")]
    sd_ms = [x * 1000 for x in res["start_delay"]]
    print(f"daemon event-loop lag ms:         p50 {pct(lag_ms, 50):6.1f}  p90 {pct(lag_ms, 90):6.1f}  "
          f"p99 {pct(lag_ms, 99):6.1f}  max {max(lag_ms):6.1f}")
    print(f"client start delay ms (its own CPU): p50 {pct(sd_ms, 50):6.1f}  p99 {pct(sd_ms, 99):6.1f}  max {max(sd_ms):6.1f}")
    expected = n_duts * odr_hz * args.speed
    print(f"daemon meanwhile: {(s1 - s0) / elapsed:.0f} samples/s ingested over {n_duts} DUTs "
          f"(simulated rate {expected:.0f}/s), SSE events received: {res['sse_events']}")


if __name__ == "__main__":
    main()
