"""One station owns its database, its ports and its relay (issue 36, part 4).

Real parts throughout: claims held by real child processes (one of them SIGKILLed), real ptys,
a real Modbus TCP server on 127.0.0.1, real PostgreSQL when it is reachable, and the headline: a
`station serve` subprocess running a fast-thermal batch on a SimStation while `station serve
--check` on the same config is refused in one line with the owner's PID and host, having sent no
byte to a board, no Modbus write and no database write; the batch finishes untouched.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from db_helpers import pg_database, pg_reachable
from drivers.sim.station_sim import SimStation
from cli.commands.demo import sim_config
from station.config import StationConfig, parse_config
from station.daemon.ownership import ClaimRefused, StationClaim, station_resources
from station.daemon.storage import open_database
from station.daemon.supervisor import Station
from test_daemon_e2e import _to_toml

ROOT = Path(__file__).resolve().parents[1]
HOST = socket.gethostname()
CHILD = """
import json, sys, time
from station.config import parse_config
from station.daemon.ownership import StationClaim
spec = json.load(open(sys.argv[1]))
claim = StationClaim.take(parse_config(spec["config"], "<child>"), database_url=spec["database_url"],
                          command="ownership child")
print("CLAIMED", flush=True)
time.sleep(600)
"""


def _env() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")


def _config(tmp_path: Path, *, lock_dir: str, serial: str, modbus_port: int, name: str = "line3-s1") -> StationConfig:
    return parse_config({
        "name": name, "lock_dir": lock_dir,
        "slots": [{"name": "s01", "serial": serial}],
        "lamp": {"tcp": {"host": "127.0.0.1", "port": modbus_port}, "unit": 1},
    }, "<test>")


class ClaimChild:
    """A child python process that takes a claim and holds it until it is killed."""

    def __init__(self, tmp_path: Path, cfg: StationConfig, database_url: str | None) -> None:
        spec = tmp_path / f"child-{time.monotonic_ns()}.json"
        spec.write_text(json.dumps({"config": cfg.model_dump(mode="json"), "database_url": database_url}))
        self.proc = subprocess.Popen([sys.executable, "-c", CHILD, str(spec)], stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, env=_env(), cwd=ROOT)
        line = self.proc.stdout.readline().strip()
        assert line == "CLAIMED", (line, self.proc.stderr.read() if self.proc.poll() is not None else "")

    def sigkill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        assert self.proc.wait(20) == -signal.SIGKILL

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(20)


@pytest.fixture
def pty_paths():
    """Two real pseudo-terminals (slave paths), as boards would be."""
    fds = [os.openpty() for _ in range(2)]
    yield [os.ttyname(s) for _, s in fds]
    for m, s in fds:
        os.close(m)
        os.close(s)


# ----------------------------------------------------------------------------------- the core
@pytest.mark.parametrize("shared", ["database", "serial port", "relay endpoint"])
def test_a_second_claim_on_one_shared_resource_is_refused_until_the_owner_is_sigkilled(tmp_path, pty_paths, shared):
    """Station A (a child process) and station B share exactly one resource; B is refused with A's
    PID and host and that resource named, and nothing else; once A is SIGKILLed (no clean-up at
    all) B gets everything. A and B use different lock directories: the database still collides
    (its lock file sits beside it)."""
    with socket.socket() as s1, socket.socket() as s2:  # two real endpoints on 127.0.0.1
        s1.bind(("127.0.0.1", 0))
        s2.bind(("127.0.0.1", 0))
        ports = [s1.getsockname()[1], s2.getsockname()[1]]
        db_a, db_b = f"sqlite:///{tmp_path / 'a.db'}", f"sqlite:///{tmp_path / 'b.db'}"
        a = _config(tmp_path, lock_dir=str(tmp_path / "locks-a"), serial=pty_paths[0], modbus_port=ports[0])
        b = _config(tmp_path, lock_dir=str(tmp_path / "locks-a" if shared != "database" else tmp_path / "locks-b"),
                    serial=pty_paths[1], modbus_port=ports[1])
        if shared == "database":
            db_b = db_a
            expected = f"the database {os.path.realpath(tmp_path / 'a.db')}"
        elif shared == "serial port":
            link = tmp_path / "ttyBOARD"  # a udev-style symlink to the same tty: the same port
            link.symlink_to(pty_paths[0])
            b.slots[0].serial = str(link)
            expected = f"the serial port {os.path.realpath(pty_paths[0])} (slot s01)"
        else:
            assert b.lamp.tcp is not None
            b.lamp.tcp.host, b.lamp.tcp.port = "localhost", ports[0]
            expected = f"the lamp relay at modbus tcp 127.0.0.1:{ports[0]}"
        child = ClaimChild(tmp_path, a, db_a)
        try:
            t0 = time.monotonic()
            with pytest.raises(ClaimRefused) as refused:
                StationClaim.take(b, database_url=db_b, command="test")
            took_s = time.monotonic() - t0
            msg = str(refused.value)
            assert msg.startswith(expected + " is held by ownership child (PID "), msg
            assert f"PID {child.proc.pid} on host {HOST}, since " in msg and " UTC)" in msg, msg
            assert msg.endswith("one station owns its boards, relay and database; stop it first"), msg
            assert [r.kind for r, _ in refused.value.held] == [
                {"database": "database", "serial port": "serial port", "relay endpoint": "Modbus endpoint"}[shared]]
            assert took_s < 1.0, took_s
            if shared == "database":  # the owner file names the owner, untouched by the refused claim
                owner = json.loads((tmp_path / "a.db.owner").read_text())
                assert owner["pid"] == child.proc.pid and owner["host"] == HOST and owner["station"] == "line3-s1"
                assert owner["started_at"].endswith("Z") and owner["resource"] == expected
            child.sigkill()
            claim = StationClaim.take(b, database_url=db_b, command="test")  # the kernel let go of A's locks
            assert claim.held
            claim.release()
            assert not claim.held
            StationClaim.take(b, database_url=db_b).release()  # and again, in the same process
        finally:
            child.stop()


def test_the_refusal_names_every_held_resource_at_most_three_then_and_n_more(tmp_path, pty_paths):
    cfg = parse_config({
        "name": "line3-s2", "lock_dir": str(tmp_path / "locks"),
        "slots": [{"name": "s01", "serial": pty_paths[0]}, {"name": "s02", "serial": pty_paths[1]},
                  {"name": "c01", "can": {"interface": "slcan", "channel": pty_paths[0] + "x", "node": 1}}],
        "lamp": {"tcp": {"host": "127.0.0.1", "port": 5020}, "unit": 1},
        "fixture": {"tcp": {"host": "127.0.0.1", "port": 5020}, "unit": 3},
    }, "<test>")
    url = f"sqlite:///{tmp_path / 'station.db'}"
    res = station_resources(cfg, database_url=url, config_path=tmp_path / "station.toml")
    assert [r.kind for r in res] == ["database", "serial port", "serial port", "CAN channel", "Modbus endpoint",
                                     "config file"]
    assert res[4].label == "the lamp relay and fixture at modbus tcp 127.0.0.1:5020"  # one endpoint, one lock
    assert len({r.lock_path for r in res}) == len(res)
    assert station_resources(cfg, database_url="memory://")[0].kind == "serial port"  # a temporary db: no claim
    replay = cfg.model_copy(update={"replay_of": "batch 12 of sqlite:///var/station.db"})
    assert "database" not in [r.kind for r in station_resources(replay, database_url=url)]  # stores beside a live one
    child = ClaimChild(tmp_path, cfg, url)
    try:
        with pytest.raises(ClaimRefused) as refused:
            StationClaim.take(cfg, database_url=url)
        msg = str(refused.value)
        assert f"and 2 more are held by ownership child (PID {child.proc.pid} on host {HOST}" in msg, msg
        assert len(refused.value.held) == 5
    finally:
        child.stop()


@pytest.mark.postgres
@pytest.mark.skipif(not pg_reachable(), reason="PostgreSQL not reachable")
def test_postgres_a_station_name_is_owned_by_one_process_on_a_shared_database(tmp_path, pty_paths):
    """A line shares one PostgreSQL database; each station's name is one session-level advisory
    lock. A second claimant of the same name is refused with the owner's PID and host (from
    pg_stat_activity's application_name); another station name on the same database is free; the
    owner's SIGKILL ends its session and frees the name."""
    with pg_database() as url:
        a = _config(tmp_path, lock_dir=str(tmp_path / "locks-a"), serial=pty_paths[0], modbus_port=5020)
        b = _config(tmp_path, lock_dir=str(tmp_path / "locks-b"), serial=pty_paths[1], modbus_port=5021)
        other = _config(tmp_path, lock_dir=str(tmp_path / "locks-c"), serial=str(tmp_path / "ttyX"), modbus_port=5022,
                        name="line3-s9")
        child = ClaimChild(tmp_path, a, url)
        try:
            with pytest.raises(ClaimRefused) as refused:
                StationClaim.take(b, database_url=url)
            msg = str(refused.value)
            assert msg.startswith("the station name 'line3-s1' on the database postgresql+psycopg://"), msg
            assert f"held by ownership child (PID {child.proc.pid} on host {HOST[:20]}" in msg, msg
            StationClaim.take(other, database_url=url).release()  # another station of the line: free
            child.sigkill()
            deadline = time.monotonic() + 10  # the server notices the dead client's socket at once
            while True:
                try:
                    StationClaim.take(b, database_url=url).release()
                    break
                except ClaimRefused:
                    assert time.monotonic() < deadline, "the SIGKILLed owner's advisory lock was not dropped"
                    time.sleep(0.1)
        finally:
            child.stop()


# ----------------------------------------------------------------------------------- in process
async def test_in_process_stations_hold_the_claim_from_start_to_close(tmp_path):
    """The tests' and `station demo`'s in-process Station claims at start(): a second Station on
    the same hardware is refused before it writes to the relay; after close() the claim is free
    again for the next Station of the same process."""
    async with SimStation(n_serial=1, n_can=1, seed=3, speed=50.0) as sim:
        data = sim_config(sim, speed=50.0, db_url=f"sqlite:///{tmp_path / 'station.db'}")
        cfg = parse_config(data, "<test>")
        db = open_database(cfg.database_url)
        first = Station(cfg, db=db)
        await first.start()
        try:
            n_writes = len(sim.modbus.writes)
            n_cmds = len(sim.serial_boards[0].commands)
            second = Station(parse_config(data, "<test>"), db=db)
            with pytest.raises(ClaimRefused, match=f"PID {os.getpid()} on host"):
                await second.start()
            await second.close()
            assert sim.modbus.writes[n_writes:] == [] and len(sim.serial_boards[0].commands) == n_cmds
            assert first.slots_status()[0]["state"] == "identified"
        finally:
            await first.close()
        assert first.claim is None
        third = Station(cfg, db=db)
        await third.start()
        await third.close()
        db.dispose()


# ----------------------------------------------------------------------------------- the headline
def _one_line(err: bytes) -> str:
    lines = [ln for ln in err.decode().splitlines() if ln.strip()]
    assert len(lines) == 1, lines
    return lines[0]


async def _station(*args: str) -> tuple[int, str, str, float]:
    t0 = time.monotonic()
    proc = await asyncio.create_subprocess_exec(sys.executable, "-m", "cli", *args, cwd=ROOT, env=_env(),
                                                stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    out, err = await asyncio.wait_for(proc.communicate(), 60)
    assert proc.returncode is not None
    return proc.returncode, out.decode(), err.decode(), time.monotonic() - t0


@pytest.mark.timeout(300)
async def test_check_during_a_running_batch_is_refused_and_touches_nothing(tmp_path):
    """`station serve` runs fast-thermal on simulated hardware; in its P hot step (lamp on)
    `station serve --check` on the same config exits non-zero within seconds, one stderr line with
    the owner's PID and host; meanwhile no command frame reached any board, no Modbus write reached
    the relay, fixture or thermometer, nothing was marked interrupted; the batch finishes with every
    DUT done. A second `station serve` on the same database but other ports is refused too."""
    speed = 250.0
    async with SimStation(n_serial=2, n_can=1, seed=5, speed=speed) as sim:
        db_path = tmp_path / "station.db"
        data = sim_config(sim, speed=speed, db_url=f"sqlite:///{db_path}")
        data["limits"] = {"lamp_max_on_s": 9000.0}
        # this test's own lock folder: the default one is the user's, shared with every test that
        # runs beside it (test_daemon_e2e's --check holds /dev/ttyNOSUCH7 there at times, and the
        # second serve below would be refused for that port instead of for the database)
        data["lock_dir"] = str(tmp_path / "locks")
        toml = tmp_path / "station.toml"
        toml.write_text(_to_toml(data))
        daemon = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "cli", "serve", "--config", str(toml), "--no-web",
            "--start-batch", "fast-thermal", "--once", cwd=ROOT, env=_env(),
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        try:
            loop = asyncio.get_running_loop()
            end = loop.time() + 120
            while not (sim.world.lamp_on and sim.world.position == 0):  # P hot: the lamp heats, plate at P
                assert daemon.returncode is None and loop.time() < end, "the batch never reached P hot"
                await asyncio.sleep(0.05)
            # the window: the plant holds still (as the fault matrix holds it) so the running daemon
            # itself has no reason to send anything; whatever arrives came from the check
            sim.paused = True
            boards = [*sim.serial_boards, *sim.can_boards]
            cmds = [len(b.commands) for b in boards]
            writes = len(sim.modbus.writes)
            rc, out, err, took_s = await _station("serve", "--config", str(toml), "--check")
            await asyncio.sleep(0.2)  # anything in flight lands
            touched = ([b.commands[n:] for b, n in zip(boards, cmds)], sim.modbus.writes[writes:])
            lamp_on_after = sim.world.lamp_on
            sim.paused = False
            print(f"serve --check refused in {took_s:.2f} s: {err.strip()}")
            assert rc == 2, (rc, out, err)
            line = _one_line(err.encode())
            assert line.startswith("station serve: error: the database "), line
            assert f"held by station serve (PID {daemon.pid} on host {HOST}, since " in line, line
            assert "one station owns its boards, relay and database; stop it first" in line
            assert "identified" not in out
            assert took_s < 10.0, took_s
            assert touched[0] == [[] for _ in boards], touched[0]  # no STOP, no ID, nothing
            assert touched[1] == [], touched[1]  # the lamp coil never switched off by the check
            assert lamp_on_after

            # a second daemon on the same database, other (absent) ports: refused by the database
            other = dict(data, slots=[{"name": "s99", "serial": "/dev/ttyNOSUCH7"}],
                         lamp={"tcp": {"host": "127.0.0.1", "port": 1}, "unit": 1})
            other.pop("fixture", None)
            other.pop("thermometer", None)
            other.pop("chamber", None)
            other_toml = tmp_path / "other.toml"
            other_toml.write_text(_to_toml(other))
            rc2, out2, err2, took2_s = await _station("serve", "--config", str(other_toml), "--no-web")
            print(f"second serve refused in {took2_s:.2f} s: {err2.strip()}")
            line2 = _one_line(err2.encode())
            assert rc2 == 2 and line2.startswith(f"station serve: error: the database {os.path.realpath(db_path)} "
                                                 f"is held by station serve (PID {daemon.pid} on host {HOST}"), line2
            assert "s99" not in line2 and "127.0.0.1:1" not in line2

            out_d, err_d = await asyncio.wait_for(daemon.communicate(), 240)
        finally:
            if daemon.returncode is None:
                daemon.kill()
                await daemon.wait()
        assert daemon.returncode == 0, (out_d.decode(), err_d.decode())
        assert "batch 1 finished" in out_d.decode(), out_d.decode()
    from db.database import Database
    from db.repository import batch_detail

    db = Database(f"sqlite:///{db_path}")
    detail = batch_detail(db, 1)
    assert detail["state"] == "finished", detail["error"]
    assert [r["state"] for r in detail["runs"]] == ["done"] * 3, [(r["slot"], r["fault_reason"]) for r in detail["runs"]]
    assert "interrupted" not in json.dumps(detail)
    db.dispose()
