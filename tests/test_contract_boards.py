"""Boards written from the contract alone, two of them sharing a serial (issue 36).

What this proves, on the real daemon (`Station`, in process) over real links (each board on its
own pseudo-terminal, opened by the station with pyserial like a USB CDC port; the lamp relay and
the fixture on a pymodbus TCP server on 127.0.0.1, drivers/sim/modbus_server.py; SQLite on disk):

- C: a board that speaks design 3.1 as written is identified, and its `D` stream is taken as the
  plate at P (the first step of `fast-thermal` completes and the lamp comes on), so the boards
  below are good enough boards and the lamp check of A and B is not vacuous;
- A: two boards answering the same serial (a cloned firmware image) are both stopped before the
  lamp heats, each faulted with a reason naming both slots and the serial; nothing is stored or
  sent to the MES as `pass` for that serial; the board with a serial of its own goes on, not
  faulted for the duplicates' sake;
- B: two boards answering an empty serial and one answering a 300-character serial are all
  stopped before the lamp heats, with the reason in words (it says "serial"); nothing goes to the
  MES as `pass`.

Why the boards are written here, from docs/design.md 3.1 and nothing else (frame `$BODY*HH\\n`
with the XOR checksum as two upper-case hex digits, `ID`/`START`/`STOP`/`ODR`, the `I`/`A`/`D`/`E`
frames): the station's codec (drivers/protocol) and the simulator's boards (drivers/sim) were
written by the same hands from the same reading of the contract, so a misreading shared by both
would pass every test that pairs them. These boards are an independent oracle: if the station
and they disagree, one of them does not follow the datasheet.

The lamp check does not poll: the Modbus server's plant records every coil write the moment the
server applies it (same event loop as the daemon), with the states of the DUT runs at that
moment; a 50 ms poll of the batch status and the coil runs beside it for the record.
"""

from __future__ import annotations

import asyncio
import os
import random
import time
import tty
from contextlib import asynccontextmanager
from typing import Any

import pytest

from db.repository import results_since, runs_of_dut
from drivers.sim.modbus_server import SimModbusServer
from station.config import parse_config
from station.daemon.storage import open_database
from station.daemon.supervisor import Station

SPEED = 20.0  # board clock (sample time) per wall second; the station's timing.speed says the same
ODR_HZ = 50.0
TICK_S = 0.02  # wall seconds between the boards' transmit turns
P_G = 0.577  # the fast-thermal P orientation: +0.577 g on every axis (design, martinez2022)
LIS3DSH = ("LIS3DSH", 60.0, 1.0, 0.0)  # sensor, ug_per_lsb, t_lsb_per_c, t_lsb_at_25c (design 3.1)
BATCH_ENDED = ("finished", "failed", "aborted", "interrupted")  # station/daemon/states.py BATCH_STATE


# ================================================================== the board, from design 3.1
def checksum(body: bytes) -> int:
    """XOR of every byte of BODY."""
    x = 0
    for b in body:
        x ^= b
    return x


def frame(body: str) -> bytes:
    """`$BODY*HH\\n`, HH two upper-case hex digits."""
    raw = body.encode("ascii")
    return b"$" + raw + b"*" + f"{checksum(raw):02X}".encode("ascii") + b"\n"


def parse_frame(line: bytes) -> list[str] | None:
    """A station command line -> its comma separated fields, or None (bad checksum, garbage)."""
    line = line.strip()
    start = line.rfind(b"$")  # garbage before the frame is skipped
    if start < 0:
        return None
    line = line[start + 1:]
    body, star, hh = line.rpartition(b"*")
    if not star or len(hh) != 2:
        return None
    try:
        if int(hh, 16) != checksum(body):
            return None
    except ValueError:
        return None
    return body.decode("ascii", "replace").split(",")


class ContractBoard:
    """A serial accelerometer board as design 3.1 describes it, on a pseudo-terminal.

    The station opens `path` (the slave) with pyserial; the board talks through the master. The
    board keeps its own slave fd open too, so the master never reads EIO while the station has the
    port closed (between connects, after the station's close). Replies: `ID` -> `I,...`;
    `START`/`STOP`/`ODR,<hz>` -> `A,<command>`; anything else -> `E,<command>,<text>`; a line with
    a bad checksum -> `E,CHK,...` (counted). While started, `D,<seq>,<t_us>,<ax>,<ay>,<az>,<t>`
    at the ODR of its own clock (running SPEED x wall time, microseconds since power-up), the
    plate at P: +0.577 g on each axis in counts of its ug_per_lsb, with a little noise, the
    temperature count of 25 C."""

    def __init__(self, serial: str, *, seed: int, sensor=LIS3DSH, fw: str = "contract-1.0",
                 odr_hz: float = ODR_HZ, speed: float = SPEED) -> None:
        self.serial = serial
        self.sensor, self.ug_per_lsb, self.t_lsb_per_c, self.t_lsb_at_25c = sensor
        self.fw = fw
        self.odr_hz = float(odr_hz)
        self.speed = float(speed)
        self.rng = random.Random(seed)
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no line discipline: bytes as they are
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)
        self.streaming = False
        self.seq = 0
        self.next_sample_us = 0  # board clock of the next sample due
        self.commands: list[str] = []  # every command received, in order (for the report)
        self.bad_lines = 0
        self.sent_samples = 0
        self.dropped_bytes = 0
        self._rx = b""
        self._out = bytearray()
        self._t0 = 0.0
        self._task: asyncio.Task | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    # ---- clock and samples -------------------------------------------------------------------
    def clock_us(self) -> int:
        """Microseconds since power-up on the board's own clock."""
        assert self._loop is not None
        return int((self._loop.time() - self._t0) * self.speed * 1e6)

    def counts(self) -> tuple[int, int, int, int]:
        nominal = round(P_G * 1e6 / self.ug_per_lsb)
        ax, ay, az = (nominal + round(self.rng.gauss(0.0, 3.0)) for _ in range(3))
        t = round(self.t_lsb_at_25c)  # 25 C: t = t_lsb_at_25c + (25 - 25) * t_lsb_per_c
        return ax, ay, az, t

    # ---- link --------------------------------------------------------------------------------
    def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._t0 = self._loop.time()
        self._loop.add_reader(self.master, self._readable)
        self._task = self._loop.create_task(self._run(), name=f"contract-board-{self.path}")

    def close(self) -> None:
        if self._loop is not None:
            self._loop.remove_reader(self.master)
        if self._task is not None:
            self._task.cancel()
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def _send(self, data: bytes) -> None:
        self._out += data
        self._flush()

    def _flush(self) -> None:
        while self._out:
            try:
                n = os.write(self.master, self._out)
            except BlockingIOError:
                # nobody reads (the port is closed): a UART has no back-pressure either, but a CDC
                # device's buffer is finite; keep at most 64 KiB, as a board's ring buffer would
                if len(self._out) > 65536:
                    self.dropped_bytes += len(self._out) - 65536
                    del self._out[:len(self._out) - 65536]
                return
            except OSError:
                return
            del self._out[:n]

    def _readable(self) -> None:
        try:
            data = os.read(self.master, 4096)
        except (BlockingIOError, OSError):
            return
        self._rx += data
        while b"\n" in self._rx:
            line, self._rx = self._rx.split(b"\n", 1)
            if not line.strip():
                continue
            fields = parse_frame(line)
            if fields is None:
                self.bad_lines += 1
                self._send(frame("E,CHK,bad frame or checksum"))
                continue
            self._command(fields)

    def _command(self, fields: list[str]) -> None:
        cmd = fields[0].strip().upper()
        self.commands.append(",".join(fields))
        if cmd == "ID":
            self._send(frame(f"I,{self.serial},{self.sensor},{self.fw},{self.ug_per_lsb:g},"
                             f"{self.t_lsb_per_c:g},{self.t_lsb_at_25c:g},{self.odr_hz:g}"))
        elif cmd == "START":
            if not self.streaming:
                self.streaming = True
                self.next_sample_us = self.clock_us()
            self._send(frame("A,START"))
        elif cmd == "STOP":
            self.streaming = False
            self._send(frame("A,STOP"))
        elif cmd == "ODR":
            try:
                hz = float(fields[1])
                if not hz > 0:
                    raise ValueError
            except (IndexError, ValueError):
                self._send(frame("E,ODR,bad rate"))
                return
            self.odr_hz = hz
            self._send(frame("A,ODR"))
        else:
            self._send(frame(f"E,{cmd or 'EMPTY'},unknown command"))

    async def _run(self) -> None:
        while True:
            await asyncio.sleep(TICK_S)
            if not self.streaming:
                self._flush()
                continue
            now_us = self.clock_us()
            period_us = 1e6 / self.odr_hz
            out = []
            while self.next_sample_us <= now_us:
                ax, ay, az, t = self.counts()
                out.append(frame(f"D,{self.seq},{int(self.next_sample_us) & 0xFFFFFFFF},{ax},{ay},{az},{t}"))
                self.seq = (self.seq + 1) & 0xFFFFFFFF
                self.next_sample_us += period_us
                self.sent_samples += 1
            if out:
                self._send(b"".join(out))
            else:
                self._flush()


# ================================================================== the plant behind the Modbus server
class Plant:
    """What SimModbusServer needs of a plant. Every write of the lamp coil (by the relay unit's
    handler, the moment the server applies it) is recorded with `observe()`'s view of the DUT runs
    at that moment."""

    def __init__(self) -> None:
        self._lamp = False
        self.position = 0  # the fixture starts at P (index 0, design 4)
        self.chamber_setpoint_c = None
        self._t0 = time.monotonic()
        self.lamp_writes: list[tuple[float, bool, Any]] = []  # (wall, value, runs then)
        self.observe = lambda: None

    @property
    def lamp_on(self) -> bool:
        return self._lamp

    @lamp_on.setter
    def lamp_on(self, value: bool) -> None:
        self._lamp = bool(value)
        try:
            seen = self.observe()
        except Exception as exc:  # noqa: BLE001 - recorded, the test reports it
            seen = f"observe failed: {exc!r}"
        self.lamp_writes.append((time.monotonic(), bool(value), seen))

    @property
    def time_s(self) -> float:
        return (time.monotonic() - self._t0) * SPEED

    @property
    def plate_temp_c(self) -> float:
        return 25.0


# ================================================================== the station around the boards
@asynccontextmanager
async def station_with(tmp_path, boards: list[ContractBoard]):
    plant = Plant()
    server = SimModbusServer(plant, "127.0.0.1", move_time_s=0.5)
    await server.start()
    for b in boards:
        b.start()
    modbus = {"host": "127.0.0.1", "port": server.port}
    cfg = parse_config({
        "name": "contract-test",
        "database_url": f"sqlite:///{tmp_path / 'station.db'}",
        "slots": [{"name": f"s{i + 1:02d}", "serial": b.path} for i, b in enumerate(boards)],
        "lamp": {"tcp": modbus, "unit": 1},
        "fixture": {"tcp": modbus, "unit": 3},  # the plate is turned by the fixture: no person needed
        "timing": {"speed": SPEED},
        "limits": {"lamp_max_on_s": 7200},
    }, "test")
    db = open_database(cfg.database_url)
    st = Station(cfg, db=db)
    try:
        await st.start()
        yield st, db, plant, server
    finally:
        await st.close()
        db.dispose()
        for b in boards:
            b.close()
        await server.stop()


def runs_view(st: Station, bid: int) -> dict[str, tuple[str, str, str | None]]:
    """slot -> (run state, fault reason, serial) as GET /api/batches/{id} shows them."""
    return {s["slot"]: (s["state"], s["fault_reason"] or "", s["serial"]) for s in st.batch_status(bid)["slots"]}


async def watch_batch(st: Station, bid: int, plant: Plant, stopped: list[str], *, observe_s: float,
                      deadline_s: float) -> list[tuple]:
    """Poll the batch and the coil every 50 ms until: a lamp-on came while a slot of `stopped` was
    not faulted (the test fails on it), or the batch ended, or every slot of `stopped` is faulted
    and then the lamp has been on for 2 s or `observe_s` went by; at most `deadline_s`."""
    loop = asyncio.get_running_loop()
    t_end = loop.time() + deadline_s
    all_stopped_at = lamp_on_at = None
    timeline = []
    while loop.time() < t_end:
        status = st.batch_status(bid)
        runs = {s["slot"]: s["state"] for s in status["slots"]}
        timeline.append((round(loop.time(), 2), status["state"], status["step_index"], plant.lamp_on, runs))
        if any(v and not all(seen_runs.get(s, ("?",))[0] == "faulted" for s in stopped)
               for _, v, seen_runs in plant.lamp_writes if isinstance(seen_runs, dict)):
            break
        if plant.lamp_on and any(runs.get(s) != "faulted" for s in stopped):
            break
        if status["state"] in BATCH_ENDED or status.get("ended") is not None:
            break
        if all(runs.get(s) == "faulted" for s in stopped):
            all_stopped_at = all_stopped_at or loop.time()
            if plant.lamp_on:
                lamp_on_at = lamp_on_at or loop.time()
                if loop.time() - lamp_on_at >= 2.0:
                    break
            elif loop.time() - all_stopped_at >= observe_s:
                break
        await asyncio.sleep(0.05)
    return timeline


def assert_no_lamp_on_while_live(plant: Plant, stopped: list[str], timeline: list[tuple]) -> None:
    for t, value, seen in plant.lamp_writes:
        if not value:
            continue
        assert isinstance(seen, dict), f"lamp switched on; the runs could not be read then: {seen}"
        live = {s: seen.get(s) for s in stopped if seen.get(s, ("?",))[0] != "faulted"}
        assert not live, (f"the lamp was switched ON while {sorted(live)} were not stopped: {live}; "
                          f"last polls: {timeline[-5:]}")
    for t, state, step, lamp, runs in timeline:
        assert not (lamp and any(runs.get(s) != "faulted" for s in stopped)), (
            f"coil ON at {t} with runs {runs} (batch {state}, step {step})")


async def end_batch(st: Station, bid: int) -> dict:
    if st.batch_status(bid)["state"] not in BATCH_ENDED:
        try:
            st.abort(bid, "test done", by="pytest")
        except ValueError:
            pass  # it ended by itself meanwhile
    status = await st.wait_batch(bid, timeout_s=30)
    await st.flush_db()
    return status


def mes_records(db) -> list[dict]:
    out, cursor = [], 0
    while True:
        page = results_since(db, cursor, limit=1000)
        if not page:
            return out
        out += page
        cursor = page[-1]["id"]


def short(serial: str | None) -> str:
    return serial if serial is None or len(serial) <= 24 else f"{serial[:12]}...({len(serial)} chars)"


# ================================================================== C: the boards speak 3.1
@pytest.mark.timeout(60)
async def test_contract_board_is_identified_and_streams_p(tmp_path):
    boards = [ContractBoard("CT-0001", seed=1)]
    async with station_with(tmp_path, boards) as (st, db, plant, server):
        slots = {s["slot"]: s for s in st.slots_status()}
        assert slots["s01"]["state"] == "identified", slots
        assert slots["s01"]["serial"] == "CT-0001", slots
        assert slots["s01"]["sensor"] == "LIS3DSH", slots
        assert any(c == "ID" for c in boards[0].commands), boards[0].commands

        # Its D frames are the plate at P, stable at 25 C: the first fast-thermal step (a segment at
        # P, lamp off) completes and the lamp comes on for P hot.
        bid = st.start_batch("fast-thermal", None, "pytest")
        plant.observe = lambda: runs_view(st, bid)
        timeline = await watch_batch(st, bid, plant, [], observe_s=25.0, deadline_s=25.0)
        status = await end_batch(st, bid)
        s01 = status["slots"][0]
        print("board commands:", boards[0].commands[:12], "sent", boards[0].sent_samples, "bad", boards[0].bad_lines)
        print("s01:", {k: s01[k] for k in ("state", "fault_reason", "samples", "segments", "link_stats")})
        print("lamp writes:", [(round(t, 2), v) for t, v, _ in plant.lamp_writes])
        assert boards[0].bad_lines == 0, "the station sent a frame whose checksum the contract board refuses"
        assert s01["samples"] > 500, s01
        assert s01["segments"] >= 1, (s01, timeline[-3:])
        assert any(v for _, v, _ in plant.lamp_writes), f"the lamp never came on for P hot: {timeline[-3:]}"
        assert not s01["fault_reason"] or "aborted" in s01["fault_reason"], s01


# ================================================================== A: a cloned image in two slots
@pytest.mark.timeout(90)
async def test_two_boards_with_one_serial_are_stopped_before_the_lamp(tmp_path):
    boards = [ContractBoard("SIM0001", seed=1), ContractBoard("SIM0001", seed=2), ContractBoard("CT-0003", seed=3)]
    async with station_with(tmp_path, boards) as (st, db, plant, server):
        print("slots at start:", [(s["slot"], s["state"], s["serial"], s["fault_reason"]) for s in st.slots_status()])
        # before Start, GET /api/slots already says why a batch would stop the two (the page shows it)
        why = {s["slot"]: s.get("identity_problem") for s in st.slots_status()}
        assert why["s03"] is None and all("s01 and s02" in (why[k] or "") and "SIM0001" in (why[k] or "")
                                          for k in ("s01", "s02")), why
        bid = st.start_batch("fast-thermal", None, "pytest")
        plant.observe = lambda: runs_view(st, bid)
        timeline = await watch_batch(st, bid, plant, ["s01", "s02"], observe_s=8.0, deadline_s=40.0)
        status = await end_batch(st, bid)
        runs = {s["slot"]: s for s in status["slots"]}
        for slot in ("s01", "s02", "s03"):
            print(slot, runs[slot]["state"], repr(runs[slot]["fault_reason"]), runs[slot]["serial"],
                  "samples", runs[slot]["samples"])
        print("lamp writes:", [(round(t, 2), v, seen) for t, v, seen in plant.lamp_writes])
        print("coil writes at the server:", [w for w in server.writes if w[0] == 1 and w[1] in (5, 15)])
        records = mes_records(db)
        print("MES records:", [(r["slot"], r["serial"], r["verdict"], r["reason"]) for r in records])

        assert_no_lamp_on_while_live(plant, ["s01", "s02"], timeline)
        for slot in ("s01", "s02"):
            r = runs[slot]
            assert r["state"] == "faulted", r
            reason = (r["fault_reason"] or "").lower()
            assert "s01" in reason and "s02" in reason and "sim0001" in reason, r["fault_reason"]
        s03 = runs["s03"]
        assert "sim0001" not in (s03["fault_reason"] or "").lower(), s03["fault_reason"]
        assert s03["serial"] == "CT-0003", s03
        assert not [r for r in records if r["serial"] == "SIM0001" and r["verdict"] == "pass"], records
        assert not [r for r in (runs_of_dut(db, "SIM0001") or []) if r.get("verdict") == "pass"]
        assert not plant.lamp_on, "the coil is still ON after the batch ended"


# ================================================================== B: serials that name nobody
@pytest.mark.timeout(90)
async def test_empty_and_overlong_serials_are_stopped_before_the_lamp(tmp_path):
    long_serial = "".join("ABCDEFGHJKLMNPQRSTUVWXYZ0123456789"[i % 34] for i in range(300))
    boards = [ContractBoard("", seed=1), ContractBoard("", seed=2), ContractBoard(long_serial, seed=3)]
    async with station_with(tmp_path, boards) as (st, db, plant, server):
        print("slots at start:", [(s["slot"], s["state"], short(s["serial"]), s["fault_reason"]) for s in st.slots_status()])
        bid = st.start_batch("fast-thermal", None, "pytest")
        plant.observe = lambda: runs_view(st, bid)
        stopped = ["s01", "s02", "s03"]
        timeline = await watch_batch(st, bid, plant, stopped, observe_s=5.0, deadline_s=40.0)
        status = await end_batch(st, bid)
        runs = {s["slot"]: s for s in status["slots"]}
        for slot in stopped:
            print(slot, runs[slot]["state"], repr(runs[slot]["fault_reason"]), short(runs[slot]["serial"]))
        print("batch:", status["state"], status["error"])
        print("lamp writes:", [(round(t, 2), v) for t, v, _ in plant.lamp_writes])
        records = mes_records(db)
        print("MES records:", [(r["slot"], short(r["serial"]), r["verdict"], r["reason"]) for r in records])

        assert_no_lamp_on_while_live(plant, stopped, timeline)
        for slot in stopped:
            r = runs[slot]
            assert r["state"] == "faulted", r
            assert "serial" in (r["fault_reason"] or "").lower(), r["fault_reason"]
        assert not [r for r in records if r["verdict"] == "pass"], records
