"""Lamp safety (design 3.3): one LampGuard owns the lamp relay; nothing else writes the coil.

The lamp goes off on abort, on any batch end, on daemon shutdown, on over-temperature of any DUT or
of the plate (reference thermometer, if configured) and when it has been on longer than the
configured maximum. A trip latches: the lamp cannot be switched on again until the next batch
(`reset()`). A failed off-write is retried with backoff, raised as an Alarm event on every failure,
and retried in the background until it succeeds.

On-time in compressed time: the plant (real or simulated) runs `speed` times faster than the wall
clock, so lamp on-time is counted as the LARGER of (a) the batch's sample clock since the lamp went
on (what the boards have lived through) and (b) wall time since the lamp went on times the
configured speed. (a) is exact when samples flow; (b) still runs when they stop or lag. Taking the
maximum errs toward switching off early, never late.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable

from drivers.base import LampRelay, Thermometer
from station.events import Alarm, EventBus, LampChanged

log = logging.getLogger("station.safety")

DEFAULT_RETRY_DELAYS_S = (0.05, 0.1, 0.2, 0.5, 1.0, 2.0)


class LampTripped(Exception):
    """The lamp was asked to go on while a safety trip is latched."""


class LampGuard:
    def __init__(
        self,
        relay: LampRelay,
        bus: EventBus,
        *,
        max_on_s: float,
        max_dut_temp_c: float,
        max_plate_temp_c: float,
        speed: float = 1.0,
        thermometer: Thermometer | None = None,
        retry_delays_s: tuple[float, ...] = DEFAULT_RETRY_DELAYS_S,
        watch_period_s: float = 0.1,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.relay = relay
        self.bus = bus
        self.max_on_s = max_on_s
        self.max_dut_temp_c = max_dut_temp_c
        self.max_plate_temp_c = max_plate_temp_c
        self.speed = speed
        self.thermometer = thermometer
        self.retry_delays_s = retry_delays_s
        self.watch_period_s = watch_period_s
        self.clock = clock
        self.batch_id = 0
        self.is_on = False  # what we last commanded (and believe)
        self.trip_reason: str | None = None
        self.plate_temp_c: float | None = None
        self.off_failures = 0
        self._on_wall: float | None = None
        self._on_sample: float | None = None
        self._sample_now = 0.0
        self._lock = asyncio.Lock()
        self._watch_task: asyncio.Task | None = None
        self._retry_task: asyncio.Task | None = None
        self._trip_listeners: list[Callable[[str], None]] = []

    # ---------------------------------------------------------------- state
    def on_trip(self, callback: Callable[[str], None]) -> None:
        """Called (synchronously) with the reason when a trip latches: the supervisor fails the batch."""
        self._trip_listeners.append(callback)

    def note_sample_time(self, batch_sample_s: float) -> None:
        """The batch's sample clock (seconds of board time since the batch started)."""
        if batch_sample_s > self._sample_now:
            self._sample_now = batch_sample_s

    def on_time_s(self) -> float:
        if not self.is_on or self._on_wall is None:
            return 0.0
        wall = (self.clock() - self._on_wall) * self.speed
        sample = self._sample_now - (self._on_sample if self._on_sample is not None else self._sample_now)
        return max(wall, sample)

    def reset(self, batch_id: int) -> None:
        """A new batch: clear a latched trip (the cause is re-checked on every sample)."""
        self.batch_id = batch_id
        self.trip_reason = None
        self._sample_now = 0.0

    # ---------------------------------------------------------------- commands
    async def set_lamp(self, on: bool, reason: str) -> None:
        if not on:
            await self.off(reason)
            return
        if self.trip_reason is not None:
            raise LampTripped(f"lamp trip latched: {self.trip_reason}")
        async with self._lock:
            await self.relay.set_lamp(True)
            if not self.is_on:
                self._on_wall = self.clock()
                self._on_sample = self._sample_now
            self.is_on = True
        self.bus.publish(LampChanged(self.batch_id, on=True, reason=reason))
        log.info("lamp on (%s)", reason)

    async def off(self, reason: str) -> bool:
        """Switch off, retrying with backoff. Always writes (the coil may differ from our belief)."""
        was_on = self.is_on
        self.is_on = False  # stop counting and refuse to believe it is on from now
        self._on_wall = None
        async with self._lock:
            ok = await self._write_off_with_retries(reason)
        if ok:
            if was_on:
                self.bus.publish(LampChanged(self.batch_id, on=False, reason=reason))
            log.info("lamp off (%s)", reason)
        elif self._retry_task is None or self._retry_task.done():
            self._retry_task = asyncio.get_running_loop().create_task(self._retry_forever(reason))
        return ok

    async def _write_off_with_retries(self, reason: str) -> bool:
        for attempt, delay in enumerate((0.0, *self.retry_delays_s)):
            if delay:
                await asyncio.sleep(delay)
            try:
                await self.relay.set_lamp(False)
                return True
            except Exception as exc:  # DriverError, timeouts, a dropped connection: all the same here
                self.off_failures += 1
                text = f"lamp OFF write failed (attempt {attempt + 1}, {reason}): {exc}"
                log.error(text)
                self.bus.publish(Alarm(self.batch_id, text=text, severity="critical"))
        return False

    async def _retry_forever(self, reason: str) -> None:
        delay = self.retry_delays_s[-1] if self.retry_delays_s else 1.0
        while True:
            await asyncio.sleep(delay)
            async with self._lock:
                if await self._write_off_with_retries(reason + ", background retry"):
                    self.bus.publish(Alarm(self.batch_id, text="lamp OFF write succeeded after retries", severity="info"))
                    self.bus.publish(LampChanged(self.batch_id, on=False, reason=reason))
                    return

    def trip(self, reason: str) -> None:
        """Latch a safety trip and switch the lamp off now (from sync code, e.g. a sample callback)."""
        first = self.trip_reason is None
        if first:
            self.trip_reason = reason
            log.error("lamp safety trip: %s", reason)
            self.bus.publish(Alarm(self.batch_id, text=f"safety trip: {reason}", severity="critical"))
        asyncio.get_running_loop().create_task(self.off(f"safety: {reason}"))
        if first:
            for cb in self._trip_listeners:
                cb(reason)

    # ---------------------------------------------------------------- checks
    def check_dut_temp(self, slot: str, temp_c: float) -> bool:
        """True if it tripped. Called with each block's hottest temperature (lamp on or not)."""
        if temp_c > self.max_dut_temp_c:
            self.trip(f"DUT {slot} at {temp_c:.1f} C > max {self.max_dut_temp_c:g} C")
            return True
        return False

    def check_plate_temp(self, temp_c: float) -> bool:
        self.plate_temp_c = temp_c
        if temp_c > self.max_plate_temp_c:
            self.trip(f"plate at {temp_c:.1f} C > max {self.max_plate_temp_c:g} C")
            return True
        return False

    def check_on_time(self) -> bool:
        on_s = self.on_time_s()
        if self.is_on and on_s > self.max_on_s:
            self.trip(f"lamp on for {on_s:.0f} s > max {self.max_on_s:g} s")
            return True
        return False

    async def _watch(self) -> None:
        thermo_fail = 0
        while True:
            self.check_on_time()
            if self.thermometer is not None:
                try:
                    self.check_plate_temp(await self.thermometer.read_temp_c())
                    thermo_fail = 0
                except Exception as exc:
                    thermo_fail += 1
                    if thermo_fail == 3 and self.is_on:
                        # Blind to the plate: do not keep heating it.
                        self.trip(f"reference thermometer unreadable: {exc}")
            await asyncio.sleep(self.watch_period_s)

    def start(self) -> None:
        if self._watch_task is None:
            self._watch_task = asyncio.get_running_loop().create_task(self._watch())

    async def close(self, reason: str = "daemon shutdown") -> bool:
        if self._watch_task is not None:
            self._watch_task.cancel()
            try:
                await self._watch_task
            except (asyncio.CancelledError, Exception):
                pass
            self._watch_task = None
        ok = await self.off(reason)
        if self._retry_task is not None and not self._retry_task.done():
            self._retry_task.cancel()
        return ok
