"""Calibration write-back through the real drivers: serial boards on pseudo-terminals, CAN boards
behind python-can's slcan interface on a simulated adapter pty. Truth is the simulated board's
NVM and the bytes it received; faults are injected on the write path."""

import asyncio
import struct
import zlib

import numpy as np
import pytest

from drivers.base import CalibrationError
from drivers.can_board import CanBoard, CanBus
from drivers.protocol import can_frames as cf
from drivers.serial_board import SerialBoard
from drivers.sim.serial_pty import SimSerialBoard
from drivers.sim.slcan_pty import SimCanBoard, SimCanHub, SlcanPtyAdapter
from station.science.thermal_model import compensate
from contracts.types import Identity, SampleBlock

LIS = Identity("SN0001", "LIS3DSH", "1.2", 60.0, 1.0, 0.0, 3.125)
ADXL = Identity("AX0001", "ADXL355", "1.0", 3.9, -9.05, 1885.0, 3.125)
TDB = (0.8123, -1.1, 0.35)
TDSF = (-250.5, 0.0, -77.25)


def f32(vals):
    return tuple(struct.unpack(f"<{len(vals)}f", struct.pack(f"<{len(vals)}f", *vals)))


WANT = f32(TDB + TDSF)
WANT_CRC = zlib.crc32(struct.pack("<6f", *WANT))


async def _collect(drv, n, timeout_s=10.0):
    blocks, got = [], 0
    end = asyncio.get_running_loop().time() + timeout_s
    while got < n and asyncio.get_running_loop().time() < end:
        b = await drv.read_block(0.3)
        blocks.append(b)
        got += len(b)
    return SampleBlock.concat(blocks)


@pytest.fixture
async def serial_rig():
    sim = SimSerialBoard(ADXL)
    sim.start()
    drv = SerialBoard(sim.path, ack_timeout_s=0.3)
    await drv.open()
    yield sim, drv
    await drv.close()
    sim.close()


@pytest.fixture
async def can_rig():
    hub = SimCanHub()
    sims = {n: hub.add(SimCanBoard(n, Identity(f"CAN-{n}", "LIS3DSH", "", 60.0, 1.0, 0.0, 3.125))) for n in (3, 9)}
    adapter = SlcanPtyAdapter(hub)
    adapter.start()
    bus = CanBus("slcan", adapter.path, 500_000, sleep_after_open=0)
    boards = {n: CanBoard(bus, n, cal_timeout_s=0.3) for n in sims}
    for b in boards.values():
        await b.open()
    yield sims, boards
    for b in boards.values():
        await b.close()
    await bus.close()
    adapter.close()


# ---- serial ---------------------------------------------------------------------------------

async def test_serial_program_readback_comp_and_nvm_survives_power_cycle(serial_rig):
    sim, drv = serial_rig
    assert sim.cal.nvm.thermal == (0.0,) * 6 and not sim.cal.nvm.comp  # virgin board
    rep = await drv.program_thermal(TDB, TDSF)
    assert rep.attempts == 1 and rep.retries == [] and rep.comp
    assert rep.crc == WANT_CRC and rep.readback.crc == WANT_CRC and rep.readback.values == WANT
    assert sim.cal.nvm.thermal == WANT and sim.cal.nvm.comp and sim.cal.nvm.thermal_crc == WANT_CRC
    # the wire: CALW with the float32 decimals, CALR, COMP,1, CALR
    kinds = [c[1:5] for c in sim.commands]
    assert kinds == [b"CALW", b"CALR", b"COMP", b"CALR"]
    sim.power_cycle()
    rb = await drv.read_thermal()
    assert rb.values == WANT and rb.crc == WANT_CRC and rb.comp and sim.power_cycles == 1


async def test_serial_bit_flip_caught_by_crc_and_retried(serial_rig):
    sim, drv = serial_rig
    sim.cal.flip_next_write(1, field_index=2, bit=20)
    rep = await drv.program_thermal(TDB, TDSF)
    assert sim.cal.flips_done == 1
    assert rep.attempts == 2 and len(rep.retries) == 1 and "crc_mismatch" in rep.retries[0]
    assert sim.cal.nvm.thermal == WANT and sim.cal.nvm.writes == 2  # the flipped write was overwritten


async def test_serial_refused_write_is_a_named_error_after_three_tries(serial_rig):
    sim, drv = serial_rig
    sim.cal.refuse_writes(99)
    with pytest.raises(CalibrationError) as ei:
        await drv.program_thermal(TDB, TDSF)
    assert ei.value.kind == "refused" and ei.value.attempts == 3 and "3 attempts" in str(ei.value)
    assert sim.cal.refused_done == 3 and sim.cal.nvm.thermal == (0.0,) * 6 and not sim.cal.nvm.comp


async def test_serial_lost_reply_retried_then_named_error(serial_rig):
    sim, drv = serial_rig
    sim.cal.drop_replies(1)
    rep = await drv.program_thermal(TDB, TDSF)
    assert rep.attempts == 2 and "no_reply" in rep.retries[0]
    sim.cal.drop_replies(99)
    with pytest.raises(CalibrationError) as ei:
        await drv.program_thermal(TDB, TDSF)
    assert ei.value.kind == "no_reply"


async def test_serial_sfem_write_and_read(serial_rig):
    sim, drv = serial_rig
    a = np.array([[1.02, 0.001, 0.0], [-0.002, 0.98, 0.0], [0.0, 0.003, 1.01]])
    b = np.array([0.012, -0.02, 0.004])
    crc = await drv.write_sfem(a, b)
    want = f32(tuple(a.reshape(-1)) + tuple(b))
    assert crc == zlib.crc32(struct.pack("<12f", *want))
    rb = await drv.read_sfem()
    assert rb.values == want and rb.crc == crc


async def test_serial_compensated_samples_follow_eq13_with_board_temperature(serial_rig):
    sim, drv = serial_rig
    await drv.identify()
    await drv.program_thermal(TDB, TDSF)
    await drv.start()
    n = 200
    k = np.arange(n)
    temp_c = 25.0 + 0.2 * k  # 25..65 C
    acc_g = np.tile([0.577, -0.577, 0.577], (n, 1))
    raw_g = acc_g + (temp_c - 25)[:, None] * (np.array(TDB) * 1e-3 + np.array(TDSF) * 1e-6 * acc_g)
    counts = np.rint(raw_g / 3.9e-6).astype(np.int64)
    tcounts = np.rint((temp_c - 25) * -9.05 + 1885).astype(np.int64)
    sim.feed(k / 3.125, counts, tcounts)
    blk = await _collect(drv, n)
    assert len(blk) == n
    # independent truth: eq. 13 on the counts the board had, with its temperature counts
    want = compensate(counts * 3.9e-6, ADXL.temp_c(tcounts), TDB, TDSF)
    assert np.max(np.abs(blk.acc_g - want)) <= 0.5 * 3.9e-6 + 1e-9  # one rounding to counts
    assert np.max(np.abs(blk.acc_g - acc_g)) < 1e-4  # the drift (up to 48 mg) is gone (0.1 C temperature steps)


# ---- CAN ------------------------------------------------------------------------------------

async def test_can_program_readback_comp_and_power_cycle(can_rig):
    sims, boards = can_rig
    rep = await boards[9].program_thermal(TDB, TDSF)
    assert rep.attempts == 1 and rep.comp and rep.readback.values == WANT and rep.crc == WANT_CRC
    s = sims[9]
    assert s.cal.nvm.thermal == WANT and s.cal.nvm.comp
    assert sims[3].cal.nvm.thermal == (0.0,) * 6 and not sims[3].cal.nvm.comp  # node 3 untouched
    # the wire: six CAL_FIELD frames in index order, CAL_COMMIT with the LE CRC, CAL_READ, COMP 1, CAL_READ
    assert s.commands[:6] == [bytes([5, k]) + struct.pack("<f", v) for k, v in enumerate(WANT)]
    assert s.commands[6] == b"\x06" + WANT_CRC.to_bytes(4, "little")
    assert s.commands[7:] == [b"\x07", b"\x08\x01", b"\x07"]
    s.power_cycle()
    rb = await boards[9].read_thermal()
    assert rb.values == WANT and rb.comp and rb.crc == WANT_CRC


async def test_can_bit_flip_caught_by_board_crc_and_retried(can_rig):
    sims, boards = can_rig
    sims[3].cal.flip_next_write(1, field_index=4, bit=0)
    rep = await boards[3].program_thermal(TDB, TDSF)
    assert sims[3].cal.flips_done == 1 and rep.attempts == 2 and "crc_mismatch" in rep.retries[0]
    assert sims[3].cal.nvm.thermal == WANT and sims[3].cal.nvm.writes == 1  # the flipped set was never stored


async def test_can_refused_and_lost_replies(can_rig):
    sims, boards = can_rig
    sims[3].cal.refuse_writes(99)
    with pytest.raises(CalibrationError) as ei:
        await boards[3].program_thermal(TDB, TDSF)
    assert ei.value.kind == "refused" and sims[3].cal.refused_done == 3
    sims[9].cal.drop_replies(1)
    rep = await boards[9].program_thermal(TDB, TDSF)
    assert rep.attempts == 2 and "no_reply" in rep.retries[0]


async def test_can_compensated_samples(can_rig):
    sims, boards = can_rig
    drv, s = boards[3], sims[3]
    await drv.identify()
    await drv.program_thermal(TDB, TDSF)
    await drv.start()
    for _ in range(200):  # START is fire-and-forget on CAN: wait until the board has it
        if s.streaming:
            break
        await asyncio.sleep(0.01)
    n = 150
    k = np.arange(n)
    temp_c = 25.0 + np.floor(k / 5.0)  # LIS3DSH: 1 C steps
    acc_g = np.tile([0.577, -0.577, 0.577], (n, 1))
    raw_g = acc_g + (temp_c - 25)[:, None] * (np.array(TDB) * 1e-3 + np.array(TDSF) * 1e-6 * acc_g)
    counts = np.rint(raw_g / 60e-6).astype(np.int64)
    s.feed(k / 3.125, counts, (temp_c - 25).astype(np.int64))
    blk = await _collect(drv, n)
    want = compensate(counts * 60e-6, temp_c, TDB, TDSF)
    assert len(blk) == n and np.max(np.abs(blk.acc_g - want)) <= 30e-6 + 1e-9
    assert np.max(np.abs(blk.acc_g - acc_g)) < 1e-4


async def test_serial_compensation_applies_sfem_after_eq13(serial_rig):
    sim, drv = serial_rig
    await drv.identify()
    a = np.array([[1.02, 0.001, 0.0], [-0.002, 0.98, 0.0], [0.0, 0.003, 1.01]])
    b = np.array([0.012, -0.02, 0.004])
    await drv.write_sfem(a, b)
    await drv.program_thermal(TDB, TDSF)
    await drv.start()
    n = 100
    k = np.arange(n)
    temp_c = 25.0 + 0.3 * k
    counts = np.tile([150000, -140000, 145000], (n, 1)) + k[:, None]
    tcounts = np.rint((temp_c - 25) * -9.05 + 1885).astype(np.int64)
    sim.feed(k / 3.125, counts, tcounts)
    blk = await _collect(drv, n)
    a32, b32 = np.array(f32(tuple(a.reshape(-1)))).reshape(3, 3), np.array(f32(tuple(b)))
    want = (compensate(counts * 3.9e-6, ADXL.temp_c(tcounts), TDB, TDSF) - b32) @ a32.T
    assert len(blk) == n and np.max(np.abs(blk.acc_g - want)) <= 0.5 * 3.9e-6 + 1e-9
    sim.power_cycle()  # the SFEM is in NVM too
    assert (await drv.read_sfem()).values == f32(tuple(a.reshape(-1)) + tuple(b))


async def test_serial_readback_with_the_right_values_but_a_wrong_crc_is_caught(serial_rig):
    """The board's CRC word of what it stores is checked on read-back, not only the values: a
    damaged CRC (values intact) is retried and, when it persists, a named error."""
    sim, drv = serial_rig
    sim.cal.corrupt_readback_crc(1)
    rep = await drv.program_thermal(TDB, TDSF)
    assert rep.attempts == 2 and "readback_mismatch" in rep.retries[0] and sim.cal.bad_crcs_done == 1
    sim.cal.corrupt_readback_crc(99)
    with pytest.raises(CalibrationError) as ei:
        await drv.program_thermal(TDB, TDSF)
    assert ei.value.kind == "readback_mismatch" and sim.cal.nvm.thermal == WANT  # values fine, CRC not


async def test_can_readback_with_the_right_values_but_a_wrong_crc_is_caught(can_rig):
    sims, boards = can_rig
    sims[3].cal.corrupt_readback_crc(99)
    with pytest.raises(CalibrationError) as ei:
        await boards[3].program_thermal(TDB, TDSF)
    assert ei.value.kind == "readback_mismatch" and sims[3].cal.nvm.thermal == WANT
