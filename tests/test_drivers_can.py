"""CAN driver: 4 boards on one bus by node id, through python-can's own slcan interface talking to
a simulated slcan adapter on a pty, and through python-can's virtual interface."""

import asyncio
import struct

import numpy as np
import pytest

from drivers.base import DriverError
from drivers.can_board import CanBoard, CanBus
from drivers.sim.slcan_pty import SimCanBoard, SimCanHub, SlcanPtyAdapter, VirtualCanBridge, can_scale
from contracts.types import Identity, SampleBlock

NODES = (1, 5, 42, 127)


def _ident(node):
    return Identity(f"CAN-{node:03d}", "LIS3DSH", "", 60.0, 1.0, 0.0, 3.125)


def _stream(n, node):
    k = np.arange(n)
    acc = np.stack([k - 100 + node, -k * 3, 16000 + node * np.ones(n, dtype=int)], axis=1)
    temp = (k // 20) + node % 10  # LIS3DSH counts: 1 C/LSB, 0 = 25 C
    return k / 3.125, acc, temp


async def _collect(drv, n, timeout_s=15.0):
    blocks, got = [], 0
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    while got < n and loop.time() < end:
        b = await drv.read_block(0.5)
        blocks.append(b)
        got += len(b)
    return SampleBlock.concat(blocks)


@pytest.fixture(params=["slcan", "virtual"])
async def rig(request):
    hub = SimCanHub()
    sims = {n: hub.add(SimCanBoard(n, _ident(n))) for n in NODES}
    if request.param == "slcan":
        adapter = SlcanPtyAdapter(hub)
        bus = CanBus("slcan", adapter.path, 500_000, sleep_after_open=0)
    else:
        adapter = VirtualCanBridge(hub, f"test-{id(hub)}")
        bus = CanBus("virtual", adapter.channel, None)
    adapter.start()
    boards = {n: CanBoard(bus, n) for n in NODES}
    for b in boards.values():
        await b.open()
    yield request.param, adapter, sims, bus, boards
    for b in boards.values():
        await b.close()
    await bus.close()
    adapter.close()


async def test_identity_and_samples_by_node(rig):
    kind, adapter, sims, bus, boards = rig
    for n, b in boards.items():
        assert await b.identify() == _ident(n)
    if kind == "slcan":
        # python-can writes S6 then O without waiting for the adapter's ack; a round
        # trip (identify above) proves the adapter has processed both, in order.
        assert adapter.is_open and adapter.bitrate_cmd == "S6"
    for b in boards.values():
        await b.start()
    await asyncio.sleep(0.2)  # START frames reach the boards
    assert all(s.streaming for s in sims.values())
    n_samples = 300  # > 256: the uint8 seq wraps
    for n, s in sims.items():
        s.feed(*_stream(n_samples, n))
    for n, b in boards.items():
        blk = await _collect(b, n_samples)
        t, acc, temp = _stream(n_samples, n)
        assert len(blk) == n_samples and blk.lost_samples == 0
        np.testing.assert_allclose(blk.time_s, t, atol=1e-9)
        np.testing.assert_allclose(blk.acc_g, acc * 60e-6)
        np.testing.assert_allclose(blk.temp_c, 25.0 + temp)
        assert b.stats.samples_lost == 0


async def test_commands_on_the_wire_and_lost_frames(rig):
    kind, adapter, sims, bus, boards = rig
    b, s = boards[42], sims[42]
    await b.identify()
    await b.set_odr(1.5625)
    await b.start()
    await asyncio.sleep(0.2)
    assert s.commands == [b"\x03", b"\x04" + struct.pack("<f", 1.5625), b"\x01"]
    assert sims[5].commands == []  # other nodes heard nothing addressed to them
    t, acc, temp = _stream(40, 42)
    s.feed(t[:10], acc[:10], temp[:10])  # decimated by 2: 5 samples
    s.corrupt_next(2)  # CRC errors: these frames never arrive
    s.feed(t[10:], acc[10:], temp[10:])
    blk = await _collect(b, 18)
    assert len(blk) == 18 and blk.lost_samples == 2
    np.testing.assert_allclose(np.diff(blk.time_s)[:4], 0.64)
    await b.stop()
    await asyncio.sleep(0.2)
    assert not s.streaming


async def test_adxl_on_can_scaled_to_int16():
    ident = Identity("ADX-1", "ADXL355", "", 3.9, -9.05, 1885.0, 3.125)
    shift, ug = can_scale(ident)
    assert (shift, ug) == (4, 62.4)
    hub = SimCanHub()
    sim = hub.add(SimCanBoard(9, ident))
    bridge = VirtualCanBridge(hub, "test-adxl")
    bridge.start()
    async with CanBus("virtual", "test-adxl", None) as bus:
        b = CanBoard(bus, 9)
        await b.open()
        got = await b.start() or b.identity
        assert got.ug_per_lsb == pytest.approx(62.4) and got.sensor == "ADXL355"
        await asyncio.sleep(0.2)
        sim.feed(np.array([0.0]), np.array([[256410, -16, 0]]), np.array([1885 - 905]))
        blk = await _collect(b, 1)
        np.testing.assert_allclose(blk.acc_g[0], [16026 * 62.4e-6, -1 * 62.4e-6, 0], rtol=1e-6)
        assert blk.temp_c[0] == pytest.approx(125.0)
    bridge.close()


async def test_adapter_gone_faults_every_board_on_that_bus():
    hub = SimCanHub()
    hub.add(SimCanBoard(1, _ident(1)))
    adapter = SlcanPtyAdapter(hub)
    adapter.start()
    bus = CanBus("slcan", adapter.path, 500_000, sleep_after_open=0)
    b = CanBoard(bus, 1)
    await b.open()
    await b.identify()
    adapter.close()
    with pytest.raises(DriverError, match="CAN bus"):
        for _ in range(10):
            await b.read_block(0.3)
    await bus.close()


async def test_missing_node_and_bad_channel():
    hub = SimCanHub()
    bridge = VirtualCanBridge(hub, "test-empty")
    bridge.start()
    async with CanBus("virtual", "test-empty", None) as bus:
        b = CanBoard(bus, 3)
        await b.open()
        with pytest.raises(DriverError, match="no identity reply from CAN node 3"):
            await b.identify(timeout_s=0.3)
        with pytest.raises(DriverError, match="already has a driver"):
            await CanBoard(bus, 3).open()
    bridge.close()
    with pytest.raises(DriverError, match="cannot open CAN bus"):
        await CanBus("slcan", "/dev/nonexistent-tty", 500_000, sleep_after_open=0).open()
