"""The daemon end to end through the real protocols: serial boards on pseudo-terminals, CAN boards
behind an slcan adapter on a pseudo-terminal, lamp relay / fixture / thermometer on a pymodbus TCP
server on 127.0.0.1, SQLite on disk. Results are checked against the simulator's truth, the lamp
coil is read back from the Modbus server, rows from the database.
"""

import asyncio
import re
import os
import signal
import sys
from contextlib import asynccontextmanager

import numpy as np
import pytest

from drivers.modbus_devices import ModbusLampRelay, ModbusLink
from drivers.sim.station_sim import SimStation
from cli.commands.demo import sim_config, truth_by_slot
from station.config import parse_config
from station.daemon.storage import open_database
from station.daemon.supervisor import Station
from contracts.types import AXES

TDB_TOL_MG_PER_C = 0.03
TDSF_TOL_PPM_PER_C = 40.0

LAMP_TEST_PROFILE = {
    "lamp-test": {
        "description": "lamp on and wait (safety tests)",
        "steps": [{"name": "hot", "position": "P", "lamp": True, "require": "none", "dwell_s": 1e6, "timeout_s": 2e6}],
    }
}


@asynccontextmanager
async def daemon(sim, tmp_path, speed, **kw):
    cfg = parse_config(sim_config(sim, speed=speed, db_url=f"sqlite:///{tmp_path / 'station.db'}", **kw), "<test>")
    db = open_database(cfg.database_url)
    st = Station(cfg, db=db)
    await st.start()
    try:
        yield st
    finally:
        await st.close()
        db.dispose()


async def coil(sim) -> bool:
    """The lamp coil as the Modbus server holds it, read over a fresh Modbus TCP connection."""
    link = ModbusLink(sim.modbus_host, sim.modbus_port)
    try:
        return await ModbusLampRelay(link, unit=1).read_lamp()
    finally:
        await link.close()


async def wait_for(pred, timeout_s, what):
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    while loop.time() < end:
        value = pred()
        if asyncio.iscoroutine(value):
            value = await value
        if value:
            return
        await asyncio.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def check_results(status, truths, slots):
    for s in status["slots"]:
        if s["slot"] not in slots:
            continue
        assert s["state"] == "done", s
        axes = s["result"]["axes"]
        t = truths[s["slot"]]
        for k, a in enumerate(AXES):
            assert abs(axes[a]["tdb_mg_per_c"] - t.tdb_mg_per_c[k]) < TDB_TOL_MG_PER_C, (s["slot"], a, axes[a], t.tdb_mg_per_c)
            assert abs(axes[a]["tdsf_ppm_per_c"] - t.tdsf_ppm_per_c[k]) < TDSF_TOL_PPM_PER_C, (s["slot"], a, axes[a], t.tdsf_ppm_per_c)


@pytest.mark.slow
@pytest.mark.timeout(240)
async def test_fast_thermal_8_serial_4_can_matches_truth(tmp_path):
    speed = 120.0
    async with SimStation(n_serial=8, n_can=4, seed=11, speed=speed) as sim:
        async with daemon(sim, tmp_path, speed) as st:
            assert all(s["state"] == "identified" for s in st.slots_status())
            events = st.bus.subscribe(maxsize=1_000_000)
            bid = st.start_batch("fast-thermal", None, "pytest")
            status = await st.wait_batch(bid, timeout_s=200)
            assert status["state"] == "finished", status["error"]
            truths = truth_by_slot(sim)
            check_results(status, truths, set(truths))
            # the streaming (martinez2022 3.3) result is there too and in the right ballpark
            for s in status["slots"]:
                live = s["result"]["streaming_live"]["axes"]
                t = truths[s["slot"]]
                assert max(abs(live[a]["tdb_mg_per_c"] - t.tdb_mg_per_c[k]) for k, a in enumerate(AXES)) < 0.1
            assert await coil(sim) is False  # lamp off after batch end
            kinds = []
            while not events.empty():
                kinds.append(events.get_nowait().kind)
            for k in ("SamplesReceived", "SegmentLogged", "DutResult", "SlotStateChanged", "StepStarted", "LampChanged"):
                assert k in kinds, k
            assert kinds.count("DutResult") == 12
            await st.flush_db()
            from db.repository import batch_detail, dut_by_serial

            detail = batch_detail(st.db, bid)
            assert detail["state"] == "finished"
            assert len(detail["runs"]) == 12 and all(r["state"] == "done" for r in detail["runs"])
            assert all(r["n_segments"] >= 4 for r in detail["runs"])
            dut = dut_by_serial(st.db, sim.truths[0].serial)
            assert abs(dut["thermal"]["x"]["tdb_mg_per_c"] - sim.truths[0].tdb_mg_per_c[0]) < TDB_TOL_MG_PER_C


@pytest.mark.slow
@pytest.mark.timeout(240)
async def test_faults_stay_in_their_slot(tmp_path):
    """s04's pty closes mid-run, s05 goes silent, s06 sends only garbage: each faults its own slot
    with its own reason; s01/s02 get garbage and bad checksums in their stream, which are counted,
    and they still finish with correct results, like s03 and the CAN board."""
    speed = 150.0
    async with SimStation(n_serial=6, n_can=1, seed=5, speed=speed) as sim:
        async with daemon(sim, tmp_path, speed, timing={"stall_timeout_s": 3.0}) as st:
            bid = st.start_batch("fast-thermal", None, "pytest")

            async def injector():
                await wait_for(lambda: st.batch_status(bid)["step_index"] >= 1, 60, "step P hot")
                sim.board(3).disconnect()
                sim.board(4).stop_streaming()
                sim.board(5).stop_streaming()
                for _ in range(60):
                    sim.board(0).inject_garbage(b"\x00\xffgarbage$D,1,2*ZZ\n")
                    sim.board(1).corrupt_next(3)
                    sim.board(5).inject_garbage(b"$D,1,2,3*00\nnoise\xfe\n")
                    await asyncio.sleep(0.1)

            inj = asyncio.create_task(injector())
            status = await st.wait_batch(bid, timeout_s=200)
            await inj
            assert status["state"] == "finished", status["error"]
            by = {s["slot"]: s for s in status["slots"]}
            assert by["s04"]["state"] == "faulted" and "link lost" in by["s04"]["fault_reason"]
            assert by["s05"]["state"] == "faulted" and "no samples for" in by["s05"]["fault_reason"]
            assert by["s06"]["state"] == "faulted" and "only garbage" in by["s06"]["fault_reason"]
            s1, s2 = by["s01"]["link_stats"], by["s02"]["link_stats"]
            assert s1["bytes_skipped"] + s1["frames_malformed"] + s1["frames_bad_checksum"] > 60
            assert s2["frames_bad_checksum"] >= 100
            check_results(status, truth_by_slot(sim), {"s01", "s02", "s03", "c01"})
            assert await coil(sim) is False


async def test_abort_switches_lamp_coil_off(tmp_path):
    async with SimStation(n_serial=2, n_can=1, seed=2, speed=50.0) as sim:
        async with daemon(sim, tmp_path, 50.0, profiles=LAMP_TEST_PROFILE) as st:
            bid = st.start_batch("lamp-test", None, "pytest")
            await wait_for(lambda: coil(sim), 20, "lamp coil on")
            assert sim.world.lamp_on
            st.abort(bid, reason="operator pressed abort")
            status = await st.wait_batch(bid, timeout_s=10)
            assert status["state"] == "aborted" and status["ended_by"] == "operator"
            assert re.fullmatch(r"aborted by operator at \S+ \S+ UTC: operator pressed abort", status["error"])
            assert await coil(sim) is False
            with pytest.raises(KeyError):
                st.batch_status(9999)
            with pytest.raises(ValueError):
                st.start_batch("no-such-profile")


async def test_over_temperature_trips_lamp(tmp_path):
    """A DUT limit just above ambient: the lamp heats the plate, the first DUT over the limit trips
    the lamp off, and the batch fails with the reason."""
    async with SimStation(n_serial=2, n_can=1, seed=3, speed=200.0) as sim:
        async with daemon(sim, tmp_path, 200.0, profiles=LAMP_TEST_PROFILE, limits={"max_dut_temp_c": 33.0},
                          thermometer=False) as st:
            alarms = st.bus.subscribe(maxsize=100000)
            bid = st.start_batch("lamp-test", None, "pytest")
            status = await st.wait_batch(bid, timeout_s=60)
            assert status["state"] == "failed"
            assert "safety trip" in status["error"] and "> max 33 C" in status["error"]
            assert await coil(sim) is False
            texts = []
            while not alarms.empty():
                e = alarms.get_nowait()
                if e.kind == "Alarm":
                    texts.append(e.text)
            assert any("safety trip" in t for t in texts)


async def test_plate_thermometer_trips_lamp(tmp_path):
    async with SimStation(n_serial=1, n_can=0, seed=3, speed=200.0) as sim:
        async with daemon(sim, tmp_path, 200.0, profiles=LAMP_TEST_PROFILE, limits={"max_plate_temp_c": 32.0}) as st:
            bid = st.start_batch("lamp-test", None, "pytest")
            status = await st.wait_batch(bid, timeout_s=60)
            assert status["state"] == "failed" and "plate at" in status["error"], status["error"]
            assert await coil(sim) is False


async def test_sigterm_of_daemon_process_switches_lamp_off(tmp_path):
    """`station serve` in a subprocess against a SimStation in this process: SIGTERM while the lamp
    is on; the coil on the (still running) Modbus server reads 0 afterwards."""
    import tomllib  # noqa: F401  (the config below must be valid TOML: written by hand)

    async with SimStation(n_serial=2, n_can=1, seed=4, speed=50.0) as sim:
        cfg = sim_config(sim, speed=50.0, db_url=f"sqlite:///{tmp_path / 'd.db'}", profiles=LAMP_TEST_PROFILE)
        toml = tmp_path / "station.toml"
        toml.write_text(_to_toml(cfg))
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "cli", "serve", "--config", str(toml), "--no-web", "--start-batch", "lamp-test",
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, env=env,
        )
        try:
            await wait_for(lambda: coil(sim), 60, "lamp coil on (daemon started the batch)")
            proc.send_signal(signal.SIGTERM)
            out, err = await asyncio.wait_for(proc.communicate(), 30)
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
        assert proc.returncode == 0, err.decode()
        assert "Traceback" not in err.decode()
        assert await coil(sim) is False
        assert not sim.world.lamp_on
        from db.database import Database
        from db.repository import batch_detail

        db = Database(f"sqlite:///{tmp_path / 'd.db'}")
        assert batch_detail(db, 1)["state"] == "interrupted"
        db.dispose()


async def test_clear_errors_for_wrong_port_and_unreachable_modbus(tmp_path):
    async with SimStation(n_serial=1, n_can=0, seed=4, speed=10.0) as sim:
        cfg = sim_config(sim, speed=10.0, db_url=f"sqlite:///{tmp_path / 'd.db'}")
        cfg["slots"].append({"name": "s99", "serial": "/dev/ttyNOSUCH7"})
        toml = tmp_path / "station.toml"
        toml.write_text(_to_toml(cfg))
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "cli", "serve", "--config", str(toml), "--check",
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
        )
        out, err = await asyncio.wait_for(proc.communicate(), 60)
        assert proc.returncode == 1
        lines = [ln for ln in err.decode().splitlines() if ln.strip()]
        assert len(lines) == 1 and "slot s99" in lines[0] and "/dev/ttyNOSUCH7" in lines[0], lines
        assert "1/2 slot(s) identified" in out.decode()

        cfg["lamp"]["tcp"]["port"] = 1  # nothing listens there
        toml.write_text(_to_toml(cfg))
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "cli", "serve", "--config", str(toml), "--check",
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
        )
        out, err = await asyncio.wait_for(proc.communicate(), 60)
        assert proc.returncode == 2
        lines = [ln for ln in err.decode().splitlines() if ln.strip()]
        assert len(lines) == 1 and "lamp" in lines[0] and "127.0.0.1:1" in lines[0], lines


def _to_toml(cfg: dict) -> str:
    """Just enough TOML for sim_config's dicts (tables, arrays of tables, inline tables)."""

    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (int, float)):
            return repr(v) if not (isinstance(v, float) and (v != v or v in (float("inf"), -float("inf")))) else "0"
        if isinstance(v, str):
            return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{k} = {val(x)}" for k, x in v.items()) + " }"
        if isinstance(v, list):
            return "[ " + ", ".join(val(x) for x in v) + " ]"
        raise TypeError(v)

    lines = [f"{k} = {val(v)}" for k, v in cfg.items() if not isinstance(v, (dict, list))]
    for k, v in cfg.items():
        if isinstance(v, dict) and k != "profiles":
            lines.append(f"[{k}]")
            lines += [f"{kk} = {val(x)}" for kk, x in v.items()]
    for k, v in cfg.items():
        if isinstance(v, list):
            for item in v:
                lines.append(f"[[{k}]]")
                lines += [f"{kk} = {val(x)}" for kk, x in item.items()]
    for name, prof in cfg.get("profiles", {}).items():
        lines.append(f'[profiles."{name}"]')
        lines += [f"{kk} = {val(x)}" for kk, x in prof.items() if kk != "steps"]
        for step in prof["steps"]:
            lines.append(f'[[profiles."{name}".steps]]')
            lines += [f"{kk} = {val(x)}" for kk, x in step.items()]
    return "\n".join(lines) + "\n"


@pytest.mark.timeout(240)
async def test_demo_station_runs_sfem_24_with_its_simulated_chamber(tmp_path):
    """The demo simulates every instrument of design 3.3 (the chamber included), so sfem-24 runs
    and its SFEM per temperature step reaches the database and the results API's shape."""
    from db.repository import batch_detail

    async with SimStation(n_serial=1, n_can=0, seed=12, speed=4000.0) as sim:
        async with daemon(sim, tmp_path, 4000.0) as st:
            bid = st.start_batch("sfem-24", None, "pytest")
            status = await st.wait_batch(bid, timeout_s=200)
            assert status["state"] == "finished", status["error"]
            slot = status["slots"][0]
            assert slot["state"] == "done", slot
            temps = slot["result"]["steps"]  # the SFEM record (contracts/sfem_result.py), coldest step first
            assert len(temps) == 3 and slot["result"]["reference_step"] == 0
            truth = sim.truths[0]
            for t, setpoint in zip(temps, (25, 45, 65)):
                assert setpoint - 5 < t["temp_c"] < setpoint + 10
            # Every step: the SFEM removes the frame errors down to the noise (~0.03 mg here). (The
            # 65 C step once left 5-13 mg: samples of the previous position, 45 deg away, that
            # arrived after the fixture reported the move; static steps now start at the first
            # sample facing their position, contracts.positions.first_facing.)
            for t in temps:
                assert t["rmse_after_mg"] < 0.01 * t["rmse_before_mg"], t["temp_c"]
            await st.flush_db()
            run = batch_detail(st.db, bid)["runs"][0]
            assert run["serial"] == truth.serial
