"""Instrument interfaces: one per kind of instrument, in the spirit of OpenHTF plugs.

Real drivers (serial, CAN, Modbus TCP/RTU) implement these. Simulated hardware does not get its
own implementation of these interfaces: it sits on the far side of a real link (pseudo-terminal,
slcan adapter on a pseudo-terminal, pymodbus server on 127.0.0.1), so the very same drivers run
against it. Drivers turn bytes into SampleBlocks and commands into bytes; they know nothing of
calibration.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass

from station.types import Identity, SampleBlock


class DriverError(Exception):
    """A link failed (port vanished, device unreachable, no reply). Faults one slot or device."""


@dataclass
class LinkStats:
    """Counters every board link keeps; corrupt input is counted and skipped, never fatal."""

    frames_ok: int = 0
    frames_bad_checksum: int = 0
    frames_malformed: int = 0  # short line, unknown type, unparsable field
    bytes_skipped: int = 0  # garbage between frames
    samples_lost: int = 0  # sequence gaps
    errors_reported: int = 0  # `E,...` frames from the board

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


class BoardDriver(abc.ABC):
    """One DUT board. All methods are coroutines that never block the event loop."""

    stats: LinkStats

    @abc.abstractmethod
    async def open(self) -> None: ...

    @abc.abstractmethod
    async def identify(self, timeout_s: float = 2.0) -> Identity: ...

    @abc.abstractmethod
    async def start(self) -> None: ...

    @abc.abstractmethod
    async def stop(self) -> None: ...

    @abc.abstractmethod
    async def set_odr(self, odr_hz: float) -> None: ...

    @abc.abstractmethod
    async def read_block(self, timeout_s: float = 1.0) -> SampleBlock:
        """Samples received since the last call (possibly empty after timeout_s).

        Raises DriverError when the link is gone (port closed, bus down).
        """

    @abc.abstractmethod
    async def close(self) -> None: ...


class LampRelay(abc.ABC):
    @abc.abstractmethod
    async def set_lamp(self, on: bool) -> None: ...

    @abc.abstractmethod
    async def read_lamp(self) -> bool: ...


class Fixture(abc.ABC):
    @abc.abstractmethod
    async def move_to(self, position: int) -> None: ...

    @abc.abstractmethod
    async def position(self) -> int: ...

    @abc.abstractmethod
    async def moving(self) -> bool: ...


class Thermometer(abc.ABC):
    @abc.abstractmethod
    async def read_temp_c(self) -> float: ...


class Chamber(abc.ABC):
    @abc.abstractmethod
    async def set_setpoint_c(self, setpoint_c: float) -> None: ...

    @abc.abstractmethod
    async def read_temp_c(self) -> float: ...
