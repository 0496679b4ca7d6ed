"""The station daemon's supervisor: the `Station` facade the web and the CLI use.

It owns the links (one driver per slot, shared CAN buses and Modbus links), the LampGuard, the
event bus and the database; it runs one Sequencer per batch and, per DUT, a pump task that reads
sample blocks, feeds that DUT's StreamingCalibrator in batches, keeps the full block list for the
offline fit and publishes SamplesReceived / SegmentLogged / SlotStateChanged / DutResult.

Faults stay in their slot: a board that disappears (DriverError), stops streaming (no samples for
`timing.stall_timeout_s` wall seconds) or sends only garbage (LinkStats: bad frames, no good ones)
faults its own DUT run; the batch goes on with the others.

Facade methods are plain (sync) methods to be called from the daemon's event loop (the web app runs
in the same loop); they return at once and the batch runs in its own task.
Unknown batch -> KeyError; a bad request -> ValueError.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from drivers.base import BoardDriver, Chamber, DriverError, Fixture, LampRelay, Thermometer
from station.config import ModbusDevice, SlotConfig, StationConfig
from station.decisions import moment as judging
from contracts.events import Alarm, DutResult, EventBus, SamplesReceived, SegmentLogged, SlotStateChanged
from contracts.positions import GRAVITY_DIRECTIONS
from station.profiles import Profile, all_profiles
from station.daemon.safety import LampGuard
from station.daemon.sequencer import TERMINAL, DutRun, Sequencer, annotate_segment, wall_text
from contracts.types import SampleBlock, StationError

log = logging.getLogger("station.daemon.supervisor")


# ------------------------------------------------------------------------------------- database
class MemoryDb:
    """Stand-in for db.Database when no database is wanted (unit tests, `--no-db`): ids only."""

    url = "memory://"

    def __init__(self) -> None:
        self._batch_ids = itertools.count(1)
        self._run_ids = itertools.count(1)
        self.batches: dict[int, dict] = {}
        self.runs: dict[int, dict] = {}

    def upgrade(self) -> str:
        return "memory"

    def create_batch(self, profile: str, operator: str, config_snapshot: dict, replay_of: str | None = None) -> int:
        i = next(self._batch_ids)
        self.batches[i] = {"profile": profile, "operator": operator, "state": "created"}
        return i

    def set_batch_state(self, batch_id: int, state: str, step_index: int | None = None, **_: Any) -> None:
        self.batches[batch_id]["state"] = state

    def create_run(self, batch_id: int, slot: str, serial: str, sensor: str = "", identity: dict | None = None) -> int:
        i = next(self._run_ids)
        self.runs[i] = {"batch_id": batch_id, "slot": slot, "serial": serial, "state": "identified"}
        return i

    def set_run_state(self, run_id: int, state: str, fault_reason: str = "") -> None:
        self.runs[run_id].update(state=state, fault_reason=fault_reason)

    def dispose(self) -> None:
        pass


def open_database(url: str | None, station: str = "") -> Any:
    """db.Database(url) upgraded to head, or MemoryDb for url None / 'memory://'."""
    if url is None or url.startswith("memory"):
        return MemoryDb()
    try:
        from db import Database  # type: ignore[attr-defined]
    except ImportError:
        try:
            from db.database import Database
        except ImportError:
            log.warning("db package not available: batch ids are kept in memory only")
            return MemoryDb()
    try:
        if url.startswith("sqlite:///"):
            from pathlib import Path

            path = Path(url[len("sqlite:///"):])
            if str(path) not in ("", ":memory:"):
                path.parent.mkdir(parents=True, exist_ok=True)
        database = Database(url, station=station)
        database.upgrade()
    except StationError:
        raise
    except Exception as exc:  # a bad path, an unwritable file, a server that is down: one line
        reason = getattr(exc, "orig", None) or exc
        raise StationError(f"database {url}: {type(reason).__name__}: {reason}".rstrip()) from None
    return database


# ------------------------------------------------------------------------------------- slots
@dataclass
class SlotRuntime:
    cfg: SlotConfig
    driver: BoardDriver | None = None
    state: str = "disconnected"  # disconnected, identified, busy, faulted
    identity: Any = None
    fault_reason: str = ""
    batch_id: int | None = None

    def status(self) -> dict:
        return {
            "slot": self.cfg.name,
            "name": self.cfg.name,
            "link": self.cfg.link,
            "state": self.state,
            "serial": self.identity.serial if self.identity else None,
            "sensor": self.identity.sensor if self.identity else None,
            "batch_id": self.batch_id,
            "fault_reason": self.fault_reason,
            "link_stats": self.driver.stats.as_dict() if self.driver is not None and hasattr(self.driver, "stats") else {},
        }


def _default_calibrator_factory():
    from station.science.streaming import StreamingCalibrator, StreamingConfig

    return StreamingCalibrator(StreamingConfig())


@dataclass
class _BatchRt:
    seq: Sequencer
    pumps: dict[str, asyncio.Task] = field(default_factory=dict)
    releasing: bool = False  # pumps end at their next turn (a cancel alone can be swallowed)


class Station:
    """The daemon. `await start()` connects the instruments and slots; `await close()` makes it safe."""

    def __init__(
        self,
        config: StationConfig,
        *,
        db: Any = None,
        bus: EventBus | None = None,
        calibrator_factory: Callable[[], Any] | None = None,
        analyse_results: bool = True,
    ) -> None:
        self.config = config
        self.bus = bus or EventBus()
        self.db = db if db is not None else MemoryDb()
        self.writer: Any = None
        self._writer_task: asyncio.Task | None = None
        self._profiles: dict[str, Profile] = all_profiles(config)
        self.slots: dict[str, SlotRuntime] = {s.name: SlotRuntime(s) for s in config.slots}
        self.batches: dict[int, _BatchRt] = {}
        self.lamp: LampGuard | None = None
        self.fixture: Fixture | None = None
        self.chamber: Chamber | None = None
        self.thermometer: Thermometer | None = None
        self.fixture_timeout_s = config.timing.fixture_timeout_s
        self.calibrator_factory = calibrator_factory or _default_calibrator_factory
        self.analyse_results = analyse_results
        self._modbus_links: dict[tuple, Any] = {}
        self._can_buses: dict[tuple, Any] = {}
        self._started = False
        self._closed = False

    # ================================================================== lifecycle
    async def start(self, connect_slots: bool = True) -> None:
        """Connect Modbus instruments (the lamp relay is mandatory) and identify every slot.

        An unreachable instrument is a StationError (one line); a slot that cannot be opened or
        identified is only marked faulted (the other slots still work).
        """
        cfg = self.config
        relay = await self._modbus_device("lamp", cfg.lamp)
        thermometer = await self._modbus_device("thermometer", cfg.thermometer) if cfg.thermometer else None
        self.fixture = await self._modbus_device("fixture", cfg.fixture) if cfg.fixture else None
        self.chamber = await self._modbus_device("chamber", cfg.chamber) if cfg.chamber else None
        self.thermometer = thermometer
        self.lamp = LampGuard(
            relay,
            self.bus,
            max_on_s=cfg.limits.lamp_max_on_s,
            max_dut_temp_c=cfg.limits.max_dut_temp_c,
            max_plate_temp_c=cfg.limits.max_plate_temp_c,
            speed=cfg.timing.speed,
            thermometer=thermometer,
            watchdog_s=cfg.limits.relay_watchdog_s,
        )
        self.lamp.on_trip(self._on_lamp_trip)
        # Safe state first: whatever the last process left, the lamp is off.
        if not await self.lamp.off("daemon start"):
            raise StationError(f"lamp relay ({cfg.lamp.link}) did not accept the OFF command")
        await self.lamp.arm_watchdog()
        self.lamp.start()
        self._start_writer()
        self._started = True
        if connect_slots:
            await asyncio.gather(*(self._connect_slot(rt) for rt in self.slots.values()))

    async def close(self, reason: str = "daemon shutdown") -> None:
        """Interrupt running batches, switch the lamp off, close every link. Idempotent."""
        if self._closed:
            return
        self._closed = True
        for rt in list(self.batches.values()):
            rt.seq.stop("interrupted", reason)
        if self.lamp is not None:  # lamp off first, before anything that can take time
            await self.lamp.off(reason)
        for rt in list(self.batches.values()):
            if rt.seq.task is not None:
                try:
                    await asyncio.wait_for(rt.seq.done.wait(), 10.0)
                except asyncio.TimeoutError:
                    log.error("batch %d did not end within 10 s", rt.seq.batch_id)
        if self.lamp is not None:
            await self.lamp.close(reason)
        for slot in self.slots.values():
            await self._close_driver(slot)
        for bus in self._can_buses.values():
            try:
                await bus.close()
            except Exception:
                pass
        for link in self._modbus_links.values():
            try:
                res = link.close()
                if asyncio.iscoroutine(res):
                    await res
            except Exception:
                pass
        await self._stop_writer()

    async def __aenter__(self) -> "Station":
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # ================================================================== database writer
    def _start_writer(self) -> None:
        if isinstance(self.db, MemoryDb):
            return
        try:
            from db.writer import DbWriter
        except ImportError:
            log.warning("db.writer not available: samples/segments/results are not stored")
            return
        loop = asyncio.get_running_loop()
        self.writer = DbWriter(self.db, on_storage=lambda reason: loop.call_soon_threadsafe(self._on_storage, reason))
        q = self.bus.subscribe(maxsize=100000, drop=False)

        async def forward() -> None:
            while True:
                ev = await q.get()
                try:
                    self.writer.submit(ev)
                except Exception:
                    log.exception("db writer refused %s", type(ev).__name__)

        self._writer_queue = q
        self._writer_task = asyncio.get_running_loop().create_task(forward(), name="db-forward")

    async def _stop_writer(self) -> None:
        if self._writer_task is not None:
            q = self._writer_queue
            while not q.empty():  # hand over what is still queued
                try:
                    self.writer.submit(q.get_nowait())
                except Exception:
                    break
            self._writer_task.cancel()
            try:
                await self._writer_task
            except (asyncio.CancelledError, Exception):
                pass
            self.bus.unsubscribe(q)
        if self.writer is not None:
            try:
                await asyncio.to_thread(self.writer.close)
            except Exception:
                log.exception("closing db writer")
            self.writer = None

    def _on_storage(self, reason: str | None) -> None:
        """The writer's storage failed (reason) or recovered (None): tell the operator at once."""
        if reason is not None:
            text = (f"database write failing: {reason}. Results are held in memory and retried; "
                    "free disk space / check the database. A batch ending now is not reported finished.")
            self.bus.publish(Alarm(0, text=text, severity="critical"))
        else:
            self.bus.publish(Alarm(0, text="database writes work again: held results stored", severity="info"))

    def storage_status(self) -> str:
        """'ok', 'none' (no database) or 'error: ...' while the writer cannot store."""
        w = self.writer
        if w is None:
            return "none" if isinstance(self.db, MemoryDb) else "ok"
        if w.failing is not None:
            return f"error: writes failing: {w.failing} ({w.backlog} events waiting)"
        return "ok"

    async def _stored_before_end(self, timeout_s: float = 15.0) -> str | None:
        """Wait until everything of the batch so far is committed. None if stored, else why not."""
        w = self.writer
        if w is None:
            return None
        q = self._writer_queue
        for _ in range(int(timeout_s / 0.01)):
            if q.empty() or w.failing is not None:
                break
            await asyncio.sleep(0.01)
        if w.failing is None and await asyncio.to_thread(w.flush, timeout_s):
            return None
        return w.failing or f"database writes did not complete within {timeout_s:g} s"

    async def flush_db(self) -> None:
        """Wait until every event published so far is committed (tests, --once summary)."""
        if self.writer is None:
            return
        q = self._writer_queue
        while not q.empty():
            await asyncio.sleep(0.01)
        await asyncio.to_thread(self.writer.flush)

    # ================================================================== links
    async def _modbus_device(self, kind: str, dev: ModbusDevice | None) -> Any:
        from drivers import modbus_devices as md

        key = dev.link_key
        link = self._modbus_links.get(key)
        if link is None:
            try:
                if dev.tcp is not None:
                    link = md.ModbusLink(host=dev.tcp.host, port=dev.tcp.port, timeout_s=dev.timeout_s)
                else:
                    link = md.ModbusLink(serial_port=dev.rtu.port, baudrate=dev.rtu.baudrate, timeout_s=dev.timeout_s)
                await link.connect()
            except (DriverError, OSError) as exc:
                raise StationError(f"{kind}: {exc}") from None
            self._modbus_links[key] = link
        cls = {
            "lamp": md.ModbusLampRelay,
            "fixture": md.ModbusFixture,
            "thermometer": md.ModbusThermometer,
            "chamber": md.ModbusChamber,
        }[kind]
        device = cls(link, unit=dev.unit)
        try:  # one read proves the unit answers
            if kind == "lamp":
                await device.read_lamp()
            elif kind == "fixture":
                await device.position()
            else:
                await device.read_temp_c()
        except (DriverError, OSError, asyncio.TimeoutError) as exc:
            raise StationError(f"{kind}: no answer from {dev.link}: {exc}") from None
        return device

    async def _make_driver(self, cfg: SlotConfig) -> BoardDriver:
        if cfg.serial is not None:
            from drivers.serial_board import SerialBoard

            return SerialBoard(cfg.serial)
        from drivers.can_board import CanBoard, CanBus

        c = cfg.can
        assert c is not None
        key = (c.interface, c.channel, c.bitrate)
        bus = self._can_buses.get(key)
        if bus is None:
            kwargs: dict[str, Any] = {"sleep_after_open": 0} if c.interface == "slcan" else {}
            bus = CanBus(c.interface, c.channel, c.bitrate, **kwargs)
            # Registered before the first await: slots connect concurrently and must share
            # one bus per channel (two python-can handles on one adapter steal each other's bytes).
            self._can_buses[key] = bus
        try:
            await bus.open()  # idempotent and locked: the first slot opens, the rest wait
        except DriverError:
            raise
        except Exception as exc:
            raise DriverError(f"cannot open CAN {c.interface}:{c.channel}: {exc}") from exc
        return CanBoard(bus, c.node)

    async def _connect_slot(self, rt: SlotRuntime, batch_id: int = 0) -> bool:
        """Open (if needed) and identify one slot. Returns False (slot faulted) on a link problem."""
        try:
            if rt.driver is None:
                rt.driver = await self._make_driver(rt.cfg)
                await rt.driver.open()
            try:
                await rt.driver.stop()  # a board left streaming by a previous process
            except DriverError:
                pass
            rt.identity = await rt.driver.identify(self.config.timing.identify_timeout_s)
        except (DriverError, OSError) as exc:
            rt.state, rt.fault_reason = "faulted", f"{rt.cfg.link}: {exc}"
            await self._close_driver(rt)
            log.warning("slot %s: %s", rt.cfg.name, rt.fault_reason)
            if not batch_id:
                self.bus.publish(SlotStateChanged(0, slot=rt.cfg.name, serial=None, state="faulted",
                                                  fault_reason=rt.fault_reason))
            return False
        rt.state, rt.fault_reason = "identified", ""
        if not batch_id:  # inside a batch, connect_duts publishes once the run exists
            self.bus.publish(SlotStateChanged(0, slot=rt.cfg.name, serial=rt.identity.serial, state="identified"))
        return True

    async def _close_driver(self, rt: SlotRuntime) -> None:
        if rt.driver is not None:
            drv, rt.driver = rt.driver, None
            try:
                await asyncio.wait_for(drv.close(), 2.0)
            except Exception:
                pass

    # ================================================================== facade
    def profiles(self) -> list[str]:
        return list(self._profiles)

    def profiles_info(self) -> list[dict]:
        """What GET /api/profiles lists: name, description, analysis kind, step count (the page
        shows the description so a newcomer can choose; 'none' means no calibration result)."""
        return [{"name": p.name, "description": p.description or None, "analysis": p.analysis,
                 "n_steps": len(p.steps), "builtin": p.builtin, "program_verify": p.program_step is not None}
                for p in self._profiles.values()]

    def profile(self, name: str) -> dict:
        if name not in self._profiles:
            raise KeyError(f"unknown profile {name!r}")
        return self._profiles[name].to_json()

    def start_batch(self, profile: str, slots: list[str] | None = None, operator: str = "") -> int:
        if not self._started or self._closed:
            raise ValueError("the station is not running")
        if profile not in self._profiles:
            raise ValueError(f"unknown profile {profile!r} (known: {', '.join(self._profiles)})")
        prof = self._profiles[profile]
        if any(s.chamber_setpoint_c is not None for s in prof.steps) and self.chamber is None:
            raise ValueError(f"profile {profile!r} needs a thermal chamber and none is configured")
        if any(rt.seq.state not in TERMINAL for rt in self.batches.values()):
            raise ValueError("a batch is already running on this station (one plate, one lamp)")
        names = list(self.slots) if slots is None else list(slots)
        if slots is not None:
            unknown = [n for n in names if n not in self.slots]
            if unknown:
                raise ValueError(f"unknown slot(s): {', '.join(unknown)}")
            if len(set(names)) != len(names):
                raise ValueError("a slot is listed twice")
        if not names:
            raise ValueError("no slots selected")
        batch_id = int(self.db.create_batch(profile, operator, self.config.snapshot(),
                                            replay_of=self.config.replay_of))
        duts = [DutRun(slot=n, link=self.slots[n].cfg.link) for n in names]
        seq = Sequencer(batch_id, prof, duts, self, self.bus, operator=operator)
        for n in names:
            self.slots[n].batch_id = batch_id
        self.batches[batch_id] = _BatchRt(seq)
        self.lamp.reset(batch_id)  # type: ignore[union-attr]
        seq.start()
        log.info("batch %d: profile %s on %d slot(s) by %r", batch_id, profile, len(names), operator)
        return batch_id

    def resume_batch(self, batch_id: int, operator: str = "") -> int:
        """Resume an interrupted batch (crash, restart) at the step after its last completed one.

        Each DUT run that was interrupted goes on as the SAME run: its stored sample stream is
        replayed through a fresh calibrator (pure science: same state as before the crash), the
        live stream is appended after it, and the board must answer with the same serial.
        Faulted or finished runs stay as they are. Returns the batch id.
        """
        if not self._started or self._closed:
            raise ValueError("the station is not running")
        if isinstance(self.db, MemoryDb):
            raise ValueError("resume needs a database (nothing was stored)")
        if any(rt.seq.state not in TERMINAL for rt in self.batches.values()):
            raise ValueError("a batch is already running on this station (one plate, one lamp)")
        rp = self.db.resume_point(int(batch_id))  # KeyError for an unknown batch
        if rp.state != "interrupted":
            raise ValueError(f"batch {batch_id} is {rp.state}: only an interrupted batch can be resumed")
        prof = self._profiles.get(rp.profile)
        if prof is None:
            raise ValueError(f"batch {batch_id} ran profile {rp.profile!r}, which this config does not have")
        if any(s.chamber_setpoint_c is not None for s in prof.steps) and self.chamber is None:
            raise ValueError(f"profile {rp.profile!r} needs a thermal chamber and none is configured")
        runs = [r for r in rp.runs if r.state == "interrupted"]
        missing = [r.slot for r in runs if r.slot not in self.slots]
        if missing:
            raise ValueError(f"batch {batch_id}: slot(s) {', '.join(missing)} are not in this config")
        if not runs:
            raise ValueError(f"batch {batch_id} has no interrupted DUT run to resume")
        duts = [self._restored_dut(r, rp) for r in runs]
        seq = Sequencer(batch_id, prof, duts, self, self.bus, operator=operator or rp.operator,
                        start_step=min(rp.next_step, len(prof.steps)))
        for d in duts:
            self.slots[d.slot].batch_id = batch_id
        self.batches[batch_id] = _BatchRt(seq)
        self.lamp.reset(batch_id)  # type: ignore[union-attr]
        seq.start()
        log.info("batch %d: resumed at step %d of %s with %d DUT(s)", batch_id, rp.next_step, rp.profile, len(duts))
        return batch_id

    def _restored_dut(self, r: Any, rp: Any) -> DutRun:
        """A DutRun carrying what the stored run already holds: samples, calibrator state, segments."""
        from db.export import run_log
        from db.repository import segments_of_run

        d = DutRun(slot=r.slot, link=self.slots[r.slot].cfg.link, run_id=r.run_id, expected_serial=r.serial)
        for step, windows in (rp.step_windows or {}).items():
            w = windows.get(r.slot)
            if w and None not in w:
                d.step_windows[int(step)] = (float(w[0]), float(w[1]))
        stored = run_log(self.db, r.run_id)
        if len(stored) == 0:
            return d
        block = SampleBlock(stored.time_s, stored.acc_g, stored.temp_c)
        d.blocks, d.block_steps = [block], [max(rp.next_step - 1, 0)]
        d.t0, d.last_t, d.resume_t = float(block.time_s[0]), float(block.time_s[-1]), float(block.time_s[-1])
        d.n_samples = len(block)
        d.calibrator = self.calibrator_factory()
        replayed = d.calibrator.update_batch(block.time_s, block.acc_g, block.temp_c)
        steps = {g["index"]: (g["step_index"], g["position"]) for g in (segments_of_run(self.db, r.run_id) or [])}
        for seg in replayed:
            if seg.index in steps:
                step, pos = steps[seg.index]
                d.segments.append(annotate_segment(seg, pos))
                d.segment_steps.append(step)
            else:
                # Logged from samples whose segment event the crash did not let commit: it belongs
                # to the interrupted step (a completed step's segments commit before its end) and
                # to the position the stored samples were taken at.
                k = min(int(np.searchsorted(stored.time_s, seg.t_end_s)), len(stored) - 1)
                pos = int(stored.position[k]) if stored.position is not None and stored.position[k] >= 0 else None
                d.unstored_segments.append((annotate_segment(seg, pos), rp.next_step))
        d.hold_calibrator = True  # fed again once the resumed step is logging (see _ingest)
        return d

    def _batch(self, batch_id: int) -> _BatchRt:
        try:
            return self.batches[int(batch_id)]
        except (KeyError, ValueError, TypeError):
            raise KeyError(f"unknown batch {batch_id}") from None

    def abort(self, batch_id: int, reason: str = "", by: str = "operator") -> None:
        """End a batch for an operator. The batch's error says who and when ("aborted by Ana at
        2026-11-23 14:02:05 UTC", then the reason if one was given): ended_by / ended_at."""
        rt = self._batch(batch_id)
        if rt.seq.state in TERMINAL:
            raise ValueError(f"batch {batch_id} has already ended ({rt.seq.state})")
        text = f"aborted by {by} at {wall_text(time.time())}"
        if reason and reason != "operator":
            text += f": {reason}"
        rt.seq.stop("aborted", text, by=by)

    def prompt(self, batch_id: int) -> dict | None:
        return self._batch(batch_id).seq.prompt

    def answer_prompt(self, batch_id: int, prompt_id: int, answer: str = "done", by: str | None = None) -> None:
        self._batch(batch_id).seq.answer_prompt(prompt_id, answer, by=by)

    def batch_status(self, batch_id: int) -> dict:
        rt = self._batch(batch_id)
        st = rt.seq.status()
        drivers = {n: self.slots[n].driver for n in self.slots}
        for s in st["slots"]:
            drv = drivers.get(s["slot"])
            if drv is not None and hasattr(drv, "stats"):
                s["link_stats"] = drv.stats.as_dict()
        st.update(judging.batch_extras(self, rt.seq))
        return st

    def batch_marker(self, batch_id: int) -> tuple:
        """Cheap fingerprint of a batch's state (cache validation): changes with every
        transition, step and DUT state change."""
        seq = self._batch(batch_id).seq
        return (seq.state, len(seq.history), seq.step_index, tuple(d.state for d in seq.duts))

    def lamp_status(self) -> dict:
        """What the page and health show of the lamp: commanded, real state (or unknown), watchdog."""
        lamp = self.lamp
        if lamp is None:
            return {"state": "unknown", "relay_error": "station not started"}
        return {"state": lamp.state, "on_commanded": lamp.is_on, "relay_error": lamp.relay_error,
                "watchdog_s": lamp.watchdog_s if lamp.watchdog_armed else 0, "trip": lamp.trip_reason}

    def judge_interrupted(self, batch_ids: list[int], reason: str = "station restarted") -> int:
        """Error verdicts for the runs of batches a killed daemon left running (judging.py)."""
        return judging.judge_interrupted_runs(self, list(batch_ids or []), reason)

    def batch_ids(self) -> list[int]:
        return sorted(self.batches)

    def slots_status(self) -> list[dict]:
        out = []
        for rt in self.slots.values():
            st = rt.status()
            if rt.batch_id is not None and rt.batch_id in self.batches:
                seq = self.batches[rt.batch_id].seq
                for d in seq.duts:
                    if d.slot == rt.cfg.name:
                        st["run_state"] = d.state
                        st["run_id"] = d.run_id
                        if seq.state not in TERMINAL:
                            st["state"] = "busy" if d.live else "faulted"
                            st["fault_reason"] = d.fault_reason or st["fault_reason"]
            out.append(st)
        return out

    def samples_taken(self, batch_id: int) -> dict[str, int]:
        """Samples each live DUT of the batch has taken in so far, by slot (cheap: a replay paces
        its recorded plant by it, station/replay/runner.py)."""
        return {d.slot: d.n_samples for d in self._batch(batch_id).seq.duts if d.live}

    async def wait_batch(self, batch_id: int, timeout_s: float | None = None) -> dict:
        rt = self._batch(batch_id)
        await asyncio.wait_for(rt.seq.done.wait(), timeout_s)
        return self.batch_status(batch_id)

    # ================================================================== sequencer hooks
    def _on_lamp_trip(self, reason: str) -> None:
        for rt in self.batches.values():
            if rt.seq.state not in TERMINAL:
                rt.seq.stop("failed", f"safety trip: {reason}")

    async def connect_duts(self, seq: Sequencer) -> None:
        rt = self.batches[seq.batch_id]

        async def one(d: DutRun) -> None:
            slot = self.slots[d.slot]
            d.state = "connecting"
            self._publish_dut(seq, d)
            if not await self._connect_slot(slot, seq.batch_id):
                self.fault_dut(seq, d, slot.fault_reason)
                return
            slot.state = "busy"
            d.identity = slot.identity
            ident = d.identity
            if d.expected_serial is not None and ident.serial != d.expected_serial:
                self.fault_dut(seq, d, f"{d.link}: found serial {ident.serial}, the interrupted run was "
                                       f"{d.expected_serial} (board swapped?)")
                return
            d.state = "identified"
            if d.run_id is None:
                d.run_id = int(self.db.create_run(seq.batch_id, d.slot, ident.serial, ident.sensor,
                                                  _identity_dict(ident)))
            if self.writer is not None:
                self.writer.bind_run(seq.batch_id, d.slot, d.run_id)
            self._publish_dut(seq, d)
            for seg, step in d.unstored_segments:
                d.segments.append(seg)
                d.segment_steps.append(step)
                self.bus.publish(SegmentLogged(seq.batch_id, slot=d.slot, serial=ident.serial, step_index=step,
                                               segment=seg))
            d.unstored_segments.clear()
            if d.calibrator is None:
                d.calibrator = self.calibrator_factory()
            # Samples still held from the board's previous run (read after its last block until
            # its STOP took effect) would open this run with that run's tail and a gap of the time
            # between the batches (issue 9: the plot's first sample).
            discard = getattr(slot.driver, "discard_held", None)  # test doubles may not have it
            dropped = discard() if discard is not None else 0
            if dropped:
                log.info("batch %d slot %s: %d samples of the previous run discarded", seq.batch_id, d.slot, dropped)
            try:
                await slot.driver.start()  # type: ignore[union-attr]
            except DriverError as exc:
                self.fault_dut(seq, d, f"{d.link}: start failed: {exc}")
                return
            d.state = "running"
            d.last_wall = time.monotonic()
            self._publish_dut(seq, d)
            rt.pumps[d.slot] = asyncio.get_running_loop().create_task(self._pump(seq, d), name=f"pump-{d.slot}")

        await asyncio.gather(*(one(d) for d in seq.duts))

    async def release_duts(self, seq: Sequencer) -> None:
        rt = self.batches[seq.batch_id]
        rt.releasing = True
        for t in rt.pumps.values():
            t.cancel()
        if rt.pumps:
            # Python 3.11's asyncio.wait_for (inside read_block) can swallow a cancel that lands as
            # its wait completes: the pump then ends on `releasing` at its next read instead.
            _, late = await asyncio.wait(rt.pumps.values(), timeout=10.0)
            for t in late:
                log.error("batch %d: pump %s did not stop within 10 s", seq.batch_id, t.get_name())
        rt.pumps.clear()
        finished = (seq.ending or seq.state) == "finished"
        # A DUT whose data the database did not take is not 'done' (nor is the batch 'finished').
        why = await self._stored_before_end() if finished else None
        if why is not None:
            seq.storage_error = why

        async def stop_one(d: DutRun) -> None:
            slot = self.slots[d.slot]
            if slot.driver is not None:
                try:
                    await asyncio.wait_for(slot.driver.stop(), 3.0)
                except Exception:
                    pass
                d.link_stats = slot.driver.stats.as_dict() if hasattr(slot.driver, "stats") else {}
            if d.live:
                if why is not None:
                    d.state, d.fault_reason = "faulted", f"results not stored: {why}"
                elif finished:
                    d.state = "done"
                else:  # every end carries a reason: the batch's own
                    d.state = "interrupted"
                    d.fault_reason = f"batch {seq.ending or seq.state}: {seq.error or 'no reason given'}"
                self._publish_dut(seq, d)
            if slot.state == "busy":
                slot.state = "identified"

        await asyncio.gather(*(stop_one(d) for d in seq.duts))
        judging.judge_final(self, seq)  # the verdict's moment: every run, once, from its final state

    def fault_dut(self, seq: Sequencer, d: DutRun, reason: str) -> None:
        if not d.live:
            return
        d.state, d.fault_reason = "faulted", reason
        log.warning("batch %d slot %s faulted: %s", seq.batch_id, d.slot, reason)
        self._publish_dut(seq, d)
        rt = self.batches.get(seq.batch_id)
        if rt is not None:
            pump = rt.pumps.get(d.slot)
            if pump is not None and pump is not asyncio.current_task():
                pump.cancel()
        slot = self.slots[d.slot]
        slot.state, slot.fault_reason = "faulted", reason
        seq.notify()

    def _publish_dut(self, seq: Sequencer, d: DutRun) -> None:
        if isinstance(self.db, MemoryDb) and d.run_id is not None:
            self.db.set_run_state(d.run_id, d.state, d.fault_reason)
        self.bus.publish(SlotStateChanged(seq.batch_id, slot=d.slot, serial=d.serial, state=d.state,
                                          fault_reason=d.fault_reason))

    # ================================================================== the data path
    async def _pump(self, seq: Sequencer, d: DutRun) -> None:
        """Read one DUT's link until the batch ends; fault only this DUT on a link problem."""
        slot = self.slots[d.slot]
        drv = slot.driver
        assert drv is not None
        timing = self.config.timing
        period = timing.read_period_s
        stats = drv.stats
        bad0 = stats.frames_bad_checksum + stats.frames_malformed + stats.bytes_skipped
        ok0 = stats.frames_ok
        try:
            rt = self.batches.get(seq.batch_id)
            while d.live and not (rt is not None and rt.releasing):
                t_read = time.monotonic()
                try:
                    block = await drv.read_block(timeout_s=max(period, 0.25))
                except DriverError as exc:
                    self.fault_dut(seq, d, f"{d.link}: link lost: {exc}")
                    await self._close_driver(slot)
                    return
                except asyncio.CancelledError:
                    raise
                except Exception as exc:  # noqa: BLE001 - a driver bug must fault its slot, never kill the pump silently
                    log.exception("slot %s: reading %s failed", d.slot, d.link)
                    self.fault_dut(seq, d, f"{d.link}: board data could not be read: {type(exc).__name__}: {exc}")
                    await self._close_driver(slot)
                    return
                now = time.monotonic()
                if len(block):
                    try:
                        self._ingest(seq, d, block, now)
                    except Exception as exc:  # noqa: BLE001 - same: this slot only, with a reason
                        log.exception("slot %s: processing a block from %s failed", d.slot, d.link)
                        self.fault_dut(seq, d, f"{d.link}: board data could not be processed: "
                                               f"{type(exc).__name__}: {exc}")
                        await self._close_driver(slot)
                        return
                    bad0 = stats.frames_bad_checksum + stats.frames_malformed + stats.bytes_skipped
                    ok0 = stats.frames_ok
                elif now - d.last_wall > timing.stall_timeout_s:
                    bad = stats.frames_bad_checksum + stats.frames_malformed + stats.bytes_skipped - bad0
                    if bad > 0 and stats.frames_ok == ok0:
                        reason = (f"{d.link}: only garbage for {now - d.last_wall:.1f} s "
                                  f"({bad} bad frames/bytes, no good frame)")
                    else:
                        reason = f"{d.link}: no samples for {now - d.last_wall:.1f} s"
                    self.fault_dut(seq, d, reason)
                    return
                # Pace the reads so that blocks are big enough to be cheap (update_batch).
                rest = period - (time.monotonic() - t_read)
                if rest > 0:
                    await asyncio.sleep(rest)
        finally:
            d.link_stats = stats.as_dict()

    def _ingest(self, seq: Sequencer, d: DutRun, block: SampleBlock, now: float) -> None:
        d.last_wall = now
        if d.resume_t is not None:
            # First block after a resume: a board whose clock restarted (CAN time is sample index /
            # ODR from our own count) is joined on one sample period after the stored stream.
            if block.time_s[0] <= d.resume_t:
                odr = d.identity.odr_hz if d.identity and d.identity.odr_hz else 1.0
                d.time_offset_s = d.resume_t + 1.0 / odr - float(block.time_s[0])
            d.resume_t = None
        if d.time_offset_s:
            block = SampleBlock(block.time_s + d.time_offset_s, block.acc_g, block.temp_c, block.lost_samples)
        if d.t0 is None:
            d.t0 = float(block.time_s[0])
        d.last_t = float(block.time_s[-1])
        d.n_samples += len(block)
        d.blocks.append(block)
        d.block_steps.append(seq.step_index)
        lamp = self.lamp
        assert lamp is not None
        self.bus.publish(SamplesReceived(seq.batch_id, slot=d.slot, serial=d.serial or "", step_index=seq.step_index,
                                         block=block, lamp_on=lamp.is_on, position=seq.position))
        if d.hold_calibrator and seq.state == "logging":
            # Resumed: the plate is where the step wants it now. No average may span the time the
            # daemon was down or the reconnect, so the calibrator's window starts over here.
            d.hold_calibrator = False
            if hasattr(d.calibrator, "restart_window"):
                d.calibrator.restart_window()
        if d.calibrator is not None and not d.hold_calibrator:
            segs = d.calibrator.update_batch(block.time_s, block.acc_g, block.temp_c)
            if segs and seq.position is None and hasattr(d.calibrator, "discard_last_segment"):
                # averaged while the plate's position was unknown (connecting, moving): no step can
                # use it, and a kept one would make the calibrator wait for a change that never comes
                for _ in segs:
                    d.calibrator.discard_last_segment()
                log.info("slot %s: a segment logged while the plate position was unknown is discarded", d.slot)
                segs = []
            for seg in segs:
                seg = annotate_segment(seg, seq.position)
                d.segments.append(seg)
                d.segment_steps.append(seq.step_index)
                self.bus.publish(SegmentLogged(seq.batch_id, slot=d.slot, serial=d.serial or "",
                                               step_index=seq.step_index, segment=seg))
        lamp.note_sample_time(seq.clock_s())
        lamp.check_dut_temp(d.slot, float(np.max(block.temp_c)))
        seq.notify()

    # ================================================================== results
    async def program_duts(self, seq: Sequencer) -> None:
        """Program and verify, part 1 (station/daemon/program_verify.py)."""
        from station.daemon import program_verify
        await program_verify.program_duts(self, seq)

    async def analyse(self, seq: Sequencer) -> None:
        from station.daemon import program_verify
        if program_verify.after_programming(seq):  # the first pass was analysed in the program step
            await program_verify.verify_duts(self, seq)
            return
        if not self.analyse_results:
            return
        kind = seq.profile.analysis
        duts = [d for d in seq.duts if d.live and d.n_samples > 0]
        if kind == "none" or not duts:
            return
        sem = asyncio.Semaphore(2)  # two cores: do not starve the pumps of other work

        async def one(d: DutRun) -> None:
            async with sem:
                try:
                    if kind == "thermal":
                        res = await asyncio.to_thread(_thermal_result, d, judging.operating_range_c(self, d.identity))
                        d.result = res
                        self.bus.publish(DutResult(seq.batch_id, slot=d.slot, serial=d.serial or "", thermal=res))
                    elif kind == "sfem":
                        res = await asyncio.to_thread(_sfem_result, d, seq.profile)
                        d.result = res
                        self.bus.publish(DutResult(seq.batch_id, slot=d.slot, serial=d.serial or "", sfem=res))
                except StationError as exc:  # InsufficientData and friends: this DUT only
                    self.fault_dut(seq, d, f"analysis: {exc}")

        await asyncio.gather(*(one(d) for d in duts))


def _identity_dict(ident: Any) -> dict:
    return {k: getattr(ident, k) for k in ("serial", "sensor", "fw", "ug_per_lsb", "t_lsb_per_c", "t_lsb_at_25c", "odr_hz")}


def _thermal_result(d: DutRun, operating_range_c: float = 70.0) -> dict:
    """Streaming (the live calibrator) and offline results of one DUT, as `station calibrate --json`."""
    # list() first: this runs in a worker thread while the pump may still append blocks; a copy
    # (atomic under the GIL) keeps the three columns of concat from seeing different lists
    from station.science.thermal_calibration import fit_samples

    block = fit_samples(SampleBlock.concat(list(d.blocks)), [s.t_end_s for s in d.segments])
    try:
        from station.science.thermal_calibration import calibrate
    except ImportError:
        calibrate = None
    if calibrate is not None:
        res = dict(calibrate(block, operating_range_c=operating_range_c))
    else:  # science not landed: the live streaming result only
        r = d.calibrator.result()
        res = {"axes": r.to_json()["axes"], "streaming": r.to_json()}
    res["serial"] = d.serial
    try:
        res["streaming_live"] = d.calibrator.result().to_json()
    except Exception as exc:
        res["streaming_live"] = {"error": str(exc)}
    res["n_samples"] = int(len(block))
    return _finite(res)


def _sfem_result(d: DutRun, profile: Profile) -> dict:
    """SFEM per temperature step from the static windows of each step (sensors2023)."""
    from station.science import sfem

    groups: dict[Any, list[int]] = {}
    for i, s in enumerate(profile.steps):
        if s.require == "static":
            groups.setdefault((s.chamber_setpoint_c, s.lamp), []).append(i)
    full = SampleBlock.concat(list(d.blocks))  # a snapshot: the pump may still append (worker thread)
    out: dict = {"temperatures": []}
    for (setpoint, lamp), idxs in groups.items():
        means, refs, temps = [], [], []
        for i in idxs:
            if i not in d.step_windows:
                continue
            t_from, t_to = d.step_windows[i]
            s = profile.steps[i]
            lo = t_from + s.settle_s
            m = (full.time_s > lo) & (full.time_s <= min(t_to, lo + s.dwell_s))
            if m.sum() < 10:
                continue
            means.append(full.acc_g[m].mean(axis=0))
            temps.append(float(full.temp_c[m].mean()))
            refs.append(GRAVITY_DIRECTIONS[s.position])
        if len(means) < 9:
            continue
        fit = sfem.fit_sfem(np.array(means), ref_dir=np.array(refs))
        fj = fit.to_json() if hasattr(fit, "to_json") else _jsonable(fit)
        out["temperatures"].append({"setpoint_c": setpoint, "lamp": lamp, "temp_c": float(np.mean(temps)),
                                    "n_positions": len(means), "fit": fj})
    if not out["temperatures"]:
        raise StationError("no temperature step has enough static positions for an SFEM fit")
    return _finite(out)


def _jsonable(v: Any) -> Any:
    import dataclasses

    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return {f.name: _jsonable(getattr(v, f.name)) for f in dataclasses.fields(v)}
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if hasattr(v, "tolist"):
        return v.tolist()
    return v


def _finite(v: Any) -> Any:
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {k: _finite(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_finite(x) for x in v]
    if hasattr(v, "tolist"):
        return _finite(v.tolist())
    return v
