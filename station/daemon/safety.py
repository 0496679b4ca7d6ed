"""Lamp safety (design 3.3): one LampGuard owns the lamp relay; nothing else writes the coil.

The lamp goes off on abort, on any batch end, on daemon shutdown, on over-temperature of any DUT or
of the plate (reference thermometer, if configured) and when it has been on longer than the
configured maximum. A trip latches: the lamp cannot be switched on again until the next batch
(`reset()`). A failed off-write is retried with backoff, raised as an Alarm event on every failure,
and retried in the background until it succeeds.

On-time in compressed time: lamp on-time is the batch's sample clock since the lamp went on (what
the boards have lived through: exact while samples flow, even when the daemon reads them late),
PLUS wall time times the configured speed since the sample clock last moved (so a stalled stream
cannot stop the count). It once was max(sample clock, wall x speed): when a loaded daemon lagged
behind a simulated plant, wall x speed ran thousands of plant seconds ahead of what the boards had
lived through and tripped whole batches (the simulator now waits for a lagging daemon instead).
At speed 1 on real hardware both counts agree within the link's buffering.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable

from drivers.base import LampRelay, Thermometer
from station.aio import cancel_and_wait
from contracts.events import Alarm, EventBus, LampChanged

log = logging.getLogger(__name__)

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
        watchdog_s: float = 0.0,
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
        self._sample_wall: float | None = None  # wall time the sample clock last moved
        self._lock = asyncio.Lock()
        self._watch_task: asyncio.Task[None] | None = None
        self._retry_task: asyncio.Task[None] | None = None
        self._trip_listeners: list[Callable[[str], None]] = []
        # Relay supervision: the host watchdog (design 3.3) and what the coil really is.
        self.watchdog_s = watchdog_s
        self.watchdog_armed = False
        self.relay_error: str | None = None  # set at the first failed read/write: state unknown
        self.relay_failures = 0
        self._write_seq = 0
        self._last_ping = -1e9

    @property
    def state(self) -> str:
        """'on', 'off' or 'unknown' (the relay did not answer the last read or write)."""
        if self.relay_error is not None:
            return "unknown"
        return "on" if self.is_on else "off"

    @property
    def ping_period_s(self) -> float:
        """How often the relay is read: at least every third of the watchdog time (design 3.3)."""
        return min(1.0, self.watchdog_s / 3.0) if self.watchdog_s > 0 else 1.0

    # ---------------------------------------------------------------- state
    def on_trip(self, callback: Callable[[str], None]) -> None:
        """Called (synchronously) with the reason when a trip latches: the supervisor fails the batch."""
        self._trip_listeners.append(callback)

    def note_sample_time(self, batch_sample_s: float) -> None:
        """The batch's sample clock (seconds of board time since the batch started)."""
        if batch_sample_s > self._sample_now:
            self._sample_now = batch_sample_s
            self._sample_wall = self.clock()

    def on_time_s(self) -> float:
        if not self.is_on or self._on_wall is None:
            return 0.0
        sample = self._sample_now - (self._on_sample if self._on_sample is not None else self._sample_now)
        since = self._on_wall if self._sample_wall is None else max(self._on_wall, self._sample_wall)
        return sample + (self.clock() - since) * self.speed

    def reset(self, batch_id: int, sample_now_s: float = 0.0) -> None:
        """A new batch: clear a latched trip (the cause is re-checked on every sample).
        `sample_now_s`: the batch's sample clock now. A resumed batch's clock starts where its
        stored samples end (an hour in, say); counted from 0, a lamp switched on before its first
        new sample would read that whole hour as on-time at that sample and trip."""
        self.batch_id = batch_id
        self.trip_reason = None
        self._sample_now = sample_now_s
        self._sample_wall = None

    # ---------------------------------------------------------------- commands
    async def set_lamp(self, on: bool, reason: str) -> None:
        if not on:
            await self.off(reason)
            return
        if self.trip_reason is not None:
            raise LampTripped(f"lamp trip latched: {self.trip_reason}")
        self._write_seq += 1
        async with self._lock:
            try:
                await self.relay.set_lamp(True)
            except Exception as exc:
                self._relay_failed(f"lamp ON write failed: {exc}")
                raise
            self._relay_ok()
            if not self.is_on:
                self._on_wall = self.clock()
                self._on_sample = self._sample_now
            self.is_on = True
        self.bus.publish(LampChanged(self.batch_id, on=True, reason=reason))
        log.info("lamp on (%s)", reason)

    async def off(self, reason: str) -> bool:
        """Switch off, retrying with backoff. Always writes (the coil may differ from our belief)."""
        was_on = self.is_on
        self._write_seq += 1
        self.is_on = False  # stop counting and refuse to believe it is on from now
        self._on_wall = None
        async with self._lock:
            ok = await self._write_off_with_retries(reason)
        if ok:
            if was_on:
                self.bus.publish(LampChanged(self.batch_id, on=False, reason=reason))
            log.info("lamp off (%s)", reason)
            return ok
        if self._retry_task is None or self._retry_task.done():
            self._retry_task = asyncio.get_running_loop().create_task(self._retry_forever(reason))
        # the lamp may still be on: whatever runs cannot go on (it keeps being retried meanwhile)
        self._latch(f"lamp relay did not take the OFF command, lamp state unknown: {self.relay_error}")
        return ok

    async def _write_off_with_retries(self, reason: str) -> bool:
        for attempt, delay in enumerate((0.0, *self.retry_delays_s)):
            if delay:
                await asyncio.sleep(delay)
            try:
                await self.relay.set_lamp(False)
                self._relay_ok()
                return True
            except Exception as exc:  # DriverError, timeouts, a dropped connection: all the same here
                self.off_failures += 1
                self.relay_error = f"lamp OFF write failed: {exc}"
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
        self._latch(reason)
        asyncio.get_running_loop().create_task(self.off(f"safety: {reason}"))

    def _latch(self, reason: str) -> bool:
        """Latch a trip (the first reason wins) and tell the listeners (the batch fails)."""
        first = self.trip_reason is None
        if first:
            self.trip_reason = reason
            log.error("lamp safety trip: %s", reason)
            self.bus.publish(Alarm(self.batch_id, text=f"safety trip: {reason}", severity="critical"))
            for cb in self._trip_listeners:
                cb(reason)
        return first

    # ---------------------------------------------------------------- relay supervision
    async def arm_watchdog(self) -> bool:
        """Set the relay's host watchdog, so a daemon that dies cannot leave the lamp on for longer."""
        if self.watchdog_s <= 0:
            return False
        try:
            await self.relay.set_watchdog(int(round(self.watchdog_s)))
        except Exception as exc:
            text = (f"lamp relay host watchdog could not be set ({exc}): if the daemon dies, the lamp "
                    "stays on until it restarts")
            log.error(text)
            self.bus.publish(Alarm(self.batch_id, text=text, severity="warning"))
            return False
        self.watchdog_armed = True
        log.info("lamp relay host watchdog armed: %g s", self.watchdog_s)
        return True

    def _relay_ok(self) -> None:
        if self.relay_error is not None:
            self.bus.publish(Alarm(self.batch_id, text="lamp relay answers again", severity="info"))
        self.relay_error = None
        self.relay_failures = 0

    def _relay_failed(self, text: str) -> None:
        first = self.relay_error is None
        self.relay_error = text
        self.relay_failures += 1
        if first:  # alarm at the first failure, not after a timeout
            msg = f"lamp relay not answering, lamp state unknown: {text}"
            log.error(msg)
            self.bus.publish(Alarm(self.batch_id, text=msg, severity="critical"))

    async def check_relay(self) -> None:
        """Read the coil (this also refreshes the host watchdog) and compare it with what we commanded."""
        seq = self._write_seq
        async with self._lock:
            try:
                coil = await asyncio.wait_for(self.relay.read_lamp(), 2.0)
            except Exception as exc:
                self._relay_failed(f"reading the lamp coil failed: {exc}")
                if self.relay_failures >= 3 and self.trip_reason is None:
                    # on or off: a relay that does not answer cannot be trusted to hold the lamp off
                    # (a stuck coil, a manual switch): the batch cannot go on (design 3.3)
                    self.trip(f"lamp relay unreachable, lamp state unknown"
                              f"{' while the lamp is on' if self.is_on else ''}: {exc}")
                return
            self._relay_ok()
        if seq != self._write_seq:
            return  # a write went in meanwhile: the read says nothing about it
        if coil and not self.is_on:
            text = "lamp coil found ON while the station commanded OFF: switching it off"
            log.error(text)
            self.bus.publish(Alarm(self.batch_id, text=text, severity="critical"))
            await self.off("coil found on")
        elif not coil and self.is_on:
            self.trip("lamp coil found OFF while the station commanded ON (relay host watchdog or manual switch)")

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
            now = time.monotonic()
            if now - self._last_ping >= self.ping_period_s:
                self._last_ping = now
                await self.check_relay()
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
        task, self._watch_task = self._watch_task, None
        if not await cancel_and_wait(task):
            log.error("lamp guard: the watch task did not stop within 5 s; switching the lamp off anyway")
        ok = await self.off(reason)
        if self._retry_task is not None and not self._retry_task.done():
            self._retry_task.cancel()
        return ok
