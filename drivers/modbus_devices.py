"""Modbus devices (design 3.3) over pymodbus async clients, TCP or RTU.

One `ModbusLink` per TCP endpoint or RS-485 line, shared by the devices on it (unit ids tell
them apart); requests are serialised on the link. Every failure (refused, timeout, exception
reply) becomes a DriverError naming the device, so the daemon can alarm on that device alone.
pymodbus 3.16: the unit is passed as `device_id=` (older 3.x used `slave=`).
"""

from __future__ import annotations

import asyncio
import inspect

from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient
from pymodbus.exceptions import ModbusException

from drivers.base import Chamber, DriverError, Fixture, LampRelay, Thermometer

# the keyword naming the unit changed across pymodbus 3.x releases
_UNIT_KW = (
    "device_id"
    if "device_id" in inspect.signature(AsyncModbusTcpClient.read_coils).parameters
    else "slave"
)


def _int16(reg: int) -> int:
    return reg - 0x10000 if reg & 0x8000 else reg


def _uint16(value: int) -> int:
    if not -0x8000 <= value <= 0x7FFF:
        raise ValueError(f"{value} does not fit an int16 register")
    return value & 0xFFFF


class ModbusLink:
    """A Modbus TCP endpoint (`host`, `port`) or an RTU line (`serial_port`, `baudrate`)."""

    def __init__(
        self,
        host: str | None = None,
        port: int = 502,
        *,
        serial_port: str | None = None,
        baudrate: int = 19200,
        timeout_s: float = 1.0,
        retries: int = 1,
    ) -> None:
        if (host is None) == (serial_port is None):
            raise ValueError("ModbusLink needs either host (TCP) or serial_port (RTU)")
        self.host = host
        self.port = port
        self.serial_port = serial_port
        self.baudrate = baudrate
        self.timeout_s = timeout_s
        self.retries = retries
        self._client: AsyncModbusTcpClient | AsyncModbusSerialClient | None = None
        self._lock: asyncio.Lock | None = None

    @property
    def where(self) -> str:
        return f"tcp://{self.host}:{self.port}" if self.host is not None else f"rtu:{self.serial_port}"

    def __repr__(self) -> str:
        return f"ModbusLink({self.where})"

    async def connect(self) -> None:
        if self._client is not None and self._client.connected:
            return
        if self._client is None:
            if self.host is not None:
                self._client = AsyncModbusTcpClient(
                    self.host, port=self.port, timeout=self.timeout_s, retries=self.retries,
                    reconnect_delay=0,
                )
            else:
                self._client = AsyncModbusSerialClient(
                    self.serial_port, baudrate=self.baudrate, timeout=self.timeout_s,  # type: ignore[arg-type]
                    retries=self.retries, reconnect_delay=0,
                )
        try:
            ok = await self._client.connect()
        except (OSError, ModbusException) as exc:
            ok = False
            reason = str(exc)
        else:
            reason = "connection refused or timed out"
        if not ok:
            self._client.close()
            self._client = None
            raise DriverError(f"Modbus device unreachable at {self.where}: {reason}")

    async def _call(self, what: str, unit: int, method: str, *args, **kwargs):
        if self._lock is None:
            self._lock = asyncio.Lock()
        async with self._lock:
            await self.connect()
            assert self._client is not None
            kwargs[_UNIT_KW] = unit
            try:
                rr = await getattr(self._client, method)(*args, **kwargs)
            except (ModbusException, OSError, asyncio.TimeoutError) as exc:
                self._client.close()
                self._client = None
                raise DriverError(f"Modbus {what} (unit {unit}) at {self.where} failed: {exc}") from exc
            if rr.isError():
                raise DriverError(f"Modbus {what} (unit {unit}) at {self.where}: exception reply {rr}")
            return rr

    async def read_coil(self, unit: int, address: int) -> bool:
        rr = await self._call(f"read coil {address}", unit, "read_coils", address, count=1)
        return bool(rr.bits[0])

    async def write_coil(self, unit: int, address: int, value: bool) -> None:
        await self._call(f"write coil {address}", unit, "write_coil", address, bool(value))

    async def read_holding(self, unit: int, address: int, count: int = 1) -> list[int]:
        rr = await self._call(f"read holding register {address}", unit, "read_holding_registers", address, count=count)
        return list(rr.registers)

    async def write_holding(self, unit: int, address: int, value: int) -> None:
        await self._call(f"write holding register {address}", unit, "write_register", address, int(value) & 0xFFFF)

    async def read_input(self, unit: int, address: int, count: int = 1) -> list[int]:
        rr = await self._call(f"read input register {address}", unit, "read_input_registers", address, count=count)
        return list(rr.registers)

    async def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None

    async def __aenter__(self) -> "ModbusLink":
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


class ModbusLampRelay(LampRelay):
    """IR lamp relay: coil 0 (1 on, 0 off). A failed write is retried before DriverError."""

    def __init__(self, link: ModbusLink, unit: int = 1, coil: int = 0, write_retries: int = 3) -> None:
        self.link, self.unit, self.coil, self.write_retries = link, unit, coil, max(1, write_retries)

    async def set_lamp(self, on: bool) -> None:
        err: DriverError | None = None
        for attempt in range(self.write_retries):
            try:
                await self.link.write_coil(self.unit, self.coil, on)
                return
            except DriverError as exc:
                err = exc
                await asyncio.sleep(0.05 * (attempt + 1))
        raise DriverError(f"lamp relay: cannot switch lamp {'on' if on else 'off'}: {err}")

    async def read_lamp(self) -> bool:
        return await self.link.read_coil(self.unit, self.coil)

    async def set_watchdog(self, seconds: int) -> None:
        """Holding register 0 of the relay = host watchdog time in s (design 3.3), read back."""
        value = max(0, min(0xFFFF, int(round(seconds))))
        await self.link.write_holding(self.unit, 0, value)
        got = (await self.link.read_holding(self.unit, 0))[0]
        if got != value:
            raise DriverError(f"lamp relay: host watchdog reads back {got} s, wrote {value} s")


class ModbusFixture(Fixture):
    """Motorised fixture: HR0 commanded position, IR0 reached position, IR1 = 1 while moving."""

    def __init__(self, link: ModbusLink, unit: int = 3) -> None:
        self.link, self.unit = link, unit

    async def move_to(self, position: int) -> None:
        await self.link.write_holding(self.unit, 0, _uint16(int(position)))

    async def position(self) -> int:
        return (await self.link.read_input(self.unit, 0, 1))[0]

    async def moving(self) -> bool:
        return bool((await self.link.read_input(self.unit, 1, 1))[0])

    async def wait_reached(self, position: int, timeout_s: float = 60.0, poll_s: float = 0.05) -> None:
        """Poll until the fixture stands still at `position`, else DriverError."""
        loop = asyncio.get_running_loop()
        end = loop.time() + timeout_s
        while True:
            regs = await self.link.read_input(self.unit, 0, 2)
            if regs[0] == position and not regs[1]:
                return
            if loop.time() > end:
                raise DriverError(f"fixture did not reach position {position} within {timeout_s:g} s")
            await asyncio.sleep(poll_s)


class ModbusThermometer(Thermometer):
    """Reference plate thermometer: IR0 int16 in 0.1 C."""

    def __init__(self, link: ModbusLink, unit: int = 2) -> None:
        self.link, self.unit = link, unit

    async def read_temp_c(self) -> float:
        return _int16((await self.link.read_input(self.unit, 0, 1))[0]) / 10.0


class ModbusChamber(Chamber):
    """Thermal chamber: HR0 set point, IR0 temperature, both int16 in 0.1 C."""

    def __init__(self, link: ModbusLink, unit: int = 4) -> None:
        self.link, self.unit = link, unit

    async def set_setpoint_c(self, setpoint_c: float) -> None:
        await self.link.write_holding(self.unit, 0, _uint16(int(round(setpoint_c * 10))))

    async def read_setpoint_c(self) -> float:
        return _int16((await self.link.read_holding(self.unit, 0, 1))[0]) / 10.0

    async def read_temp_c(self) -> float:
        return _int16((await self.link.read_input(self.unit, 0, 1))[0]) / 10.0
