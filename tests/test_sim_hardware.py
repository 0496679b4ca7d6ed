"""SimStation end to end: the real drivers on the simulated station's ptys, slcan adapter and
Modbus server, with the SimWorld physics behind them."""

import asyncio

import numpy as np
import pytest

from drivers.base import DriverError
from drivers.can_board import CanBoard, CanBus
from drivers.modbus_devices import ModbusFixture, ModbusLampRelay, ModbusLink, ModbusThermometer
from drivers.serial_board import SerialBoard
from drivers.sim.station_sim import SimStation
from contracts.types import SampleBlock


async def _open_all(sim):
    boards = [SerialBoard(p) for p in sim.serial_ports]
    bus = CanBus(**sim.can_bus_args) if sim.n_can else None
    boards += [CanBoard(bus, n) for n in sim.can_node_ids]
    for b in boards:
        await b.open()
    return boards, bus


async def _drain(boards, acc, wall_s, sim=None, plant_s=None):
    """Read every board for wall_s, or (sim, plant_s) until the plant has lived plant_s more
    seconds: the simulator waits for a lagging reader, so plant time is what physics depends on."""
    loop = asyncio.get_running_loop()
    end = loop.time() + wall_s
    t_end = None if sim is None else sim.world.time_s + plant_s
    while (loop.time() < end) if t_end is None else (sim.world.time_s < t_end and loop.time() < end):
        for i, b in enumerate(boards):
            acc[i].append(await b.read_block(0.05))


async def test_two_serial_two_can_stream_and_lamp_heats_plate():
    async with SimStation(n_serial=2, n_can=2, seed=3, speed=250) as sim:
        assert len(sim.serial_ports) == 2 and sim.can_node_ids == [1, 2] and sim.slcan_port
        boards, bus = await _open_all(sim)
        idents = [await b.identify() for b in boards]
        assert [i.serial for i in idents] == [t.serial for t in sim.truths]
        for b in boards:
            await b.start()
        link = ModbusLink(sim.modbus_host, sim.modbus_port)
        relay, therm = ModbusLampRelay(link), ModbusThermometer(link)
        t_cold = await therm.read_temp_c()
        blocks = [[] for _ in boards]
        await relay.set_lamp(True)
        assert sim.world.lamp_on
        await _drain(boards, blocks, 60, sim, 600.0)  # 600 s of simulated lamp heating (~2.4 s wall)
        t_hot = await therm.read_temp_c()
        await relay.set_lamp(False)
        assert not sim.world.lamp_on
        await _drain(boards, blocks, 60, sim, 600.0)
        t_cooled = await therm.read_temp_c()
        assert t_hot > t_cold + 10 and t_cooled < t_hot - 5
        for i, b in enumerate(boards):
            blk = SampleBlock.concat(blocks[i])
            assert len(blk) > 500, b
            assert blk.lost_samples == 0 and b.stats.frames_bad_checksum == 0
            assert np.all(np.diff(blk.time_s) > 0)
            peak = int(np.argmax(blk.temp_c))
            assert blk.temp_c[peak] > blk.temp_c[0] + 10  # the DUT saw the lamp
            assert blk.temp_c[-1] < blk.temp_c[peak] - 3  # and cooled after it went off
            assert np.all(np.abs(np.linalg.norm(blk.acc_g, axis=1) - 1.0) < 0.2)
        await link.close()
        await bus.close()


async def test_samples_depend_on_sample_time_not_speed():
    runs = []
    for speed in (60.0, 400.0):
        async with SimStation(n_serial=1, n_can=0, seed=11, speed=speed) as sim:
            (b,), _ = await _open_all(sim)
            await b.start()
            blocks = [[]]
            await _drain([b], blocks, 1.2)
            runs.append(SampleBlock.concat(blocks[0]))
            await b.close()
    a, b = runs
    common, ia, ib = np.intersect1d(np.round(a.time_s, 6), np.round(b.time_s, 6), return_indices=True)
    assert len(common) > 100
    np.testing.assert_array_equal(a.acc_g[ia], b.acc_g[ib])
    np.testing.assert_array_equal(a.temp_c[ia], b.temp_c[ib])


async def test_fault_injection_and_fixture():
    async with SimStation(n_serial=2, n_can=1, seed=5, speed=100, move_time_s=2.0) as sim:
        boards, bus = await _open_all(sim)
        for b in boards:
            await b.start()
        fixture = ModbusFixture(ModbusLink(sim.modbus_host, sim.modbus_port))
        await fixture.move_to(1)
        assert await fixture.moving() and sim.world.position == 0
        await fixture.wait_reached(1, timeout_s=5.0)
        assert sim.world.position == 1
        sim.board(0).inject_garbage(b"\xde\xad\xbe\xef\n")
        sim.board(0).corrupt_next(3)
        sim.board(2).corrupt_next(2)
        blocks = [[] for _ in boards]
        await _drain(boards, blocks, 1.0)
        assert boards[0].stats.bytes_skipped == 5 and boards[0].stats.frames_bad_checksum == 3
        assert boards[0].stats.samples_lost == 3
        assert boards[2].stats.samples_lost == 2
        sim.board(1).disconnect()
        with pytest.raises(DriverError):
            for _ in range(20):
                await boards[1].read_block(0.1)
        sim.board(0).stop_streaming()
        await _drain([boards[0], boards[2]], [blocks[0], blocks[2]], 0.3)
        assert len(await boards[0].read_block(0.3)) == 0  # board 0 went quiet, its link is fine
        assert len(await boards[2].read_block(1.0)) > 0  # the CAN board streams on
        await bus.close()


async def test_virtual_can_interface():
    async with SimStation(n_serial=0, n_can=3, seed=2, speed=200, can_interface="virtual") as sim:
        assert sim.slcan_port is None
        boards, bus = await _open_all(sim)
        for b, t in zip(boards, sim.truths):
            assert (await b.identify()).serial == t.serial
            await b.start()
        blocks = [[] for _ in boards]
        await _drain(boards, blocks, 0.8)
        assert all(len(SampleBlock.concat(bl)) > 50 for bl in blocks)
        await bus.close()


async def test_plant_waits_for_a_lagging_reader_and_loses_nothing():
    """A host that takes its bytes slowly (a loaded daemon whose event loop is busy) holds the
    simulated plant instead of letting it run ahead (which once tripped the lamp-on limit of whole
    batches under load). The host here is a plain pyserial reader that takes one kernel buffer's
    worth every 0.3 s, far slower than 4000 x 3.125 samples/s of ~40-byte frames."""
    import serial

    from drivers.protocol import serial_frames as sf

    async with SimStation(n_serial=1, n_can=0, seed=2, speed=4000) as sim:
        port = serial.Serial(sim.serial_boards[0].port.path, timeout=0)
        port.write(sf.cmd_start())
        parser = sf.FrameParser()
        frames = []
        loop = asyncio.get_running_loop()
        end = loop.time() + 4.0
        while loop.time() < end:
            frames += parser.feed(port.read(65536))
            await asyncio.sleep(0.3)
        samples = [f for f in frames if isinstance(f, sf.SampleFrame)]
        port.close()
        assert sim.held_ticks > 0
        assert sim.serial_boards[0].port.bytes_dropped == 0 and parser.stats.as_dict()["frames_bad_checksum"] == 0
        seqs = np.array([f.seq for f in samples])
        assert len(seqs) > 100 and np.all(np.diff(seqs) == 1)  # nothing lost in between
        # the plant is not far ahead of what was read: a few buffers' worth, not the 4 s x 4000
        # x 3.125 samples it would have produced unheld
        assert sim._produced - len(seqs) < 0.2 * 4.0 * 4000 * 3.125


async def test_an_unplugged_board_s_port_is_gone_and_its_number_goes_to_no_other_pty():
    """A pulled cable: the host reads EOF and cannot open the path again, and until the simulator
    closes, no pty opened on this machine (another test's board, in another process) gets the
    number: a station trying its vanished port again finds nothing, never a stranger's board."""
    import os

    async with SimStation(n_serial=1, n_can=0, seed=5, speed=100) as sim:
        board = SerialBoard(sim.serial_ports[0])
        await board.open()
        path = sim.serial_ports[0]
        sim.board(0).disconnect()
        with pytest.raises(DriverError):
            for _ in range(20):
                await board.read_block(0.1)
        await board.close()
        assert not os.path.exists(path)
        with pytest.raises(DriverError):
            await SerialBoard(path).open()
        others = [os.openpty() for _ in range(8)]
        try:
            assert path not in {os.ttyname(s) for _, s in others}
        finally:
            for m, s in others:
                os.close(m)
                os.close(s)
