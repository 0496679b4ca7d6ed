"""What a board reports of its own health (docs/design.md 3.1/3.2, issue 42), station side.

- the `I` frame's trailing key=value fields become Identity's typed health fields; a frame with none
  is the old identity; unknown keys are ignored; a malformed field makes the frame malformed
  (counted and skipped, never half-believed);
- the health fields are not WHICH board it is: identities compare equal without them, and the
  end-of-run identity check does not see them; but a `boots` that moved between the start and the
  end of a run is a restart during the run: the run ends error naming the cause (fault PC in hex),
  and the link counts it (LinkStats.board_restarts), on the real Python simulated board over a pty;
- `C` replies carry the record info; unsolicited `E,SENSOR` / `E,NVM` are counted, kept for the
  run's notes and never taken for the reply to a command in flight (a real pty board from the contract);
- CAN identity frames 11 (reset cause, record) and 12/13 (serial characters 15..28), on a python-can
  bus through the simulated slcan adapter, with an old board's identify as fast as before.
"""

from __future__ import annotations

import asyncio
import struct
import time
from functools import reduce
from operator import xor

import pytest

from contract_v2_peer import ContractPeer
from contracts.board_health import BoardRecordInfo
from contracts.types import Identity
from drivers import can_board
from drivers.can_board import CanBoard, CanBus
from drivers.protocol import can_frames as cf
from drivers.protocol import serial_frames as sf
from drivers.serial_board import SerialBoard
from drivers.sim.serial_pty import SimSerialBoard
from drivers.sim.slcan_pty import SimCanHub, SlcanPtyAdapter
from station.daemon.dut_run import DutRun
from station.daemon.identity_check import board_restart, identity_change
from station.daemon.run_end import RunEnd

BASE = "I,F4001122334455667788990A0B,ADXL355,fw-c-2.0,3.9,-9.05,1885,3.125"
OLD = Identity("F4001122334455667788990A0B", "ADXL355", "fw-c-2.0", 3.9, -9.05, 1885.0, 3.125)


def _frame(body: str) -> bytes:
    raw = body.encode()
    return b"$%s*%02X\n" % (raw, reduce(xor, raw, 0))


def _parse(*bodies: str) -> tuple[list, sf.FrameParser]:
    p = sf.FrameParser()
    return p.feed(b"".join(_frame(b) for b in bodies)), p


# ---- the I frame -----------------------------------------------------------------------------------

def test_identity_with_every_key():
    got, p = _parse(BASE + ",reset=fault,boots=3,fault=00000400,fault_pc=08001a2C,rec_ver=2,rec_gen=7,rec_slot=1,"
                           "rec_state=fallback,caps=scal+sfem3,sensor_reinit=2")
    assert p.stats.frames_ok == 1 and p.stats.frames_malformed == 0
    i = got[0].identity
    assert (i.reset_cause, i.boots, i.fault_cfsr, i.fault_pc, i.sensor_reinits) == ("fault", 3, 0x400, 0x08001A2C, 2)
    assert i.record == BoardRecordInfo(rec_ver=2, rec_gen=7, rec_slot=1, rec_state="fallback")
    assert i.caps == frozenset({"scal", "sfem3"})
    assert (i.serial, i.sensor, i.fw, i.ug_per_lsb, i.t_lsb_per_c, i.t_lsb_at_25c, i.odr_hz) == \
        ("F4001122334455667788990A0B", "ADXL355", "fw-c-2.0", 3.9, -9.05, 1885.0, 3.125)
    # the station writes the same fields back (hex upper case, caps sorted): one reading of the table
    assert sf.IdentityFrame(i).encode() == _frame(
        BASE + ",reset=fault,boots=3,fault=00000400,fault_pc=08001A2C,rec_ver=2,rec_gen=7,rec_slot=1,"
               "rec_state=fallback,caps=scal+sfem3,sensor_reinit=2")


def test_identity_without_keys_is_the_old_one():
    got, p = _parse(BASE)
    i = got[0].identity
    assert i == OLD and p.stats.frames_malformed == 0
    assert (i.reset_cause, i.boots, i.fault_cfsr, i.fault_pc, i.record, i.sensor_reinits) == (None,) * 6
    assert i.caps == frozenset()
    assert sf.IdentityFrame(OLD).encode() == _frame(BASE)  # no key written for a health not reported
    # no record slot: "-"; an empty caps list is no capability
    got, _ = _parse(BASE + ",rec_ver=0,rec_gen=0,rec_slot=-,rec_state=empty,caps=")
    assert got[0].identity.record == BoardRecordInfo(0, 0, None, "empty") and got[0].identity.caps == frozenset()


def test_unknown_keys_are_ignored_and_malformed_fields_skip_the_frame():
    got, p = _parse(BASE + ",color=blue,reset=cosmic_ray,x9=1=2,boots=4")
    assert p.stats.frames_malformed == 0
    assert got[0].identity.reset_cause == "cosmic_ray" and got[0].identity.boots == 4  # a newer board's word, kept
    bad = ["boots", "boots=abc", "boots=-1", "boots=4294967296", "boots= 1", "fault=400", "fault_pc=0800XYZ1",
           "rec_slot=x", "=5", "caps=scal++sfem3", "caps=SCAL", "boots=1,boots=2", "reset=", "reset=Power",
           "rec_gen=1.5", "sensor_reinit=+1"]
    got, p = _parse(*(BASE + "," + b for b in bad), BASE + ",boots=9")
    assert p.stats.frames_malformed == len(bad) and p.stats.frames_ok == 1
    assert [f.identity.boots for f in got] == [9]
    got, p = _parse("I,SN1,LIS3DSH,fw,60,1,0")  # seven fields: short, as ever
    assert got == [] and p.stats.frames_malformed == 1


def test_cal_readback_carries_the_record():
    base = "C,0.5,-1.25,0,-120,0,-480.5,0A1B2C3D,1"
    got, p = _parse(base + ",rec_ver=2,rec_gen=12,rec_slot=0,rec_state=ok", base, base + ",rec_slot=z",
                    base + ",future=1")
    assert p.stats.frames_malformed == 1
    assert got[0].record == BoardRecordInfo(2, 12, 0, "ok") and got[0].comp and got[0].crc == 0x0A1B2C3D
    assert got[1].record is None and got[2].record is None and got[1] == got[2]
    assert sf.FrameParser().feed(got[0].encode()) == [got[0]]


# ---- the same board, restarted ---------------------------------------------------------------------

def test_identity_equality_ignores_the_health_fields():
    import dataclasses
    h = dataclasses.replace(OLD, reset_cause="watchdog", boots=2, fault_cfsr=1, fault_pc=2,
                            record=BoardRecordInfo(2, 3, 1, "ok"), caps={"scal"}, sensor_reinits=5)
    assert h == OLD and hash(h) == hash(OLD) and isinstance(h.caps, frozenset)
    assert identity_change(OLD, h) is None
    assert identity_change(OLD, dataclasses.replace(h, fw="fw-c-2.1")) == "fw 'fw-c-2.0' -> 'fw-c-2.1'"


def test_board_restart_names_the_cause():
    import dataclasses
    start = dataclasses.replace(OLD, reset_cause="power", boots=1)
    assert board_restart(start, start) is None
    assert board_restart(OLD, dataclasses.replace(OLD, boots=2)) is None  # not reported at the start: cannot tell
    assert board_restart(start, dataclasses.replace(OLD, reset_cause="watchdog", boots=2)) == \
        "the board restarted during the run: watchdog reset (boots 1 -> 2)"
    assert board_restart(start, dataclasses.replace(OLD, reset_cause="fault", boots=3, fault_cfsr=0x400,
                                                    fault_pc=0x08001A2C)) == \
        "the board restarted during the run: fault reset at pc 0x08001A2C (CFSR 0x00000400) (boots 1 -> 3)"
    assert board_restart(dataclasses.replace(start, boots=4), dataclasses.replace(OLD, reset_cause="power", boots=1)) == \
        "the board restarted during the run: power reset (boots 4 -> 1)"


class _Slots:
    """RunEnd's view of the slot bank (run_end.EndSlots) over real drivers: board_changed reads the
    identity again and compares it as station/daemon/slots.py does (identity_check.identity_change)."""

    def __init__(self, drivers: dict) -> None:
        self.drivers = drivers
        self.bus = None

    def driver_of(self, slot: str):
        return self.drivers.get(slot)

    async def stop_streams(self, seq) -> None:
        pass

    async def stop_board(self, d: DutRun) -> bool:
        drv = self.drivers[d.slot]
        await drv.stop()
        d.link_stats = drv.stats.as_dict()
        return True

    async def board_changed(self, d: DutRun, when: str) -> str | None:
        change = identity_change(d.identity, await self.drivers[d.slot].identify())
        return None if change is None else f"{d.slot}'s board changed {when}: {change}"

    async def slot_free(self, d: DutRun, answered: bool, shutting_down: bool) -> None:
        pass

    def publish_dut(self, seq, d: DutRun) -> None:
        pass


async def test_restart_on_the_python_sim_board_ends_the_run_with_its_cause():
    """The Python simulated board on a real pty reports reset=power,boots=1; a watchdog reset
    (reset_streaming) moves boots to 2: the driver counts the restart, and the run end names it."""
    sim = SimSerialBoard(Identity("SIM0042", "LIS3DSH", "sim-1", 60.0, 1.0, 0.0, 3.125))
    sim.start()
    drv = SerialBoard(sim.path)
    await drv.open()
    try:
        start = await drv.identify()
        assert (start.reset_cause, start.boots) == ("power", 1) and start == sim.identity
        d = DutRun("s01", identity=start, state="running")
        d.link_stats = drv.stats.as_dict()
        end = RunEnd(_Slots({"s01": drv}), storage=None, verdicts=None)  # type: ignore[arg-type]
        assert await drv.identify() == start and end._restarted(d) is None  # same boots: same life
        sim.reset_streaming()
        now = await drv.identify()
        assert (now.reset_cause, now.boots) == ("watchdog", 2) and now == start  # the same board
        assert drv.stats.board_restarts == 1
        assert end._restarted(d) == "s01: the board restarted during the run: watchdog reset (boots 1 -> 2)"
        assert d.link_stats["board_restarts"] == 1
        await drv.identify()
        assert drv.stats.board_restarts == 1  # counted once, not at every identify after it
    finally:
        await drv.close()
        sim.close()


# ---- unsolicited E frames ---------------------------------------------------------------------------

async def test_unsolicited_errors_are_counted_and_never_answer_a_command():
    peer = ContractPeer()
    drv = SerialBoard(peer.path, ack_timeout_s=0.5, retries=1)
    await drv.open()
    try:
        peer.before_next_reply = _frame("E,NVM,calibration record CRC mismatch in slot 1")
        ident = await drv.identify()
        assert ident.serial == "CP0001"
        peer.before_next_reply = _frame("E,SENSOR,no data-ready for 960 ms")
        await drv.start()  # E,SENSOR came first: the START's own A,START answers it
        assert drv.stats.errors_reported == 2 and drv.stats.sensor_reinits_reported == 1
        assert drv.last_board_error == "SENSOR: no data-ready for 960 ms"
        peer.before_next_reply = _frame("E,STOP,refused")
        with pytest.raises(Exception, match="STOP"):  # a command's own error still fails it
            await drv.stop()
        assert drv.last_board_error == "SENSOR: no data-ready for 960 ms"
    finally:
        await drv.close()
        peer.close()


# ---- CAN frames 11, 12, 13 --------------------------------------------------------------------------

def test_can_identity_frames_11_12_13_decode():
    serial = "F4" + "00112233445566778899AABB"  # 26 characters: the STM32 UID serial
    frames = cf.encode_identity_v2(serial, 3.9, 3.125, reset_cause="watchdog",
                                   record=BoardRecordInfo(2, 0x01020304, None, "fallback"))
    # byte layout written out from the contract
    assert frames[0] == b"\x00F400112" and frames[1] == b"\x012334455"
    assert frames[4] == bytes([11, 3, 1, 2]) + struct.pack("<I", 0x01020304)
    assert frames[5] == b"\x0c6677889" and frames[6] == b"\x0d9AABB\x00\x00"
    for order in (frames, frames[::-1], [frames[k] for k in (4, 0, 6, 2, 1, 5, 3)]):
        a = cf.IdentityAssembler()
        for fr in order:
            a.feed(fr)
        assert a.complete and not a.waits_for_more
        ident = a.identity(None)
        assert ident.serial == serial and ident.reset_cause == "watchdog"
        assert ident.record == BoardRecordInfo(2, 0x01020304, None, "fallback")
    # the base frames of a full 14-character serial may go on: the assembler says so
    a = cf.IdentityAssembler()
    for fr in frames[:4]:
        a.feed(fr)
    assert a.complete and a.waits_for_more and a.serial == serial[:14]
    a.feed(frames[5])
    assert a.waits_for_more and a.extension_incomplete
    # a short serial: nothing more to wait for; unknown codes are "unknown"
    a = cf.IdentityAssembler()
    for fr in cf.encode_identity("SHORT1", 60.0, 3.125) + [bytes([11, 99, 42, 1, 0, 0, 0, 0])]:
        a.feed(fr)
    assert not a.waits_for_more and a.identity(None).reset_cause == "unknown"
    assert a.identity(None).record.rec_state == "unknown"
    with pytest.raises(ValueError):
        cf.IdentityAssembler().feed(bytes([11, 1, 0]))  # frame 11 is 8 bytes
    with pytest.raises(ValueError):
        cf.encode_identity_v2("X" * 29, 60.0, 1.0)


class _CanPeer:
    """A CAN node answering IDENTIFY with frames packed here from the contract (struct, not cf)."""

    def __init__(self, node_id: int, serial: str, *, v2: bool) -> None:
        self.node_id, self.serial, self.v2 = node_id, serial.encode(), v2
        self.send = None

    def on_frame(self, arb_id: int, data: bytes) -> None:
        if arb_id != 0x600 + self.node_id or bytes(data[:1]) != b"\x03":
            return
        s = self.serial.ljust(28, b"\0")
        out = [b"\x00" + s[:7], b"\x01" + s[7:14], b"\x02" + struct.pack("<f", 60.0), b"\x03" + struct.pack("<f", 3.125)]
        if self.v2:
            out.append(bytes([11, 1, 0, 1]) + struct.pack("<I", 5))
            if len(self.serial) > 14:
                out += [b"\x0c" + s[14:21], b"\x0d" + s[21:28]]
        for payload in out:
            self.send(0x580 + self.node_id, payload)


async def test_can_identify_long_serials_and_old_boards(monkeypatch):
    """On python-can's slcan interface to the simulated adapter (a real pty): a v2 board's 26-character
    serial and frame 11 arrive; an old board with a short serial answers without any wait; an old
    board with exactly 14 characters costs one grace period (frames 12/13 could have followed)."""
    grace_s = 1.0
    monkeypatch.setattr(can_board, "IDENT_EXT_GRACE_S", grace_s)  # long, so that a wait shows
    hub = SimCanHub()
    long_serial = "F4" + "0123456789ABCDEF01234567"
    peers = {1: _CanPeer(1, long_serial, v2=True), 2: _CanPeer(2, "OLD-1", v2=False), 3: _CanPeer(3, "OLD-14-CHARS-X", v2=False),
             4: _CanPeer(4, "NEW-2", v2=True)}
    for p in peers.values():
        hub.add(p)  # type: ignore[arg-type]
    adapter = SlcanPtyAdapter(hub)
    adapter.start()
    bus = CanBus("slcan", adapter.path, 500_000, sleep_after_open=0)
    boards = {n: CanBoard(bus, n) for n in peers}
    try:
        for b in boards.values():
            await b.open()
        took = {}
        for n, b in boards.items():
            t0 = time.monotonic()
            ident = await b.identify(timeout_s=9.0)  # 3 s per try: the grace is not cut short
            took[n] = time.monotonic() - t0
            assert ident.serial == peers[n].serial.decode()
            if not peers[n].v2:
                assert ident.reset_cause is None and ident.record is None
        assert took[1] < grace_s and took[2] < grace_s and took[4] < grace_s, took
        assert took[3] >= grace_s, took
        # the long serial's reply waited for 12/13 and so holds frame 11 (sent before them)
        assert boards[1].identity.reset_cause == "power"
        # a short serial's first reply is taken at frame 3 (an old board must not wait): its frame 11,
        # right behind, reaches the driver's identity; from then on this node's replies wait for it
        await asyncio.sleep(0.3)
        assert boards[4].identity.reset_cause == "power"
        assert boards[4].identity.record == BoardRecordInfo(1, 5, None, "ok")
        t0 = time.monotonic()
        again = await boards[4].identify(timeout_s=9.0)
        assert time.monotonic() - t0 < grace_s and again.reset_cause == "power" and again.record.rec_gen == 5
        assert boards[2].identity.reset_cause is None
        assert all(b.stats.frames_malformed == 0 for b in boards.values())
    finally:
        for b in boards.values():
            await b.close()
        await bus.close()
        adapter.close()


class _Storage:
    async def stored_before_end(self, timeout_s: float = 15.0) -> str | None:
        return None


async def test_release_ends_a_restarted_run_error_and_a_steady_one_done():
    """RunEnd.release_duts at a finished batch's end, two Python sim boards on real ptys: the one
    whose watchdog reset it during the run ends faulted with the cause, the other is done."""
    from types import SimpleNamespace

    sims = [SimSerialBoard(Identity(f"SIM00{k}", "LIS3DSH", "sim-1", 60.0, 1.0, 0.0, 3.125)) for k in (1, 2)]
    drvs = {}
    try:
        for k, sim in enumerate(sims):
            sim.start()
            drvs[f"s0{k + 1}"] = drv = SerialBoard(sim.path)
            await drv.open()
        duts = [DutRun(slot, identity=await drv.identify(), state="running") for slot, drv in drvs.items()]
        await drvs["s01"].start()
        sims[0].reset_streaming()  # a watchdog reset (not streaming any sample: no stream break to see it)
        seq = SimpleNamespace(duts=duts, ending=None, state="finished", error=None, batch_id=1,
                              profile=SimpleNamespace(analysis="none"))
        await RunEnd(_Slots(drvs), _Storage(), verdicts=None).release_duts(seq)  # type: ignore[arg-type]
        assert (duts[0].state, duts[0].fault_reason) == \
            ("faulted", "s01: the board restarted during the run: watchdog reset (boots 1 -> 2)")
        assert duts[0].link_stats["board_restarts"] == 1
        assert (duts[1].state, duts[1].fault_reason) == ("done", "")
    finally:
        for drv in drvs.values():
            await drv.close()
        for sim in sims:
            sim.close()
