"""Serial board driver against simulated boards on real pseudo-terminals (no mocks)."""

import asyncio

import numpy as np
import pytest

from drivers.base import DriverError
from drivers.protocol import serial_frames as sf
from drivers.serial_board import SerialBoard
from drivers.sim.serial_pty import SimSerialBoard
from contracts.types import Identity

LIS = Identity("SN0001", "LIS3DSH", "1.2", 60.0, 1.0, 0.0, 3.125)
ADXL = Identity("AX0001", "ADXL355", "1.0", 3.9, -9.05, 1885.0, 3.125)


def _stream(n, odr=3.125, start=0):
    k = np.arange(start, start + n)
    time_s = k / odr
    acc = np.stack([k % 100 - 50, -k, 16000 + k % 7], axis=1)
    temp = (k // 10) % 50
    return time_s, acc, temp


async def _collect(drv, n, timeout_s=10.0):
    blocks = []
    got = 0
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    while got < n and loop.time() < end:
        b = await drv.read_block(0.5)
        blocks.append(b)
        got += len(b)
    from contracts.types import SampleBlock

    return SampleBlock.concat(blocks)


@pytest.fixture
async def board():
    sim = SimSerialBoard(LIS)
    sim.start()
    drv = SerialBoard(sim.path)
    await drv.open()
    yield sim, drv
    await drv.close()
    sim.close()


async def test_identify_start_and_exact_samples(board):
    sim, drv = board
    ident = await drv.identify()
    assert ident == LIS
    await drv.start()
    assert sim.streaming
    assert sim.commands[:2] == [b"$ID*0D\n", b"$START*40\n"]
    t, acc, temp = _stream(500)
    sim.feed(t, acc, temp)
    blk = await _collect(drv, 500)
    assert len(blk) == 500 and blk.lost_samples == 0
    np.testing.assert_allclose(blk.time_s, t, atol=1e-6)
    np.testing.assert_allclose(blk.acc_g, acc * 60e-6, rtol=1e-12)
    np.testing.assert_allclose(blk.temp_c, 25.0 + temp)
    assert drv.stats.frames_ok == 502 and drv.stats.samples_lost == 0


async def test_adxl_scaling():
    sim = SimSerialBoard(ADXL)
    sim.start()
    drv = SerialBoard(sim.path)
    await drv.open()
    try:
        await drv.start()  # identifies on its own
        sim.feed(np.array([0.0]), np.array([[256410, -256410, 0]]), np.array([1885 - 905]))
        blk = await _collect(drv, 1)
        np.testing.assert_allclose(blk.acc_g[0], [256410 * 3.9e-6, -256410 * 3.9e-6, 0.0])
        assert blk.temp_c[0] == pytest.approx(125.0)
    finally:
        await drv.close()
        sim.close()


async def test_odr_and_stop_bytes_on_the_wire(board):
    sim, drv = board
    await drv.identify()
    await drv.set_odr(1.5625)
    await drv.stop()
    assert sim.commands[-2:] == [sf.encode("ODR,1.5625"), b"$STOP*18\n"]
    assert drv.identity.odr_hz == 1.5625
    with pytest.raises(DriverError, match="unsupported"):
        await drv.set_odr(7.0)  # the board answers E: not a divisor of its rate


async def test_faults_counted_not_fatal(board):
    sim, drv = board
    await drv.start()
    t, acc, temp = _stream(10)
    sim.feed(t[:3], acc[:3], temp[:3])
    sim.inject_garbage(b"\x00\x13garbage\n$D,1,2")  # garbage line, then a partial frame
    sim.corrupt_next(2)  # seq 3 and 4 arrive with bad checksums -> lost
    sim.feed(t[3:], acc[3:], temp[3:])
    blk = await _collect(drv, 8)
    assert len(blk) == 8
    assert blk.lost_samples == 2 and drv.stats.samples_lost == 2
    assert drv.stats.frames_bad_checksum == 2
    # 10 bytes of garbage line + the 6-byte partial frame glued to the next frame's start
    assert drv.stats.bytes_skipped == 10 + 6
    assert drv.stats.frames_malformed == 0


async def test_seq_wrap_and_clock_wrap(board):
    sim, drv = board
    await drv.start()
    sim.seq = 0xFFFFFFFE
    sim.t0_us = 2**32 - 640000  # board clock 0.64 s before its uint32 wrap
    t, acc, temp = _stream(6)
    sim.feed(t[:3], acc[:3], temp[:3])
    sim.seq = (sim.seq + 2) & 0xFFFFFFFF  # two samples lost across the wrap
    sim.feed(t[5:], acc[5:], temp[5:])
    blk = await _collect(drv, 4)
    assert blk.lost_samples == 2
    np.testing.assert_allclose(blk.time_s - blk.time_s[0], [0, 0.32, 0.64, 1.6], atol=1e-6)


async def test_port_vanishing_faults_that_board_only():
    sims = [SimSerialBoard(LIS) for _ in range(2)]
    for s in sims:
        s.start()
    drvs = [SerialBoard(s.path) for s in sims]
    try:
        for d in drvs:
            await d.open()
            await d.start()
        t, acc, temp = _stream(20)
        for s in sims:
            s.feed(t[:10], acc[:10], temp[:10])
        assert len(await _collect(drvs[0], 10)) == 10
        sims[0].disconnect()
        sims[1].feed(t[10:], acc[10:], temp[10:])
        with pytest.raises(DriverError, match="vanished"):
            for _ in range(5):
                await drvs[0].read_block(0.5)
        with pytest.raises(DriverError):
            await drvs[0].start()
        assert len(await _collect(drvs[1], 20)) == 20  # the other board streams on
    finally:
        for d in drvs:
            await d.close()
        for s in sims:
            s.close()


async def test_no_reply_and_missing_port_errors(tmp_path):
    with pytest.raises(DriverError, match="cannot open"):
        await SerialBoard(str(tmp_path / "ttyNOPE")).open()
    sim = SimSerialBoard(LIS)
    sim.start()
    sim._command = lambda frame: None  # a board that never answers
    drv = SerialBoard(sim.path, ack_timeout_s=0.1, retries=2)
    await drv.open()
    try:
        with pytest.raises(DriverError, match="no identity reply"):
            await drv.identify(timeout_s=0.3)
        drv.identity = LIS
        with pytest.raises(DriverError, match="did not acknowledge START"):
            await drv.start()
        assert sim.commands.count(b"$START*40\n") == 2
    finally:
        await drv.close()
        sim.close()


async def test_pyserial_url_without_fd_uses_reader_thread():
    """loop:// echoes what we write: our own command comes back as a frame we skip (unknown)."""
    drv = SerialBoard("loop://")
    await drv.open()
    try:
        assert drv._thread is not None
        drv._write(sf.SampleFrame(0, 5, 1, 2, 3, 4).encode())
        drv.identity = LIS
        blk = await drv.read_block(2.0)
        assert len(blk) == 1 and blk.time_s[0] == pytest.approx(5e-6)
    finally:
        await drv.close()


@pytest.mark.parametrize("body", [
    "D,1,2,99999999999999999999,0,0,25",   # count beyond int64: once an OverflowError in read_block
    "D,1,2,0,0,0,4294967296",              # temperature count beyond int32
    "D,4294967296,2,0,0,0,25",             # seq beyond uint32
    "D,1,18446744073709551616,0,0,0,25",   # t_us beyond uint64
])
async def test_checksum_valid_out_of_range_frame_is_counted_and_skipped(board, body):
    """A frame that passes the checksum but holds a number outside its field is malformed: counted,
    skipped, and the samples around it arrive (the slot lives on)."""
    sim, drv = board
    await drv.start()
    t, acc, temp = _stream(20)
    sim.feed(t[:10], acc[:10], temp[:10])
    sim.inject_garbage(sf.encode(body))
    sim.feed(t[10:], acc[10:], temp[10:])
    blk = await _collect(drv, 20)
    assert len(blk) == 20
    np.testing.assert_allclose(blk.acc_g, acc * 60e-6, rtol=1e-12)
    assert drv.stats.frames_malformed == 1


@pytest.mark.parametrize("fields", [("nan", "1", "0", "3.125"), ("60", "0", "0", "3.125"),
                                    ("60", "1", "inf", "3.125"), ("0", "1", "0", "3.125"),
                                    ("60", "1", "0", "-1")])
def test_identity_with_nan_or_zero_scale_is_malformed(fields):
    """A NaN/zero scale would make every sample NaN and blind the over-temperature check."""
    parser = sf.FrameParser()
    frames = parser.feed(sf.encode(",".join(("I", "SN1", "LIS3DSH", "1", *fields))))
    assert frames == [] and parser.stats.frames_malformed == 1
