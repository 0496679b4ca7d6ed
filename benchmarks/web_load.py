"""Latency of the operator page's poll, GET /api/batches/{id}?view=compact, at a fixed request rate
while 64 simulated DUTs stream.

    .venv/bin/python benchmarks/web_load.py [--rate 100] [--requests 3000] [--serial 48] [--can 16]
                                            [--speed 60] [--sse 1] [--view compact|full] [--plain]
                                            [--no-etag] [--no-gc-freeze]

A whole simulated station (48 serial boards on pseudo-terminals + 16 CAN boards behind an slcan
adapter, lamp relay and fixture on Modbus TCP, all on this machine), the real daemon with SQLite
and the web app on a loopback port (tests/web_support.LiveStation). A fast-thermal batch runs on
every slot; the simulated boards run in a child process (as real boards are outside the daemon;
--sim-in-daemon puts them in the daemon's event loop instead). Once all of them stream, a separate
client process (its own interpreter, so it does not share the daemon's GIL) sends GET
/api/batches/{id}?view=compact open-loop at --rate requests/s from 16 threads on keep-alive
connections (each request is due at its scheduled time; "scheduled -> answer" also counts any wait
for a free client thread) while --sse clients listen to /api/events like an open operator page.

By default the client does what the page does (web/static/status.js): it asks for the compact view
and revalidates like a browser, each worker thread sending the ETag of the last answer it got in
If-None-Match (a 304 has no body). Prints the answers' sizes (200s and 304s), p50/p90/p99/max
latency, the achieved rate, errors, the daemon's event-loop lag, and the samples/s the daemon
ingested meanwhile. --view full asks for the full status instead (what the page polled before
issue 40; the MES's view); --plain first runs a pass of a client that never sends If-None-Match, on
a fresh station at the same point of its batch (--view full --plain --no-etag: the figures this
benchmark printed before); --no-etag skips the revalidating pass. Once the station is up, its
start-up heap is frozen as the daemon does (station/daemon/heap.py; --no-gc-freeze: not). No
assertion: a figure, not a test. Loopback only; on a shared machine the figures are noisy.
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

def client_main(url: str, batch_id: int, token: str, rate: float, n: int, sse: int, etag: bool = False,
                view: str = "full") -> None:
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
        path = f"/api/batches/{batch_id}" + ("?view=compact" if view == "compact" else "")
        workers = 16
        lat, late, starts, errors, sizes = [], [], [], [], []
        statuses: dict[str, int] = {}
        lock = threading.Lock()
        t0 = time.perf_counter() + 0.2

        def worker(k: int) -> None:
            conn = http.client.HTTPConnection(u.hostname, u.port, timeout=30)
            headers = {"Authorization": f"Bearer {token}"}  # per worker: its own last ETag, like a browser
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
                    if etag and resp.status == 200 and resp.getheader("ETag"):
                        headers["If-None-Match"] = resp.getheader("ETag")
                    with lock:
                        starts.append(start - sched)
                        statuses[str(resp.status)] = statuses.get(str(resp.status), 0) + 1
                        if resp.status not in (200, 304) or (resp.status == 304 and not etag):
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
                "start_delay": starts, "statuses": statuses, "sizes": sizes}

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
    ap.add_argument("--view", choices=("full", "compact"), default="compact",
                    help="compact (default): GET /api/batches/{id}?view=compact, what the operator page polls; "
                         "full: the full status (what the page polled before; the MES's view)")
    ap.add_argument("--plain", action="store_true",
                    help="first a pass of a client that never sends If-None-Match (on a fresh station)")
    ap.add_argument("--no-etag", dest="etag", action="store_false",
                    help="skip the pass of the client that revalidates with If-None-Match, like the page")
    ap.add_argument("--no-gc-freeze", dest="gc_freeze", action="store_false",
                    help="do not freeze the start-up heap once the station is up, as the daemon does when it "
                         "serves the web (station/daemon/heap.py)")
    ap.add_argument("--client", nargs=3, metavar=("URL", "BATCH", "N"), help=argparse.SUPPRESS)
    ap.add_argument("--client-etag", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.client:
        url, batch, n = args.client
        client_main(url, int(batch), os.environ["STATION_TOKEN"], args.rate, int(n), args.sse, etag=args.client_etag,
                    view=args.view)
        return

    n_duts = args.serial + args.can
    query = "?view=compact" if args.view == "compact" else ""
    print(f"web_load: {args.serial} serial + {args.can} CAN simulated DUTs, speed x{args.speed:g}, "
          f"{args.requests} x GET /api/batches/{{id}}{query} at {args.rate:g}/s, {args.sse} SSE client(s)"
          + ("" if args.gc_freeze else ", start-up heap NOT frozen"), flush=True)
    if not (args.plain or args.etag):
        raise SystemExit("web_load: --no-etag without --plain leaves no pass to run")
    passes = [("plain", run_pass(args, etag=False))] if args.plain else []
    if args.etag:
        passes.append(("etag", run_pass(args, etag=True)))
    for name, (bid, res, odr_hz) in passes:
        if name == "plain":
            print(f"--- a client that never sends If-None-Match [view={args.view}]")
        else:
            print(f"--- a client that revalidates like the page's browser: each thread sends the ETag of its last "
                  f"answer [view={args.view}]" + (", on a fresh station at the same point of its batch" if args.plain
                                                  else ""))
        report(bid, res, n_duts, n_duts * odr_hz * args.speed)


def run_pass(args: argparse.Namespace, etag: bool) -> tuple[int, dict, float]:
    """One client pass on a fresh station, once every DUT of its batch streams (so that both passes
    measure the same part of the batch): its answers, the daemon's loop lag, the samples ingested
    meanwhile; (batch id, results, the boards' ODR)."""
    import asyncio

    import httpx

    from web_support import TOKENS, LiveStation, auth, wait_for

    with tempfile.TemporaryDirectory() as tmp, \
            LiveStation(Path(tmp), n_serial=args.serial, n_can=args.can, speed=args.speed, fixture=True,
                        sse_interval_s=0.5, sim_process=not args.sim_in_daemon) as live:
        with httpx.Client(base_url=live.url, timeout=30) as c:
            slots = c.get("/api/slots", headers=auth("operator")).json()
            ok = [s for s in slots if s["state"] == "identified"]
            print(f"web_load: {len(ok)}/{len(slots)} slots identified", flush=True)
            if args.gc_freeze:  # what `station serve` / `station demo` do once they serve the web
                from station.daemon.heap import freeze_startup_heap

                live.call(freeze_startup_heap)
            r = c.post("/api/batches", json={"profile": "fast-thermal", "operator": "bench"}, headers=auth("operator"))
            r.raise_for_status()
            bid = r.json()["id"]

            def streaming():
                st = c.get(f"/api/batches/{bid}", headers=auth("operator")).json()
                return st if all((s.get("samples") or 0) > 0 for s in st["slots"]) else None

            wait_for(streaming, 120, interval_s=0.5, what="every DUT streaming")

            def samples_now() -> int:  # from the daemon itself: the HTTP answer may be a render 0.5 s old
                return live.call(lambda: sum(s["samples"] or 0 for s in live.station.batch_status(bid)["slots"]))

            lags: list[float] = []
            lag_stop = threading.Event()

            async def lag_monitor():  # how late the daemon's event loop wakes a 10 ms sleep
                loop = asyncio.get_running_loop()
                while not lag_stop.is_set():
                    t = loop.time()
                    await asyncio.sleep(0.01)
                    lags.append(loop.time() - t - 0.01)

            asyncio.run_coroutine_threadsafe(lag_monitor(), live.loop)
            s0, t_start = samples_now(), time.monotonic()
            env = {**os.environ, "STATION_TOKEN": TOKENS["operator"]}
            proc = subprocess.run(
                [sys.executable, __file__, "--client", live.url, str(bid), str(args.requests),
                 "--rate", str(args.rate), "--sse", str(args.sse), "--view", args.view]
                + (["--client-etag"] if etag else []),
                env=env, capture_output=True, text=True, timeout=args.requests / args.rate + 120)
            s1, elapsed = samples_now(), time.monotonic() - t_start
            lag_stop.set()
            st1 = c.get(f"/api/batches/{bid}", headers=auth("operator")).json()
        if proc.returncode != 0:
            print(proc.stderr, file=sys.stderr)
            raise SystemExit(f"web_load: client failed ({proc.returncode})")
        res = json.loads(proc.stdout.strip().splitlines()[-1])
        odr_hz = float(live.sim.odr_hz) if hasattr(live.sim, "odr_hz") else float(live.sim.world.odr_hz)
    return bid, {**res, "lags": lags, "st": st1, "samples_per_s": (s1 - s0) / elapsed}, odr_hz


def report(bid: int, res: dict, n_duts: int, expected: float) -> None:
    """The figures of one pass: the batch, the answers (sizes, 200s and 304s), latency, the loop lag."""
    st1 = res["st"]
    faulted = [s["slot"] for s in st1["slots"] if s["state"] == "faulted"]
    lat_ms = [x * 1000 for x in res["lat"]]
    late_ms = [x * 1000 for x in res["late"]]
    print(f"batch {bid}: state {st1['state']}, step {st1['step'].get('name')}, faulted slots: {len(faulted)} {faulted[:8]}")
    print(f"requests: {len(lat_ms)} ok, {len(res['errors'])} errors {sorted(set(res['errors']))[:5]}, "
          f"achieved {len(lat_ms) / res['wall']:.1f} req/s over {res['wall']:.1f} s, {res['bytes'] / 1024:.1f} KiB per answer")
    statuses = res.get("statuses") or {}
    full = [b for b in res.get("sizes") or [] if b > 0]
    if full:
        print(f"answer sizes (with a body): min {min(full)} B, max {max(full)} B ({max(full) / 1024:.1f} KiB)")
    if "304" in statuses:
        print(f"answers: {statuses.get('200', 0)} x 200 ({sum(full) / max(1, len(full)) / 1024:.1f} KiB each), "
              f"{statuses['304']} x 304 (no body); {sum(full) / max(1, len(lat_ms)) / 1024:.1f} KiB per request")
    print(f"latency ms (send -> answer):     p50 {pct(lat_ms, 50):6.1f}  p90 {pct(lat_ms, 90):6.1f}  "
          f"p99 {pct(lat_ms, 99):6.1f}  max {max(lat_ms):6.1f}")
    print(f"latency ms (scheduled -> answer): p50 {pct(late_ms, 50):6.1f}  p90 {pct(late_ms, 90):6.1f}  "
          f"p99 {pct(late_ms, 99):6.1f}  max {max(late_ms):6.1f}")
    lag_ms = [x * 1000 for x in res["lags"]] or [float("nan")]
    sd_ms = [x * 1000 for x in res["start_delay"]]
    print(f"daemon event-loop lag ms:         p50 {pct(lag_ms, 50):6.1f}  p90 {pct(lag_ms, 90):6.1f}  "
          f"p99 {pct(lag_ms, 99):6.1f}  max {max(lag_ms):6.1f}")
    print(f"client start delay ms (its own CPU): p50 {pct(sd_ms, 50):6.1f}  p99 {pct(sd_ms, 99):6.1f}  max {max(sd_ms):6.1f}")
    print(f"daemon meanwhile: {res['samples_per_s']:.0f} samples/s ingested over {n_duts} DUTs "
          f"(simulated rate {expected:.0f}/s), SSE events received: {res['sse_events']}")


if __name__ == "__main__":
    main()
