"""Simulated Modbus devices (design 3.3) in one pymodbus TCP server on 127.0.0.1.

Units: 1 lamp relay (coil 0; HR0 host watchdog in s: no request to the relay for that long
switches the coil off by itself, in wall time like the real module), 2 reference thermometer (IR0, 0.1 C), 3 fixture (HR0 commanded,
IR0 reached, IR1 moving), 4 thermal chamber (HR0 set point, IR0 temperature, 0.1 C). Writes act
on the plant at once (lamp_on, chamber_setpoint_c); a fixture move takes `move_time_s` of
simulated time, during which IR1 = 1 and the plant keeps its old position. Input registers are
filled from the plant on every read, so they are never stale. The plant is anything with the
SimWorld attributes (`lamp_on`, `position`, `chamber_setpoint_c`, `time_s`, `plate_temp_c`).
"""

from __future__ import annotations

import asyncio
import math
import socket
import time
from typing import Any, Protocol

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

UNIT_RELAY = 1
UNIT_THERMOMETER = 2
UNIT_FIXTURE = 3
UNIT_CHAMBER = 4

FC_READ_COILS = 1
FC_READ_HOLDING = 3
FC_READ_INPUT = 4
FC_WRITE_COIL = 5
FC_WRITE_REGISTER = 6
FC_WRITE_COILS = 15
FC_WRITE_REGISTERS = 16


class Plant(Protocol):
    lamp_on: bool
    position: int
    chamber_setpoint_c: float | None

    @property
    def time_s(self) -> float: ...

    @property
    def plate_temp_c(self) -> float: ...


def _reg(temp_c: float) -> int:
    return int(math.floor(max(-3276.8, min(3276.7, temp_c)) * 10 + 0.5)) & 0xFFFF


def _int16(reg: int) -> int:
    return reg - 0x10000 if reg & 0x8000 else reg


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def _device(unit: int, action, *, coils: int = 0, hr: int = 0, ir: int = 0) -> SimDevice:
    def block(n: int, bits: bool) -> list[SimData]:
        if bits:  # bit blocks must be BITS even when unused (16 coils per register)
            return [SimData(0, count=16, values=False, datatype=DataType.BITS)]
        if not n:
            return [SimData(0, count=1, datatype=DataType.INVALID)]
        return [SimData(0, count=n, values=0, datatype=DataType.REGISTERS)]

    return SimDevice(
        unit,
        simdata=(block(coils, True), block(0, True), block(hr, False), block(ir, False)),
        action=action,
    )


class SimModbusServer:
    """The four devices on one Modbus TCP server; `port` is chosen free unless given."""

    def __init__(self, plant: Plant, host: str = "127.0.0.1", port: int = 0, *, move_time_s: float = 4.0) -> None:
        self.plant = plant
        self.host = host
        self.port = port or free_port(host)
        self.move_time_s = move_time_s
        self.commanded_position = int(plant.position)
        self.reached_position = int(plant.position)
        self.moving = False
        self._move_end_s = 0.0
        # a fixture that re-homes/verifies: every move command reports moving for at least this many
        # sample seconds, even to where it already is (tests: a slow first positioning)
        self.settle_s = 0.0
        self.writes: list[tuple[int, int, int, Any]] = []  # (unit, fc, address, values) log
        self.server: ModbusTcpServer | None = None
        # Relay host watchdog (design 3.3): wall seconds, 0 = off.
        self.watchdog_s = 0
        self.watchdog_trips = 0
        self.last_relay_request = time.monotonic()
        self.relay_offline = False  # fault injection: the relay answers nothing (tests)
        self.fixture_offline = False  # fault injection: the fixture answers nothing
        # fault injection: the fixture reports "reached, not moving" this many sample seconds before
        # the plate really gets there (a limit switch hit early, a controller that acks the command)
        self.reports_early_s = 0.0
        self._watchdog_task: asyncio.Task | None = None

    # ---- plant side ------------------------------------------------------------------------
    def update(self) -> None:
        """Finish a fixture move whose time is up (called by the clock and on every request)."""
        t = self.plant.time_s
        if self.moving and self.reports_early_s > 0 and t >= self._move_end_s - self.reports_early_s:
            self.reached_position = self.commanded_position  # says "there" while the plate still moves
        if self.moving and t >= self._move_end_s:
            self.moving = False
            self.reached_position = self.commanded_position
            self.plant.position = self.commanded_position

    @property
    def reports_moving(self) -> bool:
        """What input register 1 says: a fixture that reports early says 'not moving' already."""
        return self.moving and not (self.reports_early_s > 0 and self.reached_position == self.commanded_position)

    def _start_move(self, position: int) -> None:
        self.commanded_position = position
        same = position == self.reached_position and not self.moving
        if same and not self.settle_s:
            return
        self.moving = True
        self._move_end_s = self.plant.time_s + max(0.0 if same else self.move_time_s, self.settle_s)

    # ---- pymodbus actions (run in the server's event loop) ---------------------------------
    async def _relay(self, fc, start, address, count, regs, values):
        if self.relay_offline:
            return ExcCodes.GATEWAY_NO_RESPONSE
        self.last_relay_request = time.monotonic()
        if fc in (FC_WRITE_REGISTER, FC_WRITE_REGISTERS) and values is not None:
            self.writes.append((UNIT_RELAY, fc, address, list(values)))
            if address == 0:
                self.watchdog_s = int(values[0])
            return None
        if fc == FC_READ_HOLDING:
            regs[0] = self.watchdog_s & 0xFFFF
            return None
        if values is not None and fc in (FC_WRITE_COIL, FC_WRITE_COILS):
            self.writes.append((UNIT_RELAY, fc, address, list(values)))
            if address <= 0 < address + len(values):
                self.plant.lamp_on = bool(values[0 - address])
        elif fc == FC_READ_COILS:
            regs[0] = (regs[0] & ~1) | int(bool(self.plant.lamp_on))
        return None

    async def _thermometer(self, fc, start, address, count, regs, values):
        if fc == FC_READ_INPUT:
            regs[0] = _reg(self.plant.plate_temp_c)
        return None

    async def _fixture(self, fc, start, address, count, regs, values):
        if self.fixture_offline:
            return ExcCodes.GATEWAY_NO_RESPONSE
        if values is not None and fc in (FC_WRITE_REGISTER, FC_WRITE_REGISTERS):
            self.writes.append((UNIT_FIXTURE, fc, address, list(values)))
            if address == 0:
                self._start_move(int(values[0]))
        self.update()
        if fc == FC_READ_INPUT:
            regs[0] = self.reached_position & 0xFFFF
            regs[1] = int(self.reports_moving)
        return None

    async def _chamber(self, fc, start, address, count, regs, values):
        if values is not None and fc in (FC_WRITE_REGISTER, FC_WRITE_REGISTERS):
            self.writes.append((UNIT_CHAMBER, fc, address, list(values)))
            if address == 0:
                self.plant.chamber_setpoint_c = _int16(int(values[0])) / 10.0
        if fc == FC_READ_INPUT:
            regs[0] = _reg(self.plant.plate_temp_c)
        return None

    async def _absent(self, fc, start, address, count, regs, values):
        """Any other unit: answer like a TCP gateway whose target does not respond."""
        return ExcCodes.GATEWAY_NO_RESPONSE

    # ---- lifecycle -------------------------------------------------------------------------
    async def start(self) -> None:
        devices = [
            _device(0, self._absent, coils=1, hr=1, ir=2),
            _device(UNIT_RELAY, self._relay, coils=1, hr=1),
            _device(UNIT_THERMOMETER, self._thermometer, ir=1),
            _device(UNIT_FIXTURE, self._fixture, hr=1, ir=2),
            _device(UNIT_CHAMBER, self._chamber, hr=1, ir=1),
        ]
        self.server = ModbusTcpServer(devices, address=(self.host, self.port))
        await self.server.serve_forever(background=True)
        self._watchdog_task = asyncio.get_running_loop().create_task(self._watchdog())

    async def _watchdog(self, period_s: float = 0.05) -> None:
        """The relay module's own safe state: no request for watchdog_s -> coil off."""
        while True:
            await asyncio.sleep(period_s)
            if (self.watchdog_s and self.plant.lamp_on
                    and time.monotonic() - self.last_relay_request > self.watchdog_s):
                self.plant.lamp_on = False
                self.watchdog_trips += 1

    async def stop(self) -> None:
        if self._watchdog_task is not None:
            self._watchdog_task.cancel()
            self._watchdog_task = None
        if self.server is not None:
            await self.server.shutdown()
            self.server = None

    async def datastore(self, unit: int, fc: int, address: int, count: int = 1) -> list:
        """Read the server's own datastore (what a client would get), for tests and the UI."""
        assert self.server is not None
        return list(await self.server.context.async_getValues(unit, fc, address, count))

    async def __aenter__(self) -> "SimModbusServer":
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()
