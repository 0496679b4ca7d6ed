"""The driver's methods for the board's own streaming calibrator (design 3.1 $SCAL / $SCRR / G / R,
issue 42): against a board written from the contract (tests/contract_v2_peer.py, a real pty) and
against the reference firmware itself (firmware/build/host/fwboard, a real process on a real pty).

What must hold: SCAL is acknowledged; SCRR gives the result with its clamp flags, or raises the
board's own `E,SCRR` text; `G` frames arriving in the middle of the sample stream are held for
take_selfcal_segments and disturb nothing (every sample delivered, nothing lost or malformed); a
board or link without the capability says so (property False, a DriverError that says "not
supported").
"""

from __future__ import annotations

import asyncio
from functools import reduce
from operator import xor

import numpy as np
import pytest

from contract_v2_peer import ContractPeer
from contracts.sfem_cubic import SfemCubicRecord
from contracts.types import Identity, SampleBlock
from drivers.base import BoardSelfCalResult, CalibrationError, NotSupportedByBoard
from drivers.can_board import CanBoard, CanBus
from drivers.protocol.selfcal_frames import SegmentReportFrame
from drivers.serial_board import BoardErrorReply, SerialBoard
from drivers.sim.firmware_build import missing_tools


def _frame(body: str) -> bytes:
    raw = body.encode()
    return b"$%s*%02X\n" % (raw, reduce(xor, raw, 0))


async def _collect(drv, n: int, timeout_s: float = 10.0) -> SampleBlock:
    blocks, got = [], 0
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    while got < n and loop.time() < end:
        b = await drv.read_block(0.3)
        blocks.append(b)
        got += len(b)
    return SampleBlock.concat(blocks)


async def test_selfcal_against_the_contract_peer():
    peer = ContractPeer(extras=",reset=power,boots=1,caps=scal")
    drv = SerialBoard(peer.path, ack_timeout_s=0.5)
    await drv.open()
    try:
        await drv.identify()
        assert drv.supports_selfcal and not drv.supports_sfem_cubic
        await drv.set_selfcal(True)
        assert peer.selfcal_on and peer.commands[-1] == ["SCAL", "1"]
        with pytest.raises(BoardErrorReply) as exc:
            await drv.read_selfcal()
        assert exc.value.code == "SCRR" and exc.value.text == "no result: no segments"
        peer.scrr_reply = "R,0.5,-1.25,0.031,-120,0,-480.5,6,2"
        assert await drv.read_selfcal() == BoardSelfCalResult((0.5, -1.25, 0.031), (-120.0, 0.0, -480.5), 6,
                                                              (False, True, False))
        # G frames in the middle of the stream: held apart, the samples untouched
        await drv.start()
        lines, segs = [], []
        for k in range(300):
            lines.append(_frame(f"D,{k},{k * 320000},{k},{-k},{16000 + k},{k % 7}"))
            if k % 100 == 50:
                seg = SegmentReportFrame(k // 100, k // 100, k * 320000, (0.001, -0.002, 0.998), 25.5 + k / 100, 900)
                segs.append(seg)
                lines.append(_frame(f"G,{seg.index},{seg.orientation},{seg.t_end_us},0.001,-0.002,0.998,"
                                    f"{seg.temp_c!r},900"))
        peer.send(b"".join(lines))
        blk = await _collect(drv, 300)
        assert len(blk) == 300 and blk.lost_samples == 0
        np.testing.assert_array_equal(blk.time_s, np.arange(300) * 320000 / 1e6)
        np.testing.assert_array_equal(blk.acc_g[:, 2], (16000 + np.arange(300)) * 3.9e-6)
        assert drv.take_selfcal_segments() == segs and drv.take_selfcal_segments() == []
        assert drv.stats.frames_malformed == 0 and drv.stats.resets == 0 and drv.stats.frames_bad_checksum == 0
        await drv.set_selfcal(False)
        assert not peer.selfcal_on
    finally:
        await drv.close()
        peer.close()


async def test_boards_without_the_capability_say_so():
    peer = ContractPeer()  # an old board: no caps
    drv = SerialBoard(peer.path, ack_timeout_s=0.5)
    await drv.open()
    try:
        await drv.identify()
        assert not drv.supports_selfcal and not drv.supports_sfem_cubic
    finally:
        await drv.close()
        peer.close()
    can = CanBoard(CanBus("virtual", "test-no-selfcal", None), 5)
    assert not can.supports_selfcal and not can.supports_sfem_cubic and can.take_selfcal_segments() == []
    with pytest.raises(NotSupportedByBoard, match="not supported by this board"):
        await can.set_selfcal(True)
    with pytest.raises(NotSupportedByBoard, match="not supported by this board"):
        await can.read_selfcal()
    rec = SfemCubicRecord(25.0, 0.0, 50.0, ((1.0,) * 12,) * 4)
    with pytest.raises(CalibrationError, match="not supported by this board") as exc:
        await can.write_sfem_cubic(rec)
    assert exc.value.kind == "unsupported"
    with pytest.raises(CalibrationError, match="not supported by this board"):
        await can.read_sfem_cubic()


ADXL = Identity("FWSC0001", "ADXL355", "fw-c-1.0", 3.9, -9.05, 1885.0, 3.125)


async def test_selfcal_on_the_reference_firmware():
    """The C firmware's calibrator (firmware/core/fw_selfcal.c) through the production driver: it
    runs without START on every sample its sensor gives; a steady orientation at a steady
    temperature saves segments (G frames, their raw means in g and C), and SCRR answers."""
    if missing_tools("host"):
        pytest.skip(f"no {missing_tools('host')}")
    from drivers.sim.firmware_boards import FirmwareBoard

    board = FirmwareBoard(ADXL, "host")
    board.start()
    drv = SerialBoard("", ack_timeout_s=2.0)
    try:
        await board.wait_ready()
        drv.port = board.path
        await drv.open()
        await drv.identify()
        await drv.set_selfcal(True)
        n = 4000  # 40 s at 100 Hz, still: the calibrator saves at least one segment
        board.feed(np.arange(n) * 0.01, np.tile([0, 0, 256410], (n, 1)), np.full(n, 1885))
        segs: list[SegmentReportFrame] = []
        loop = asyncio.get_running_loop()
        end = loop.time() + 20.0
        while not segs and loop.time() < end:
            await asyncio.sleep(0.2)
            segs = drv.take_selfcal_segments()
        assert segs, "no G frame from the firmware's calibrator"
        for s in segs:
            assert abs(s.acc_g[2] - 256410 * 3.9e-6) < 1e-3 and abs(s.acc_g[0]) < 1e-6 and abs(s.temp_c - 25.0) < 1e-3
        try:
            res = await drv.read_selfcal()
            assert res.n_segments >= 1
        except BoardErrorReply as exc:  # one orientation at one temperature: no TDB to fit yet
            assert exc.code == "SCRR" and exc.text.startswith("no result: ")
        await drv.set_selfcal(False)
        assert drv.stats.frames_malformed == 0 and drv.stats.frames_bad_checksum == 0
    finally:
        await drv.close()
        board.close()
