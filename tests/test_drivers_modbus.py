"""Modbus drivers against the simulated devices on a pymodbus TCP server on 127.0.0.1."""

from dataclasses import dataclass

import pytest

from drivers.base import DriverError
from drivers.modbus_devices import ModbusChamber, ModbusFixture, ModbusLampRelay, ModbusLink, ModbusThermometer
from drivers.sim.modbus_server import FC_READ_COILS, FC_READ_HOLDING, FC_READ_INPUT, SimModbusServer, free_port


@dataclass
class Plant:
    """A stand-in for SimWorld's controls and plate temperature."""

    lamp_on: bool = False
    position: int = 0
    chamber_setpoint_c: float | None = None
    time_s: float = 0.0
    plate_temp_c: float = 24.96


@pytest.fixture
async def rig():
    plant = Plant()
    async with SimModbusServer(plant, move_time_s=4.0) as srv:
        link = ModbusLink("127.0.0.1", srv.port, timeout_s=1.0)
        yield plant, srv, link
        await link.close()


async def test_relay_coil_on_off(rig):
    plant, srv, link = rig
    relay = ModbusLampRelay(link)
    await relay.set_lamp(True)
    assert plant.lamp_on and await relay.read_lamp()
    assert await srv.datastore(1, FC_READ_COILS, 0) == [True]
    await relay.set_lamp(False)
    assert not plant.lamp_on and not await relay.read_lamp()
    assert await srv.datastore(1, FC_READ_COILS, 0) == [False]
    assert [w[:3] for w in srv.writes] == [(1, 5, 0), (1, 5, 0)]


async def test_fixture_move_takes_time(rig):
    plant, srv, link = rig
    fx = ModbusFixture(link)
    await fx.move_to(7)
    assert await srv.datastore(3, FC_READ_HOLDING, 0) == [7]
    assert await fx.moving() and await fx.position() == 0 and plant.position == 0
    plant.time_s = 3.9
    assert await fx.moving()
    plant.time_s = 4.0
    assert not await fx.moving() and await fx.position() == 7 and plant.position == 7
    await fx.wait_reached(7, timeout_s=1.0)
    assert await srv.datastore(3, FC_READ_INPUT, 0, 2) == [7, 0]


async def test_thermometer_and_chamber_scaling(rig):
    plant, srv, link = rig
    th, ch = ModbusThermometer(link), ModbusChamber(link)
    assert await th.read_temp_c() == 25.0  # 24.96 -> 250 (0.1 C)
    plant.plate_temp_c = -12.34
    assert await th.read_temp_c() == -12.3
    assert await srv.datastore(2, FC_READ_INPUT, 0) == [(-123) & 0xFFFF]
    await ch.set_setpoint_c(-40.0)
    assert plant.chamber_setpoint_c == -40.0
    assert await srv.datastore(4, FC_READ_HOLDING, 0) == [(-400) & 0xFFFF]
    assert await ch.read_setpoint_c() == -40.0
    plant.plate_temp_c = 85.07
    assert await ch.read_temp_c() == 85.1


async def test_unreachable_device_is_a_clear_error():
    link = ModbusLink("127.0.0.1", free_port(), timeout_s=0.5)
    with pytest.raises(DriverError, match=r"unreachable at tcp://127\.0\.0\.1:\d+"):
        await ModbusThermometer(link).read_temp_c()
    with pytest.raises(DriverError, match="cannot switch lamp off"):
        await ModbusLampRelay(link, write_retries=2).set_lamp(False)
    with pytest.raises(ValueError):
        ModbusLink()


async def test_missing_unit_is_a_clear_error(rig):
    plant, srv, link = rig
    with pytest.raises(DriverError, match=r"unit 9"):
        await ModbusThermometer(link, unit=9).read_temp_c()


async def test_station_tries_a_slow_relay_again_at_start_and_fails_clearly_when_it_never_answers():
    """A relay that starts listening 0.8 s after the station asks (a gateway still booting, a host
    busy for a second) is found on the second or third try; one that never answers is a one-line
    StationError naming the device after about 1.5 s of pauses."""
    import asyncio
    import time

    from contracts.types import StationError
    from station.config import ModbusDevice
    from station.daemon.instruments import Links

    plant = Plant()
    port = free_port()
    dev = ModbusDevice.model_validate({"tcp": {"host": "127.0.0.1", "port": port}, "unit": 1, "timeout_s": 0.3})

    async def late_server():
        await asyncio.sleep(0.8)
        srv = SimModbusServer(plant, port=port)
        await srv.start()
        return srv

    links = Links()
    started = asyncio.create_task(late_server())
    relay = await links.relay(dev)
    srv = await started
    try:
        await relay.set_lamp(True)
        assert plant.lamp_on
        await relay.set_lamp(False)
    finally:
        await links.close()
        await srv.stop()

    never = ModbusDevice.model_validate({"tcp": {"host": "127.0.0.1", "port": free_port()}, "unit": 1,
                                         "timeout_s": 0.3})
    t0 = time.monotonic()
    with pytest.raises(StationError, match=r"^lamp: Modbus device unreachable at tcp://127\.0\.0\.1:\d+"):
        await Links().relay(never)
    assert time.monotonic() - t0 >= 1.5
