"""The board firmware as real processes: build/host/fwboard on a real pty, fed by a sensor bridge.

The station side is the production driver (drivers/serial_board.SerialBoard, pyserial on the pty
slave) or raw slcan lines decoded with drivers/protocol/{slcan_lines,can_frames}.py. The NVM is a
real file: power cycles are process restarts; a corrupt byte in the file and a flash write torn by
a power loss (--nvm-tear-after) are checked at boot.
"""

from __future__ import annotations

import asyncio
import socket
import struct
import subprocess
import time

import numpy as np
import pytest

from contracts.types import Identity
from drivers.protocol import can_frames as cf
from drivers.protocol import serial_frames as sf
from drivers.protocol.cal_record import crc32_f32, to_f32
from drivers.protocol.slcan_lines import split_frames
from drivers.serial_board import SerialBoard
from drivers.sim.board_nvm import CalFirmware
from tests.firmware_nvm import SLOT_BYTES
from tests.firmware_proc import FwProc, _spawn, fwboard, procs  # noqa: F401 (fixtures)

LIS = Identity("SN0001", "LIS3DSH", "fw-c-1.0", 60.0, 1.0, 0.0, 3.125)
ADXL = Identity("AX0001", "ADXL355", "fw-c-1.0", 3.9, -9.05, 1885.0, 3.125)
SLOT = SLOT_BYTES


async def _collect(drv, n, timeout_s=10.0):
    from contracts.types import SampleBlock
    blocks, got = [], 0
    end = time.monotonic() + timeout_s
    while got < n and time.monotonic() < end:
        b = await drv.read_block(0.5)
        blocks.append(b)
        got += len(b)
    return SampleBlock.concat(blocks)


async def test_serial_board_driver_end_to_end(fwboard, tmp_path, procs):
    rng = np.random.default_rng(21)
    p = _spawn(procs, fwboard, ADXL, tmp_path / "nvm.bin")
    drv = SerialBoard(p.path, ack_timeout_s=2.0)
    await drv.open()
    try:
        assert await drv.identify() == ADXL
        await drv.start()
        n = 300
        acc = rng.integers(-500000, 500000, (n, 3))
        temp = rng.integers(1500, 2300, n)
        ts = p.feed(acc, temp)
        blk = await _collect(drv, n)
        assert len(blk) == n and blk.lost_samples == 0
        np.testing.assert_array_equal(blk.time_s, np.array(ts) / 1e6)
        np.testing.assert_array_equal(blk.acc_g, ADXL.acc_g(acc))
        np.testing.assert_array_equal(blk.temp_c, ADXL.temp_c(temp))
        await drv.stop()
        # the driver re-learns the sample period from the first step after START: let the board
        # take four samples while stopped (a t_us gap would count as missed samples, seq running
        # on), so one new period (1.6 s) lies between the last sample sent and the first decimated one
        p.feed(acc[:4], temp[:4])
        await drv.stop()  # a round trip: the board took the four before it reads the next command
        await drv.set_odr(0.625)
        await drv.start()
        p.feed(acc[:96], temp[:96])  # ends on a sent sample: the next rate's first step is its period
        blk = await _collect(drv, 20)
        assert len(blk) == 20
        np.testing.assert_array_equal(blk.acc_g, ADXL.acc_g(acc[:96:5]))
        await drv.stop()
        with pytest.raises(Exception):
            await drv.set_odr(1.0)  # E,ODR,unsupported rate 1
        # program and verify (write, read back, CRC, compensation on), then the SFEM
        tdb, tdsf = [0.71, -1.13, 0.22], [-120.5, -310.0, -5.25]
        report = await drv.program_thermal(tdb, tdsf)
        want = to_f32([*tdb, *tdsf])
        assert report.crc == crc32_f32(want) and report.comp and tuple(report.readback.values) == want
        a = np.eye(3) + 0.01 * np.arange(9).reshape(3, 3) / 9
        b = [0.01, -0.02, 0.005]
        sfem = to_f32([*a.reshape(-1), *b])
        assert await drv.write_sfem(a, b) == crc32_f32(sfem)
        rb = await drv.read_sfem()
        assert tuple(rb.values) == sfem and rb.crc == crc32_f32(sfem)
        # D frames now carry compensated counts (eq. 13 with the board's temperature, then the SFEM)
        await drv.set_odr(3.125)
        await drv.start()
        p.feed(acc[:100], temp[:100])
        blk = await _collect(drv, 100)
        fwc = CalFirmware()
        fwc.nvm.thermal, fwc.nvm.sfem = want, sfem
        expect = fwc.compensate_counts(acc[:100], ADXL.temp_c(temp[:100]), ADXL.ug_per_lsb)
        got = np.rint(blk.acc_g / (ADXL.ug_per_lsb * 1e-6)).astype(np.int64)
        assert np.abs(got - expect).max() <= 1 and (got == expect).mean() > 0.95
        await drv.stop()
        assert drv.stats.frames_bad_checksum == 0 and drv.stats.frames_malformed == 0
    finally:
        await drv.close()
    assert p.stop() == 0  # SIGTERM: clean exit


def _calw(p: FwProc, vals) -> list:
    return p.command(sf.cmd_calw(vals[:3], vals[3:])[1:-4].decode())


def test_nvm_survives_power_cycles_and_corruption(fwboard, tmp_path, procs):
    nvm = tmp_path / "nvm.bin"
    first = to_f32([0.5, -0.5, 0.25, -100, -200, -300])
    second = to_f32([1.0, -1.0, 0.5, -50, -60, -70])
    p = _spawn(procs, fwboard, LIS, nvm)
    assert nvm.read_bytes() == b"\xff" * (2 * SLOT)  # created erased
    assert p.command("CALR") == [sf.CalReadFrame((0.0,) * 6, crc32_f32([0.0] * 6), False)]
    assert _calw(p, first) == [sf.AckFrame("CALW", (sf.fmt_crc(crc32_f32(first)),))]
    assert p.command("COMP,1") == [sf.AckFrame("COMP")]
    assert _calw(p, second) == [sf.AckFrame("CALW", (sf.fmt_crc(crc32_f32(second)),))]
    assert p.stop() == 0
    # power cycle: the newest record (generation 3) applied, no error at boot
    p = _spawn(procs, fwboard, LIS, nvm)
    assert p.read_until(lambda b: False, timeout=0.3) == b""
    assert p.command("CALR") == [sf.CalReadFrame(second, crc32_f32(second), True)]
    assert p.stop() == 0
    data = bytearray(nvm.read_bytes())
    gens = [struct.unpack_from("<I", data, k * SLOT + 8)[0] for k in range(2)]
    newest = int(np.argmax(gens))
    assert sorted(gens) == [2, 3]
    # one corrupt byte in the newest record: reported at boot, the older record applied
    data[newest * SLOT + 14] ^= 0x10
    nvm.write_bytes(bytes(data))
    p = _spawn(procs, fwboard, LIS, nvm)
    assert p.frames(p.read_until(lambda b: b"\n" in b)) == [
        sf.ErrorFrame("NVM", f"calibration record CRC mismatch in slot {newest}")]
    assert p.command("CALR") == [sf.CalReadFrame(first, crc32_f32(first), True)]
    assert p.stop() == 0
    # both corrupt: zeros, compensation off, CALR refused; D frames are raw counts
    data[(1 - newest) * SLOT + 50] ^= 0x01
    nvm.write_bytes(bytes(data))
    p = _spawn(procs, fwboard, LIS, nvm)
    assert len(p.frames(p.read_until(lambda b: b.count(b"\n") >= 2))) == 2
    assert p.command("CALR") == [sf.ErrorFrame("CALR", "calibration record corrupt")]
    assert p.command("START") == [sf.AckFrame("START")]
    p.feed([[1000, -1000, 16000]] * 3, [40] * 3)
    got = p.frames(p.read_until(lambda b: b.count(b"\n") >= 3))
    assert [(f.ax, f.ay, f.az, f.t) for f in got] == [(1000, -1000, 16000, 40)] * 3
    assert p.command("STOP") == [sf.AckFrame("STOP")]
    assert _calw(p, first)[0] == sf.AckFrame("CALW", (sf.fmt_crc(crc32_f32(first)),))
    assert p.command("CALR") == [sf.CalReadFrame(first, crc32_f32(first), False)]
    assert p.stop() == 0


@pytest.mark.parametrize("tear", [1, 50, 103])
def test_torn_flash_write_is_never_applied(fwboard, tmp_path, procs, tear):
    nvm = tmp_path / "nvm.bin"
    old = to_f32([0.5, -0.5, 0.25, -100, -200, -300])
    new = to_f32([1.0, -1.0, 0.5, -50, -60, -70])
    p = _spawn(procs, fwboard, LIS, nvm)
    _calw(p, old)
    assert p.stop() == 0
    p = _spawn(procs, fwboard, LIS, nvm, tear=tear)
    p.write(sf.cmd_calw(new[:3], new[3:]))
    assert p.proc.wait(5) != 0  # power lost in the middle of the write: no reply
    p.stop()
    p = _spawn(procs, fwboard, LIS, nvm)
    assert p.frames(p.read_until(lambda b: b"\n" in b)) == [
        sf.ErrorFrame("NVM", "calibration record CRC mismatch in slot 1")]
    assert p.command("CALR") == [sf.CalReadFrame(old, crc32_f32(old), False)]
    assert p.stop() == 0


def test_own_pty_and_bridge_eof(fwboard, tmp_path):
    a, child = socket.socketpair()
    proc = subprocess.Popen([str(fwboard), "--uart-pty", "--bridge-fd", str(child.fileno()), "--nvm",
                             str(tmp_path / "n.bin"), "--fw", "fw-x-2"], pass_fds=(child.fileno(),),
                            stdout=subprocess.PIPE, text=True)
    child.close()
    try:
        line = proc.stdout.readline()
        assert line.startswith("PTY /dev/pts/")
        a.sendall(sf.encode("B,SN9,LIS3DSH,60,1,0,3.125"))
        a.settimeout(5)
        assert a.recv(64) == sf.encode("READY")
        time.sleep(1.0)  # idle: poll() blocks, no busy loop (many boards share two cores)
        fields = open(f"/proc/{proc.pid}/stat").read().rsplit(")", 1)[1].split()
        assert int(fields[11]) + int(fields[12]) <= 5, "CPU ticks while idle"

        async def identify():
            drv = SerialBoard(line.split()[1])
            await drv.open()
            try:
                return await drv.identify()
            finally:
                await drv.close()
        assert asyncio.run(identify()) == Identity("SN9", "LIS3DSH", "fw-x-2", 60.0, 1.0, 0.0, 3.125)
        a.close()  # the simulator goes away: the board process ends
        assert proc.wait(5) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _slcan(arb: int, data: bytes) -> bytes:
    return b"t%03X%d%s\r" % (arb, len(data), data.hex().upper().encode())


def test_can_node_over_slcan_lines(fwboard, tmp_path, procs):
    node = 7
    nvm = tmp_path / "can.bin"
    p = _spawn(procs, fwboard, ADXL, nvm, can=node)

    def exchange(data: bytes, n: int) -> list[tuple[int, bytes]]:
        p.write(_slcan(cf.CMD_BASE + node, data))
        buf = bytearray(p.read_until(lambda b: b.count(b"\r") >= n, timeout=2.0 if n else 0.3))
        frames, garbled = split_frames(buf)
        assert garbled == 0 and not buf
        return frames

    frames = exchange(cf.encode_command(cf.CMD_IDENTIFY), 5)
    assert [a for a, _ in frames] == [cf.IDENT_BASE + node] * 5
    assert [d for _, d in frames[:4]] == cf.encode_identity("AX0001", 3.9 * 16, 3.125)
    # frame 11 (contract v2): reset cause (the target's), record state 2 = empty, version 0, generation 0
    assert frames[4][1][0] == 11 and frames[4][1][1] <= 6 and frames[4][1][2:] == bytes([2, 0, 0, 0, 0, 0])
    assert exchange(bytes([cf.CMD_START]), 0) == []
    acc = np.array([[256410, -256410, 1000], [-17, 8, 7], [524287, -524288, 0], [24, -24, 8]])
    temp = np.array([1885, 1885 - 905, 1885 + 452, 1885 + 5000])
    p.feed(acc, temp)
    frames, _ = split_frames(bytearray(p.read_until(lambda b: b.count(b"\r") >= 4)))
    from drivers.sim.slcan_pty import SimCanBoard
    sent = []
    sim = SimCanBoard(node, ADXL, send=lambda arb, data: sent.append((arb, bytes(data))))
    sim.streaming = True
    sim.feed(np.arange(4) / 3.125, acc, temp)
    assert frames == sent  # shift 4 with rounding, int8 temperature clamped, seq
    assert cf.decode_sample(frames[0][1]) == cf.CanSample(16026, -16026, 63, 0, 0)
    assert exchange(bytes([cf.CMD_STOP]), 0) == []
    vals = to_f32([0.7, -1.1, 0.2, -120.5, -310.0, -5.25])
    for k, v in enumerate(vals):
        assert exchange(cf.encode_cal_field(k, v), 0) == []
    ((arb, st),) = exchange(cf.encode_cal_commit(crc32_f32(vals)), 1)
    assert cf.decode_cal_reply(st)[1] == cf.CalStatus(cf.CAL_STORED, False, crc32_f32(vals))
    assert exchange(cf.encode_comp(True), 0) == []
    assert p.stop() == 0
    p = _spawn(procs, fwboard, ADXL, nvm, can=node)  # power cycle
    (frame11,) = [d for _, d in exchange(cf.encode_command(cf.CMD_IDENTIFY), 5) if d[0] == 11]
    assert frame11[2:] == bytes([0, 1]) + struct.pack("<I", 2)  # ok, version 1, generation 2 (commit, COMP)
    frames = exchange(cf.encode_cal_read(), 7)
    assert [cf.decode_cal_reply(d)[1] for _, d in frames[:6]] == list(vals)
    assert cf.decode_cal_reply(frames[6][1])[1] == cf.CalStatus(cf.CAL_STORED, True, crc32_f32(vals))
    assert p.stop() == 0
