"""Shared helpers of tests/test_web_*.py and tests/test_browser.py: a whole simulated station
(SimStation: serial boards on ptys, CAN boards behind slcan on a pty, Modbus TCP lamp relay on
127.0.0.1), the real Station daemon with a real SQLite file, and the web app served by uvicorn on
a free loopback port, all in one background thread with its own event loop (as in the daemon).
Tests talk to it over real HTTP."""

from __future__ import annotations

import asyncio
import shutil
import socket
import threading
import time
from concurrent.futures import Future
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

TOKENS = {
    "operator": "op-token-0123456789",
    "mes": "mes-token-0123456789",
    "admin": "admin-token-0123456789",
}


def auth(role: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {TOKENS[role]}"}


def free_port() -> int:
    """A port free now, for a server another process binds (a `station serve` child). An in-process
    server takes bound_socket() instead: no window in which the port can go to someone else."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def bound_socket() -> socket.socket:
    """A socket on 127.0.0.1 bound to a port the kernel chose, for uvicorn's serve(sockets=[...]).
    A port picked by free_port() and bound later can be taken in between (under load a CI run lost
    it to another connection: 'address already in use', every test of a module in error)."""
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    s.bind(("127.0.0.1", 0))
    return s


def sim_config(sim, *, speed: float, fixture: bool = False, webhook_url: str | None = None, db_url: str = "memory://",
               products: dict | None = None, profiles: dict | None = None):
    from station.config import parse_config

    slots = [{"name": f"s{i + 1}", "serial": p} for i, p in enumerate(sim.serial_ports)]
    slots += [
        {"name": f"c{n}", "can": {"interface": "slcan", "channel": sim.slcan_port, "node": n}} for n in sim.can_node_ids
    ]
    modbus = {"host": sim.modbus_host, "port": sim.modbus_port}
    data: dict[str, Any] = {
        "name": "test-station",
        "database_url": db_url,
        "slots": slots,
        "lamp": {"tcp": modbus, "unit": 1},
        "timing": {"speed": speed},
        "limits": {"lamp_max_on_s": 7200},
        "tokens": [{"token": t, "role": r, "name": f"test-{r}"} for r, t in TOKENS.items()],
        # a batch that runs until it is aborted (abort/prompt tests need one that is surely running)
        "profiles": {"hold": {"description": "test: hold the plate at P until aborted", "analysis": "none",
                              "steps": [{"name": "hold", "position": "P", "lamp": False, "require": "none",
                                         "dwell_s": 1e6, "timeout_s": 2e6}]}},
    }
    if fixture:
        data["fixture"] = {"tcp": modbus, "unit": 3}
    if webhook_url:
        data["mes_webhook_url"] = webhook_url
    if products:
        data["products"] = products
    if profiles:  # more site profiles beside "hold"
        data["profiles"].update(profiles)
    return parse_config(data, "test")


class LiveStation:
    """Context manager: SimStation + Station + SQLite + web app on http://127.0.0.1:<port>."""

    def __init__(self, tmp_path: Path, *, n_serial: int = 2, n_can: int = 1, speed: float = 400.0,
                 fixture: bool = False, seed: int = 7, outbox=False, sse_interval_s: float = 0.3,
                 access_log: bool = False, operator_hands: bool = False, sim_process: bool = False,
                 products: dict | None = None, profiles: dict | None = None) -> None:
        """operator_hands: without a motorized fixture, play the operator's hands: when a "turn the
        plate" prompt is confirmed, the simulated plate is turned to the prompted position (the
        operator turns it, then presses Confirm).

        sim_process: run the simulated boards in a child process (`python tests/web_support.py
        sim ...`), like real hardware outside the daemon, so that the simulator does not share the
        daemon's event loop and GIL (benchmarks); then `self.sim` only describes the links."""
        self.tmp_path = Path(tmp_path)
        self.n_serial, self.n_can, self.speed = n_serial, n_can, speed
        self.fixture, self.seed, self.outbox = fixture, seed, outbox
        self.sse_interval_s = sse_interval_s
        self.access_log = access_log
        self.operator_hands = operator_hands
        self.sim_process = sim_process
        self.products = products  # spec limits per product (station/decisions/limits.py), None = built-ins
        self.profiles = profiles  # site profiles added to the config (beside "hold")
        self._child = None
        self.prompts_answered: list[int] = []
        self._sock = bound_socket()
        self.port = self._sock.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self.db_path = self.tmp_path / "station.db"
        self.loop: asyncio.AbstractEventLoop | None = None
        self._ready: Future = Future()
        self._stop: asyncio.Event | None = None
        self._thread = threading.Thread(target=self._main, name="live-station", daemon=True)
        self.station = self.sim = self.app = self.server = None

    # --- lifecycle ----------------------------------------------------------------------------
    def __enter__(self) -> "LiveStation":
        self._thread.start()
        self._ready.result(timeout=60)
        return self

    def __exit__(self, *exc) -> None:
        if self.loop is not None and self._stop is not None:
            self.loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(timeout=60)

    def _main(self) -> None:
        try:
            asyncio.run(self._amain())
        except BaseException as exc:  # noqa: BLE001
            if not self._ready.done():
                self._ready.set_exception(exc)
            raise

    async def _amain(self) -> None:
        from drivers.sim.station_sim import SimStation
        from station.daemon.storage import open_database
        from station.daemon.supervisor import Station
        from web.app import create_app
        from web.server import serve_web, stop_web

        self.loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        if self.sim_process:
            sim_cm = _SimChild(self.n_serial, self.n_can, self.seed, self.speed)
        else:
            sim_cm = SimStation(n_serial=self.n_serial, n_can=self.n_can, seed=self.seed, speed=self.speed)
        async with sim_cm as sim:
            self.sim = sim
            cfg = sim_config(sim, speed=self.speed, fixture=self.fixture, db_url=f"sqlite:///{self.db_path}",
                             products=self.products, profiles=self.profiles)
            db = open_database(cfg.database_url)
            station = Station(cfg, db=db)
            await station.start()
            self.station = station
            hands = asyncio.create_task(self._hands(station.bus, sim)) if self.operator_hands else None
            self.app = create_app(station, outbox=self.outbox, sse_interval_s=self.sse_interval_s)
            # the daemon's own start-up (station serve/demo), slow-client limits included
            self.server, serve = await serve_web(station, "127.0.0.1", self.port, app=self.app, sock=self._sock,
                                                 access_log=self.access_log)
            await _started(self.server, serve)
            self._ready.set_result(True)
            await self._stop.wait()
            await stop_web(self.server, serve, timeout_s=10)
            if hands is not None:
                hands.cancel()
            await station.close()
            db.dispose()

    async def _hands(self, bus, sim) -> None:
        from drivers.sim.operator import operator_hands

        await operator_hands(bus, sim.world, self.prompts_answered)

    # --- helpers ------------------------------------------------------------------------------
    def call(self, fn, *args, timeout: float = 30, **kwargs):
        """Run fn (sync or coroutine function) in the station's loop and return its result."""

        async def run():
            out = fn(*args, **kwargs)
            if asyncio.iscoroutine(out):
                out = await out
            return out

        return asyncio.run_coroutine_threadsafe(run(), self.loop).result(timeout)

    def flush_db(self) -> None:
        self.call(self.station.flush_db, timeout=60)


class _SimChild:
    """SimStation in a child process; an async context manager giving its links like SimStation."""

    def __init__(self, n_serial: int, n_can: int, seed: int, speed: float) -> None:
        self.args = [str(n_serial), str(n_can), str(seed), str(speed)]
        self.proc = None

    async def __aenter__(self):
        import json
        import sys
        from types import SimpleNamespace

        self.proc = await asyncio.create_subprocess_exec(
            sys.executable, str(Path(__file__).resolve()), "sim", *self.args,
            stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE)
        line = await asyncio.wait_for(self.proc.stdout.readline(), 60)
        if not line:
            raise RuntimeError("simulated station child exited before it was ready")
        return SimpleNamespace(**json.loads(line))

    async def __aexit__(self, *exc) -> None:
        if self.proc is not None and self.proc.returncode is None:
            self.proc.stdin.close()  # the child ends when its stdin closes
            try:
                await asyncio.wait_for(self.proc.wait(), 10)
            except asyncio.TimeoutError:
                self.proc.kill()
                await self.proc.wait()


async def _sim_child_main(n_serial: int, n_can: int, seed: int, speed: float) -> None:
    import json
    import sys

    from drivers.sim.station_sim import SimStation

    async with SimStation(n_serial=n_serial, n_can=n_can, seed=seed, speed=speed) as sim:
        links = {"serial_ports": list(sim.serial_ports), "slcan_port": sim.slcan_port,
                 "can_node_ids": list(sim.can_node_ids), "modbus_host": sim.modbus_host,
                 "modbus_port": sim.modbus_port, "odr_hz": float(sim.world.odr_hz)}
        print(json.dumps(links), flush=True)
        await asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)  # until the parent closes it


def wait_for(predicate, timeout_s: float, interval_s: float = 0.1, what: str = "condition"):
    deadline = time.monotonic() + timeout_s
    last = None
    while time.monotonic() < deadline:
        last = predicate()
        if last:
            return last
        time.sleep(interval_s)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what} (last: {last!r})")


# --- a database with stored results, written through the real DbWriter ---------------------------

def thermal_json(tdb, tdsf, method: str) -> dict:
    return {
        "method": method,
        "n_segments": 4,
        "axes": {ax: {"tdb_mg_per_c": float(tdb[i]), "tdsf_ppm_per_c": float(tdsf[i])} for i, ax in enumerate("xyz")},
    }


def seed_results(db, n_duts: int = 5, *, batch_profile: str = "fast-thermal", serial_prefix: str = "WEB", seed: int = 0):
    """One batch with n_duts finished runs (samples, 4 segments, streaming + offline results).

    Returns {serial: {"run_id", "tdb", "tdsf"}} (the truth the API must give back)."""
    from db.writer import DbWriter
    from contracts.events import DutResult, DutVerdict, SamplesReceived, SegmentLogged, SlotStateChanged
    from contracts.run_records import ThermalReport
    from contracts.types import SampleBlock, Segment

    rng = np.random.default_rng(seed)
    batch_id = db.create_batch(batch_profile, "tester", {})
    writer = DbWriter(db, interval_s=0.05)
    truth = {}
    try:
        for i in range(n_duts):
            serial = f"{serial_prefix}{i + 1:04d}"
            slot = f"s{i + 1}"
            run_id = db.create_run(batch_id, slot, serial, "LIS3DSH", {"serial": serial})
            writer.bind_run(batch_id, slot, run_id)
            n = 600
            t = np.arange(n) / 3.125
            temp = 25.0 + 20.0 * (1 - np.exp(-t / 60.0))
            sign = np.where(np.arange(n) < n // 2, 1.0, -1.0)[:, None]
            tdb = rng.uniform(-1.2, 1.4, 3)
            tdsf = rng.uniform(-500, 0, 3)
            acc0 = 0.577 * sign * np.ones((n, 3))
            acc = acc0 + (temp - 25.0)[:, None] * (tdb * 1e-3 + tdsf * 1e-6 * acc0) + rng.normal(0, 1e-4, (n, 3))
            acc = np.round(acc / 60e-6) * 60e-6
            writer.submit(SlotStateChanged(batch_id, slot=slot, serial=serial, state="running"))
            writer.submit(SamplesReceived(batch_id, slot=slot, serial=serial, step_index=0,
                                          block=SampleBlock(t, acc, np.round(temp)), lamp_on=True, position=0))
            for k in range(4):
                seg = Segment(index=k, orientation=k // 2, n_samples=100, t_start_s=float(t[k * 150]),
                              t_end_s=float(t[k * 150 + 100]), acc_mean_g=tuple(acc[k * 150:k * 150 + 100].mean(0)),
                              acc_std_g=(1e-4, 1e-4, 1e-4), temp_mean_c=float(temp[k * 150 + 50]), temp_std_c=0.3,
                              position=k // 2)
                writer.submit(SegmentLogged(batch_id, slot=slot, serial=serial, step_index=k, segment=seg))
            thermal = {"serial": serial, "axes": thermal_json(tdb, tdsf, "offline")["axes"],
                       "streaming": thermal_json(tdb * 1.01, tdsf * 1.01, "streaming"),
                       "offline": thermal_json(tdb, tdsf, "offline")}
            writer.submit(DutResult(batch_id, slot=slot, serial=serial, thermal=ThermalReport.from_json(thermal), sfem=None))
            writer.submit(SlotStateChanged(batch_id, slot=slot, serial=serial, state="done"))
            # the run's final verdict: the MES record (design 8; results alone are data)
            writer.submit(DutVerdict(batch_id, slot=slot, serial=serial, verdict={
                "verdict": "pass", "grade": "A", "tray": "A", "reason": "all limits met", "attempt": 1,
                "run_id": run_id}))
            truth[serial] = {"run_id": run_id, "tdb": tdb, "tdsf": tdsf, "slot": slot, "batch_id": batch_id}
        assert writer.flush(30)
    finally:
        writer.close()
    db.set_batch_state(batch_id, "finished")
    return truth


if __name__ == "__main__":  # `python tests/web_support.py sim N_SERIAL N_CAN SEED SPEED` (see _SimChild)
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    if len(sys.argv) == 6 and sys.argv[1] == "sim":
        asyncio.run(_sim_child_main(int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5])))
    else:
        raise SystemExit("usage: web_support.py sim N_SERIAL N_CAN SEED SPEED")


async def _started(server, task, timeout_s: float = 30.0) -> None:
    """Wait until serve_web's server accepts (it returns after at most 4 s, started or not)."""
    t0 = time.monotonic()
    while not server.started:
        if task.done():
            task.result()
            raise RuntimeError("test web server exited before it started")
        assert time.monotonic() - t0 < timeout_s, "test web server did not start"
        await asyncio.sleep(0.02)


def serve_in_thread(app, timeout_s: float = 30.0):
    """Run a FastAPI app on a real uvicorn server on 127.0.0.1 in a daemon thread, started as the
    daemon starts its own (web/server.py serve_web); returns (url, stop). For tests that need the
    HTTP stack but not a daemon (records, audit, certificates, exports, the MES feed)."""
    from web.server import serve_web, stop_web

    sock = bound_socket()
    port = sock.getsockname()[1]
    ready: Future = Future()

    async def main() -> None:
        stop_event = asyncio.Event()
        try:
            server, task = await serve_web(app.state.station, "127.0.0.1", port, app=app, sock=sock)
            await _started(server, task, timeout_s)
        except BaseException as exc:  # noqa: BLE001 - the test thread raises it
            ready.set_exception(exc)
            raise
        ready.set_result((asyncio.get_running_loop(), stop_event))
        await stop_event.wait()
        await stop_web(server, task, timeout_s=10)

    th = threading.Thread(target=lambda: asyncio.run(main()), name="test-web", daemon=True)
    th.start()
    loop, stop_event = ready.result(timeout_s + 10)

    def stop() -> None:
        loop.call_soon_threadsafe(stop_event.set)
        th.join(10)

    return f"http://127.0.0.1:{port}", stop


class IdleStation:
    """What the page's start-up asks of the daemon: an idle station with no slots (pages that show
    only stored records: the Records view, replays)."""

    def __init__(self, db, config=None):
        from contracts.events import EventBus

        self.db, self.config = db, config  # a config: the station's, for routes that read it (results)
        self.bus = EventBus()  # the page's live stream: nothing happens on an idle station

    def profiles(self):
        return []

    def slots_status(self):
        return []

    def batch_ids(self):
        return []

    def running_batch(self):
        return None


CHROMIUM = shutil.which("chromium") or ("/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None)


@contextmanager
def chromium_page(width: int = 1400, height: int = 1000, timeout_ms: int = 20_000):
    """(page, errors): a page of Debian's headless chromium driven by playwright, and the list its
    uncaught JavaScript errors go to (a test asserts it is empty). The browser is closed after."""
    from playwright import sync_api

    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True,
                                     args=["--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"])
        try:
            page = browser.new_page(viewport={"width": width, "height": height})
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(f"{e} at {getattr(e, 'stack', '')}"))
            page.set_default_timeout(timeout_ms)
            yield page, errors
        finally:
            browser.close()
