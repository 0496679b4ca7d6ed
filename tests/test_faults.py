"""Fault suite (fail-safe issue): each fault on the real links (serial ptys, slcan, pymodbus server
on 127.0.0.1, SQLite on disk), and afterwards the lamp coil off, the fault named, the other slots
going on, and nothing reported as done that was not stored.
"""

import asyncio

import pytest

from drivers.protocol import serial_frames as sf
from drivers.sim.station_sim import SimStation
from tests.test_daemon_e2e import LAMP_TEST_PROFILE, coil, daemon, wait_for


async def test_out_of_range_frame_is_counted_and_a_driver_bug_faults_only_its_slot(tmp_path):
    """A checksum-valid frame with a 20-digit count once killed its slot's intake silently (and
    with it the stall watchdog) while the lamp stayed on. Now the frame is counted and skipped, and
    any unexpected exception in a driver faults that slot with a reason; the others go on."""
    async with SimStation(n_serial=3, n_can=0, seed=4, speed=50.0) as sim:
        async with daemon(sim, tmp_path, 50.0, profiles=LAMP_TEST_PROFILE) as st:
            bid = st.start_batch("lamp-test", None, "pytest")
            await wait_for(lambda: coil(sim), 20, "lamp coil on")
            sim.board(0).inject_garbage(sf.encode("D,1,2,99999999999999999999,0,0,25"))
            drv = st.slots["s02"].driver

            async def broken_read_block(timeout_s=1.0):
                raise RuntimeError("driver bug")

            drv.read_block = broken_read_block
            await wait_for(lambda: st.batch_status(bid)["slots"][1]["state"] == "faulted", 10, "s02 faulted")
            n0 = {s["slot"]: s["samples"] for s in st.batch_status(bid)["slots"]}
            await asyncio.sleep(1.0)
            status = st.batch_status(bid)
            by = {s["slot"]: s for s in status["slots"]}
            assert "board data could not be read: RuntimeError: driver bug" in by["s02"]["fault_reason"]
            for name in ("s01", "s03"):  # still streaming
                assert by[name]["state"] not in ("faulted", "interrupted"), by[name]
                assert by[name]["samples"] > n0[name]
            assert st.slots["s01"].driver.stats.frames_malformed >= 1
            st.abort(bid, reason="end of test")
            status = await st.wait_batch(bid, timeout_s=10)
            assert await coil(sim) is False


async def _serve(sim, tmp_path, *extra, limits=None, web_port=None):
    """`station serve` in a subprocess against the SimStation of this process (which outlives it)."""
    import os
    import sys

    from cli.commands.demo import sim_config
    from tests.test_daemon_e2e import _to_toml

    cfg = sim_config(sim, speed=sim.speed, db_url=f"sqlite:///{tmp_path / 'd.db'}", profiles=LAMP_TEST_PROFILE,
                     limits=limits, http_port=web_port or 8080)
    toml = tmp_path / "station.toml"
    toml.write_text(_to_toml(cfg))
    args = ["--no-web"] if web_port is None else []
    return await asyncio.create_subprocess_exec(
        sys.executable, "-m", "cli", "serve", "--config", str(toml), *args, "--start-batch", "lamp-test",
        *extra, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
        env=dict(os.environ, PYTHONUNBUFFERED="1"))


async def _time_until_lamp_off(sim, timeout_s: float) -> float:
    """Wall seconds until the plant's lamp is off, watched WITHOUT a Modbus request (a read of the
    relay would refresh its host watchdog)."""
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    while sim.world.lamp_on:
        if loop.time() - t0 > timeout_s:
            raise AssertionError(f"lamp still on {timeout_s} s later")
        await asyncio.sleep(0.01)
    return loop.time() - t0


async def test_sigkill_of_daemon_relay_host_watchdog_switches_lamp_off(tmp_path):
    """Nothing in the dead daemon can switch the lamp off: the relay's host watchdog (design 3.3),
    armed by the daemon at start and refreshed while it lives, does it within the watchdog time."""
    import signal

    async with SimStation(n_serial=1, n_can=0, seed=4, speed=20.0) as sim:
        proc = await _serve(sim, tmp_path, limits={"relay_watchdog_s": 1.0})
        try:
            await wait_for(lambda: sim.world.lamp_on, 60, "lamp on (daemon started the batch)")
            assert sim.modbus.watchdog_s == 1  # armed over Modbus: HR0 of the relay
            assert (1, 6, 0, [1]) in sim.modbus.writes
            await asyncio.sleep(2.0)  # the live daemon keeps the watchdog fed: lamp stays on
            assert sim.world.lamp_on and sim.modbus.watchdog_trips == 0
            proc.send_signal(signal.SIGKILL)
            await proc.wait()
            off_s = await _time_until_lamp_off(sim, 5.0)
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
        assert sim.modbus.watchdog_trips == 1
        assert off_s <= 1.0 + 0.2, off_s  # watchdog time + the relay's 50 ms check, some scheduling
        assert await coil(sim) is False
        print(f"SIGKILL -> lamp off in {off_s:.2f} s (relay host watchdog 1 s)")


async def test_sigterm_with_an_open_event_stream_switches_lamp_off_first(tmp_path):
    """Shutdown once waited up to 5 s for the web server (an open SSE stream) before the lamp."""
    import signal

    from tests.web_support import free_port

    port = free_port()
    async with SimStation(n_serial=1, n_can=0, seed=4, speed=20.0) as sim:
        proc = await _serve(sim, tmp_path, web_port=port)
        try:
            await wait_for(lambda: sim.world.lamp_on, 60, "lamp on")
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(b"GET /api/events?token=demo-operator-token HTTP/1.1\r\nHost: x\r\n\r\n")
            await writer.drain()
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 10)
            assert b" 200 " in head.split(b"\r\n")[0], head
            proc.send_signal(signal.SIGTERM)
            off_s = await _time_until_lamp_off(sim, 5.0)
            _, err = await asyncio.wait_for(proc.communicate(), 30)
            writer.close()
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
        assert proc.returncode == 0, err.decode()
        assert off_s < 1.0, off_s
        print(f"SIGTERM with an open event stream -> lamp off in {off_s:.2f} s")


async def test_relay_unreachable_lamp_state_unknown_and_alarm_at_first_failure(tmp_path):
    """No plate thermometer, the relay stops answering while the lamp is on: the first failed read
    raises a critical alarm naming the relay, the batch shows the lamp state 'unknown', the batch
    fails after three failed reads, and the relay's own watchdog switches the lamp off."""
    async with SimStation(n_serial=1, n_can=0, seed=4, speed=20.0) as sim:
        async with daemon(sim, tmp_path, 20.0, profiles=LAMP_TEST_PROFILE, thermometer=False,
                          limits={"relay_watchdog_s": 2.0}) as st:
            events = st.bus.subscribe(maxsize=100000)
            bid = st.start_batch("lamp-test", None, "pytest")
            await wait_for(lambda: sim.world.lamp_on and st.batch_status(bid)["lamp_state"] == "on", 20, "lamp on")
            loop = asyncio.get_running_loop()
            t0 = loop.time()
            sim.modbus.relay_offline = True
            await wait_for(lambda: st.batch_status(bid)["lamp_state"] == "unknown", 5, "lamp state unknown")
            alarm_s = None
            while alarm_s is None:
                ev = await asyncio.wait_for(events.get(), 5)
                if ev.kind == "Alarm" and "lamp relay not answering" in ev.text:
                    alarm_s = loop.time() - t0
                    assert ev.severity == "critical"
            status = await st.wait_batch(bid, timeout_s=30)
            assert status["state"] == "failed" and "lamp relay unreachable" in status["error"], status["error"]
            off_s = await _time_until_lamp_off(sim, 5.0)
            assert sim.modbus.watchdog_trips == 1
            sim.modbus.relay_offline = False
        assert alarm_s < 1.5, alarm_s  # the relay is read every third of the watchdog time (<= 0.67 s)
        print(f"relay unreachable -> alarm in {alarm_s:.2f} s, lamp off by its watchdog {off_s:.2f} s later")


def test_nan_or_infinite_safety_limits_are_refused():
    from station.config import parse_config

    base = {"slots": [{"name": "s1", "serial": "/dev/null"}], "lamp": {"tcp": {"host": "127.0.0.1", "port": 502}}}
    for key, value in (("max_dut_temp_c", float("nan")), ("lamp_max_on_s", float("inf")),
                       ("max_plate_temp_c", float("-inf"))):
        with pytest.raises(Exception) as err:
            parse_config({**base, "limits": {key: value}}, "<test>")
        assert key in str(err.value)


@pytest.fixture
def small_disk(tmp_path):
    """A real, size-limited file system (tmpfs, 16 MB) for the database: disk-full is a real ENOSPC."""
    import subprocess

    mnt = tmp_path / "disk"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=16m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {r.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def _fill(directory) -> "object":
    """Write a filler file until the file system is full; returns its path (delete it to free space).
    Only on a small test file system (the tmpfs of `small_disk` or the fault matrix): a directory
    that is not one (a mount that silently did not happen) would fill the machine's own disk and
    stall every other test's database."""
    import os

    fs = os.statvfs(directory)
    total_mb = fs.f_blocks * fs.f_frsize / 2**20
    if total_mb > 256:
        raise AssertionError(f"refusing to fill {directory}: a {total_mb:.0f} MB file system is not a test tmpfs")
    filler = directory / "filler.bin"
    # unbuffered: every write reaches the file system inside the try, so closing the file has no
    # buffered bytes left to flush into a full disk (a buffered close raised ENOSPC in CI)
    with open(filler, "wb", buffering=0) as f:
        try:
            while True:
                f.write(b"\0" * 65536)
        except OSError:
            pass
    return filler


async def test_disk_full_mid_batch_alarms_never_reports_done_and_loses_nothing(small_disk):
    """The database's disk fills during P hot. Before: 2,129 events dropped with an ERROR line
    each, the batch shown finished with every DUT done, health 'db: ok'. Now: a critical alarm at
    once, health says the writes fail, the batch ends 'failed' with no DUT 'done', and once space
    is freed every held event is stored: all segments and results in the database, integrity ok."""
    import sqlite3

    from db.database import Database
    from db.repository import batch_detail

    async with SimStation(n_serial=2, n_can=0, seed=6, speed=200.0) as sim:
        async with daemon(sim, small_disk, 200.0) as st:
            alarms = st.bus.subscribe(maxsize=1_000_000)
            bid = st.start_batch("fast-thermal", None, "pytest")
            await wait_for(lambda: st.batch_status(bid)["step_index"] >= 1, 60, "step P hot")
            await st.flush_db()
            filler = _fill(small_disk)
            await wait_for(lambda: st.storage_status().startswith("error"), 30, "writer reports the failure")
            assert "full" in st.storage_status()
            status = await st.wait_batch(bid, timeout_s=120)
            texts = []
            while not alarms.empty():
                ev = alarms.get_nowait()
                if ev.kind == "Alarm":
                    texts.append((ev.severity, ev.text))
            assert any(sev == "critical" and "database write failing" in t for sev, t in texts), texts
            assert status["state"] == "failed" and "results not stored" in status["error"], status["error"]
            assert all(s["state"] != "done" for s in status["slots"]), [s["state"] for s in status["slots"]]
            assert all("results not stored" in (s["fault_reason"] or "") for s in status["slots"])
            n_segments = {s["serial"]: s["segments"] for s in status["slots"]}
            assert all(n >= 4 for n in n_segments.values())
            assert await coil(sim) is False
            filler.unlink()  # the operator frees space: the held events go in
            await wait_for(lambda: st.storage_status() == "ok", 30, "writer recovers")
            await st.flush_db()
            assert st.writer.stats["dropped_events"] == 0
    db = Database(f"sqlite:///{small_disk / 'station.db'}")
    try:
        detail = batch_detail(db, bid)
        assert detail["state"] == "failed"
        stored = {r["serial"]: r["n_segments"] for r in detail["runs"]}
        assert stored == n_segments
        assert all(r.get("thermal") or r.get("result_seq") for r in detail["runs"]), detail["runs"]
    finally:
        db.dispose()
    con = sqlite3.connect(small_disk / "station.db")
    assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    con.close()


def _cli(*args, timeout_s=60):
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "cli", *args], capture_output=True, text=True,
                          timeout=timeout_s)


def _one_line_error(r, *words):
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr[-2000:]
    for w in words:
        assert w in lines[0], lines[0]


def test_port_taken_is_one_line_not_a_hang(tmp_path):
    """`station demo` once hung forever (uvicorn's SystemExit in a task) when its port was taken."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        r = _cli("demo", "--no-batch", "--serial", "1", "--can", "0", "--port", str(port),
                 "--db", f"sqlite:///{tmp_path / 'd.db'}")
    _one_line_error(r, f"127.0.0.1:{port}", "in use", "--port")


def test_corrupted_database_is_refused_at_start(tmp_path):
    """A damaged SQLite file once passed `serve --check` and then answered 500 on most routes."""
    from db.database import Database

    good = tmp_path / "d.db"
    db = Database(f"sqlite:///{good}")
    db.upgrade()
    db.dispose()  # checkpoint the WAL into the file
    data = bytearray(good.read_bytes())
    for i in range(4096 + 100, len(data), 997):  # damage every page after the first
        data[i] ^= 0x55
    good.write_bytes(bytes(data))
    assert len(data) > 8 * 4096
    r = _cli("demo", "--no-batch", "--serial", "1", "--can", "0", "--port", "0", "--db", f"sqlite:///{good}")
    _one_line_error(r, "corrupted", str(good))
    r = _cli("demo", "--no-batch", "--serial", "1", "--can", "0", "--port", "0", "--db", f"sqlite:///{tmp_path}")
    _one_line_error(r, "cannot open database")
    r = _cli("demo", "--no-batch", "--serial", "1", "--can", "0", "--port", "0", "--db", "sqlite:////proc/none/d.db")
    _one_line_error(r, "database sqlite:////proc/none/d.db")


def test_config_that_is_not_utf8_is_one_line(tmp_path):
    cfg = tmp_path / "station.toml"
    cfg.write_bytes(b'name = "ok"\nnote = "\xff"\n')
    r = _cli("serve", "--config", str(cfg), "--check")
    _one_line_error(r, "line 2", "not UTF-8")


async def test_fixture_failure_ends_the_batch_naming_the_device(tmp_path):
    """A fixture that stops answering mid-batch once ended it as `internal error: DriverError(...)`
    with a traceback; now the batch fails naming the fixture and what to check, lamp off."""
    async with SimStation(n_serial=1, n_can=0, seed=4, speed=100.0) as sim:
        async with daemon(sim, tmp_path, 100.0) as st:
            bid = st.start_batch("fast-thermal", None, "pytest")
            await wait_for(lambda: st.batch_status(bid)["step_index"] >= 1, 60, "step P hot")
            sim.modbus.fixture_offline = True  # the fixture stops answering: the move to N fails
            status = await st.wait_batch(bid, timeout_s=120)
            assert status["state"] == "failed", status
            assert status["error"].startswith("fixture failed: ") and "(check its power" in status["error"], status["error"]
            assert await coil(sim) is False
            assert "internal error" not in status["error"]
