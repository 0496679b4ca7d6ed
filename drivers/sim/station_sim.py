"""SimStation: a whole simulated station on real links, in compressed time.

    async with SimStation(n_serial=2, n_can=2, seed=1, speed=50) as sim:
        board = SerialBoard(sim.serial_ports[0])              # real pty
        bus = CanBus(**sim.can_bus_args)                       # slcan adapter on a pty
        relay = ModbusLampRelay(ModbusLink(sim.modbus_host, sim.modbus_port))

Time: one clock task owns the SimWorld. Every tick it computes how many samples the world is
behind `speed` x (wall time since start) x ODR, advances it by exactly that many samples (in
pieces, and split at the instant a fixture move ends) and hands every board its DUT's samples.
The world's noise streams and thermal chain are per sample, so the samples (and therefore all
results) depend only on sample time, never on speed or tick size; only *when* a command lands
(in sample time) depends on the wall clock, as with real hardware.
"""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import Callable
from typing import Any

from drivers.sim.firmware_boards import FirmwareBoard
from drivers.sim.modbus_server import SimModbusServer
from drivers.sim.physics import DutTruth, draw_population
from drivers.sim.serial_pty import SimSerialBoard
from drivers.sim.slcan_pty import SimCanBoard, SimCanHub, SlcanPtyAdapter, VirtualCanBridge
from drivers.sim.world import EnvConfig, SimWorld, WorldChunk

MAX_CHUNK_SAMPLES = 2048
_virtual_ids = itertools.count(1)


class SimStation:
    """N serial + M CAN simulated boards, the Modbus devices, and the clock (see module doc).

    Boards are ordered serial first, then CAN (same order as `truths` and world DUT index).
    CAN boards get node ids 1..M. `can_interface` "slcan" (adapter on a pty, default) or
    "virtual" (python-can in-process bus; then `slcan_port` is None).
    """

    def __init__(
        self,
        n_serial: int = 0,
        n_can: int = 0,
        seed: int = 0,
        speed: float = 1.0,
        effects: tuple[str, ...] | list[str] = (),
        odr_hz: float | None = None,
        *,
        sensor: str = "LIS3DSH",
        env: EnvConfig | None = None,
        truths: list[DutTruth] | None = None,
        can_interface: str = "slcan",
        tick_s: float = 0.05,
        move_time_s: float = 4.0,
        world: Any = None,
        firmware: dict[int, str] | None = None,
    ) -> None:
        if n_can > 127:
            raise ValueError("at most 127 CAN boards on one bus")
        self.n_serial = int(n_serial)
        self.n_can = int(n_can)
        self.seed = seed
        self.speed = float(speed)
        self.tick_s = tick_s
        if world is not None:  # another plant (drivers/sim/replay.py: recorded samples), no physics truth
            if world.n_duts != self.n_serial + self.n_can:
                raise ValueError("the world must have n_serial + n_can DUTs")
            self.truths: list[DutTruth] = []
            self.world = world
        else:
            if truths is None:
                truths = draw_population(self.n_serial + self.n_can, seed, sensor=sensor, effects=tuple(effects))
            if len(truths) != self.n_serial + self.n_can:
                raise ValueError("truths must have n_serial + n_can entries")
            self.truths = list(truths)
            self.world = SimWorld(self.truths, env=env, odr_hz=odr_hz, seed=seed)
        # DUT index -> "host" | "qemu": that board runs the C firmware (drivers/sim/firmware_boards.py)
        self.firmware = dict(firmware or {})
        if any(i >= self.n_serial + self.n_can or i < 0 for i in self.firmware):
            raise ValueError("firmware board index out of range")
        self.can_interface = can_interface
        self.move_time_s = move_time_s
        self.serial_boards: list[SimSerialBoard] = []
        self.can_boards: list[SimCanBoard] = []
        self.can_node_ids: list[int] = []
        self.serial_ports: list[str] = []
        self.slcan_port: str | None = None
        self.can_channel: str | None = None
        self.modbus: SimModbusServer | None = None
        self.modbus_host = "127.0.0.1"
        self.modbus_port = 0
        self._hub = SimCanHub()
        self._adapter: SlcanPtyAdapter | VirtualCanBridge | None = None
        self._clock: asyncio.Task | None = None
        self._listeners: list[Callable[[WorldChunk], None]] = []
        self._wall0 = 0.0
        self._sim0_samples = 0
        self._produced = 0
        self.paused = False
        self.backpressure_bytes = 32 * 1024  # a live reader this far behind holds the plant clock
        self.held_ticks = 0
        self.max_hold_s = 2.0  # wall seconds; well under any stall timeout
        self.max_catchup_ticks = 2.0  # one advance covers at most this many ticks of plant time
        self.capped_ticks = 0
        # pace() -> True holds the plant for as long as it says so (no max_hold_s): a replay's
        # recorded plant waits for the daemon's processing, not only for its byte readers
        self.pace: Callable[[], bool] | None = None

    # ---- lifecycle -------------------------------------------------------------------------
    async def __aenter__(self) -> "SimStation":
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def start(self) -> None:
        w = self.world
        for i in range(self.n_serial):
            b = self._make_serial_board(i)
            b.start()
            self.serial_boards.append(b)
            self.serial_ports.append(b.path)
        for j in range(self.n_can):
            node = j + 1
            self.can_boards.append(self._hub.add(self._make_can_board(j, node)))
            self.can_node_ids.append(node)
        if self.n_can:
            if self.can_interface == "slcan":
                self._adapter = SlcanPtyAdapter(self._hub)
                self.slcan_port = self._adapter.path
                self.can_channel = self._adapter.path
            elif self.can_interface == "virtual":
                self.can_channel = f"simstation-{next(_virtual_ids)}"
                self._adapter = VirtualCanBridge(self._hub, self.can_channel)
            else:
                raise ValueError(f"can_interface must be 'slcan' or 'virtual', not {self.can_interface!r}")
            self._adapter.start()
        try:
            await asyncio.gather(*(b.wait_ready() for b in self._firmware_boards()))
        except BaseException:
            await self.close()
            raise
        self.serial_ports = [b.path for b in self.serial_boards]  # a QEMU board's pty is known once it booted
        self.modbus = SimModbusServer(w, self.modbus_host, move_time_s=self.move_time_s)
        await self.modbus.start()
        self.modbus_port = self.modbus.port
        loop = asyncio.get_running_loop()
        self._wall0 = loop.time()
        self._clock = asyncio.create_task(self._run_clock(), name="simstation-clock")

    def _make_serial_board(self, i: int) -> SimSerialBoard:
        if i in self.firmware:
            return FirmwareBoard(self.world.identity(i), self.firmware[i])  # type: ignore[return-value]
        return SimSerialBoard(self.world.identity(i))

    def _make_can_board(self, j: int, node: int) -> SimCanBoard:
        i = self.n_serial + j
        if i in self.firmware:
            board = FirmwareBoard(self.world.identity(i), self.firmware[i], node_id=node)
            board.start()
            return board  # type: ignore[return-value]
        return SimCanBoard(node, self.world.identity(i))

    def _firmware_boards(self) -> list[FirmwareBoard]:
        return [b for b in [*self.serial_boards, *self.can_boards] if isinstance(b, FirmwareBoard)]

    async def close(self) -> None:
        if self._clock is not None:
            self._clock.cancel()
            try:
                await self._clock
            except (asyncio.CancelledError, Exception):  # noqa: BLE001
                pass
            self._clock = None
        if self.modbus is not None:
            await self.modbus.stop()
        for b in self.serial_boards:
            b.close()
        for b in self._firmware_boards():
            b.close()
        if self._adapter is not None:
            self._adapter.close()
            self._adapter = None

    # ---- accessors -------------------------------------------------------------------------
    @property
    def can_bus_args(self) -> dict[str, Any]:
        """Keyword arguments for drivers.can_board.CanBus to reach the simulated CAN boards."""
        if self.can_channel is None:
            raise ValueError("this SimStation has no CAN boards")
        if self.can_interface == "slcan":
            return {"interface": "slcan", "channel": self.can_channel, "bitrate": 500_000, "sleep_after_open": 0}
        return {"interface": "virtual", "channel": self.can_channel, "bitrate": None}

    def board(self, i: int) -> SimSerialBoard | SimCanBoard:
        """Board i (serial first, then CAN) with its fault injection methods."""
        if i < self.n_serial:
            return self.serial_boards[i]
        return self.can_boards[i - self.n_serial]

    def power_cycle(self, i: int, off_s: float = 0.0) -> None:
        """Board i loses power and restarts: its RAM state is gone, its NVM (calibration) is kept,
        and the world's self-heating of that DUT starts over."""
        self.board(i).power_cycle()
        self.world.power_cycle(i, off_s)

    def subscribe(self, callback: Callable[[WorldChunk], None]) -> None:
        """callback(chunk) after every world advance (simulator truth for tests and plots)."""
        self._listeners.append(callback)

    def disconnect_can_adapter(self) -> None:
        """Pull the slcan adapter: the whole CAN bus vanishes for the driver."""
        if self._adapter is not None:
            self._adapter.close()
            self._adapter = None

    # ---- the clock -------------------------------------------------------------------------
    def _due_samples(self, now: float) -> int:
        return int((now - self._wall0) * self.speed * self.world.odr_hz) + self._sim0_samples

    def set_speed(self, speed: float) -> None:
        """Change the compression factor without a jump in simulated time."""
        now = asyncio.get_running_loop().time()
        self._sim0_samples = self._produced
        self._wall0 = now
        self.speed = float(speed)

    def advance(self, n: int) -> None:
        """Advance the world n samples now and deliver them (also usable with speed=0)."""
        while n > 0:
            step = min(n, MAX_CHUNK_SAMPLES)
            mod = self.modbus
            if mod is not None:
                mod.update()
                if mod.moving:  # stop exactly at the end of a fixture move
                    left = mod._move_end_s - self.world.time_s
                    k = max(1, int(-(-left * self.world.odr_hz // 1)))
                    step = min(step, k)
            chunk = self.world.advance(step)
            self._deliver(chunk)
            n -= step
            self._produced += step
        if self.modbus is not None:
            self.modbus.update()

    def _deliver(self, chunk: WorldChunk) -> None:
        for i, b in enumerate(self.serial_boards):
            b.feed(chunk.time_s, chunk.acc_counts[i], chunk.temp_counts[i])
        for j, b in enumerate(self.can_boards):
            i = self.n_serial + j
            b.feed(chunk.time_s, chunk.acc_counts[i], chunk.temp_counts[i])
        for cb in self._listeners:
            cb(chunk)

    async def _run_clock(self) -> None:
        loop = asyncio.get_running_loop()
        last_advance = loop.time()
        while True:
            await asyncio.sleep(self.tick_s)
            if self.paused:
                self._sim0_samples = self._produced
                self._wall0 = loop.time()
                continue
            now = loop.time()
            if self.pace is not None and self.pace():
                self._sim0_samples = self._produced
                self._wall0 = now
                self.held_ticks += 1
                continue
            if self._backlog(now) > self.backpressure_bytes and now - last_advance < self.max_hold_s:
                # The daemon is behind (a loaded machine): the plant waits for it instead of running
                # ahead, so a compressed-time run gives the same physics whatever the CPU load. The
                # plant still moves a tick every max_hold_s, so no board ever looks stalled.
                self._sim0_samples = self._produced
                self._wall0 = now
                self.held_ticks += 1
                continue
            due = self._due_samples(now)
            cap = max(1, int(self.max_catchup_ticks * self.tick_s * self.speed * self.world.odr_hz))
            if due - self._produced > cap:
                # The loop was held up (a loaded machine): the plant does not jump ahead by the whole
                # hold-up in one piece (at x3000, 0.3 s is 900 s of sample time, more than a static
                # step's timeout, all of it delivered before the daemon's next look); it slows down
                # instead, as it does for a reader that is behind.
                self._sim0_samples = self._produced + cap
                self._wall0 = now
                due = self._produced + cap
                self.capped_ticks += 1
            if due > self._produced:
                self.advance(due - self._produced)
            last_advance = now

    def _backlog(self, now: float) -> int:
        ports = [b.port for b in self.serial_boards if isinstance(b, SimSerialBoard)]
        if self._adapter is not None and hasattr(self._adapter, "port"):
            ports.append(self._adapter.port)
        return max([p.backlog_bytes(now) for p in ports] + [b.backlog_bytes(now) for b in self._firmware_boards()],
                   default=0)
