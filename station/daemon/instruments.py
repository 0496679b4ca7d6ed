"""The station's links: Modbus instruments (lamp relay, fixture, thermometer, chamber) and the
board drivers of its slots, built from the config.

Links are shared where the hardware is: devices on one Modbus link (one TCP server or one RS-485
port) use one client, and every CAN slot on one adapter uses one bus (two python-can handles on one
adapter steal each other's bytes). This is the one place that knows which driver class serves
which kind of link; the rest of the daemon sees `BoardDriver` and the instrument interfaces.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from typing import TypeVar

from contracts.types import StationError
from drivers import modbus_devices as md
from drivers.base import BoardDriver, Chamber, DriverError, Fixture, LampRelay, Thermometer
from drivers.can_board import CanBoard, CanBus
from drivers.serial_board import SerialBoard
from station.config import ModbusDevice, SlotConfig

log = logging.getLogger(__name__)

# Pauses between tries of a Modbus instrument at start (wall seconds): three tries in about 1.5 s
# plus their timeouts, then the start fails with the last try's reason.
CONNECT_RETRY_DELAYS_S = (0.5, 1.0)

Device = TypeVar("Device")


class Links:
    """Every open link of one daemon, closed together when the station closes."""

    def __init__(self, speed: float = 1.0) -> None:
        self.speed = speed  # plant time per wall second (timing.speed): serial boards time silences with it
        self.modbus: dict[tuple[object, ...], md.ModbusLink] = {}
        self.can_buses: dict[tuple[str, str, int], CanBus] = {}

    async def relay(self, dev: ModbusDevice) -> LampRelay:
        """The lamp relay; reading its coil proves the unit answers."""
        return await self._device("lamp", dev, md.ModbusLampRelay, lambda r: r.read_lamp())

    async def fixture(self, dev: ModbusDevice) -> Fixture:
        return await self._device("fixture", dev, md.ModbusFixture, lambda f: f.position())

    async def thermometer(self, dev: ModbusDevice) -> Thermometer:
        return await self._device("thermometer", dev, md.ModbusThermometer, lambda t: t.read_temp_c())

    async def chamber(self, dev: ModbusDevice) -> Chamber:
        return await self._device("chamber", dev, md.ModbusChamber, lambda c: c.read_temp_c())

    async def _device(self, kind: str, dev: ModbusDevice, build: Callable[[md.ModbusLink, int], Device],
                      probe: Callable[[Device], Awaitable[object]]) -> Device:
        """The instrument `kind` on its (shared) Modbus link; one read proves the unit answers.
        A unit that is slow to answer at start (a gateway still booting, a host busy for a
        second) is tried again after 0.5 s and 1 s; an unreachable link or a silent unit after
        that is a StationError (one line)."""
        for delay_s in CONNECT_RETRY_DELAYS_S:
            try:
                return await self._device_once(kind, dev, build, probe)
            except StationError as exc:
                log.info("%s (trying again in %g s)", exc, delay_s)
                await asyncio.sleep(delay_s)
        return await self._device_once(kind, dev, build, probe)

    async def _device_once(self, kind: str, dev: ModbusDevice, build: Callable[[md.ModbusLink, int], Device],
                           probe: Callable[[Device], Awaitable[object]]) -> Device:
        key = dev.link_key
        link = self.modbus.get(key)
        if link is None:
            try:
                if dev.tcp is not None:
                    link = md.ModbusLink(host=dev.tcp.host, port=dev.tcp.port, timeout_s=dev.timeout_s)
                else:
                    assert dev.rtu is not None
                    link = md.ModbusLink(serial_port=dev.rtu.port, baudrate=dev.rtu.baudrate, timeout_s=dev.timeout_s)
                await link.connect()
            except (DriverError, OSError) as exc:
                raise StationError(f"{kind}: {exc}") from None
            self.modbus[key] = link
        device = build(link, dev.unit)
        try:
            await probe(device)
        except (DriverError, OSError, asyncio.TimeoutError) as exc:
            raise StationError(f"{kind}: no answer from {dev.link}: {exc}") from None
        return device

    async def board_driver(self, cfg: SlotConfig) -> BoardDriver:
        """A driver for the slot's board (not yet opened, except the shared CAN bus)."""
        if cfg.serial is not None:
            return SerialBoard(cfg.serial, speed=self.speed)
        c = cfg.can
        assert c is not None
        key = (c.interface, c.channel, c.bitrate)
        bus = self.can_buses.get(key)
        if bus is None:
            bus = CanBus(c.interface, c.channel, c.bitrate,
                         **({"sleep_after_open": 0} if c.interface == "slcan" else {}))
            # Registered before the first await: slots connect concurrently and must share one bus.
            self.can_buses[key] = bus
        try:
            await bus.open()  # idempotent and locked: the first slot opens, the rest wait
        except DriverError:
            raise
        except Exception as exc:
            raise DriverError(f"cannot open CAN {c.interface}:{c.channel}: {exc}") from exc
        return CanBoard(bus, c.node)

    async def close(self) -> None:
        for bus in self.can_buses.values():
            try:
                await bus.close()
            except Exception:  # noqa: BLE001 - closing: a bus that will not close is gone anyway
                pass
        for link in self.modbus.values():
            try:
                await link.close()
            except Exception:  # noqa: BLE001 - same
                pass
