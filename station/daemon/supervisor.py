"""The station daemon's facade: the `Station` the web and the CLI use, wiring parts with one job each.

    instruments.py  links: Modbus instruments, board drivers, shared CAN buses
    storage.py      the database (a temporary SQLite file when none is configured) and its writer
    slots.py        SlotBank: identify, bind to a DUT run, start streaming, fault one alone
    intake.py       per DUT: the pump that reads its link and the ingest of each sample block
    batches.py      BatchDesk: start, retest or resume a batch; the running one and the last ended
    sequencer.py    one state machine per batch (steps, plate, lamp, prompts)
    run_end.py      RunEnd: analysis, program-and-verify, end states, then the verdict's moment
    rig.py          Rig: the sequencer's `Hardware` (instruments + slot bank + run end)
    progress.py     what the batch status adds: decision summary, sorting, time left

The Station owns the shared state (config, event bus, database, links, the LampGuard) and builds
the parts once; at start it hands the sequencer's `Hardware` to the batch desk as a `Rig`, which
calls the slot bank and the run's end directly, never back through this facade.

Facade methods are plain (sync) methods to be called from the daemon's event loop (the web app runs
in the same loop); they return at once and the batch runs in its own task.
Unknown batch -> KeyError; a bad request -> ValueError.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
from collections.abc import Callable

from contracts.events import EventBus
from contracts.trace import Trace
from contracts.types import NotFound, StationError
from db.database import Database
from db.writer import DbWriter
from station.config import StationConfig
from station.cfx.outbox import CfxOutbox
from station.daemon.batches import BatchDesk
from station.daemon.dut_run import Calibrator, wall_text
from station.daemon.instruments import Links
from station.daemon.ownership import StationClaim, database_url_of
from station.daemon.progress import batch_extras
from station.daemon.rig import Rig
from station.daemon.route_gate import RouteGate
from station.daemon.run_end import RunEnd
from station.daemon.safety import LampGuard
from station.daemon.sequencer import Sequencer
from station.daemon.slots import SlotBank, SlotRuntime
from station.daemon.states import TERMINAL
from station.daemon.storage import Storage, open_database, storage_state
from station.decisions import moment
from station.decisions.verdict_context import VerdictContext
from station.profiles import Profile, all_profiles
from station.science.streaming import StreamingCalibrator
from station.science.streaming_config import StreamingConfig

log = logging.getLogger(__name__)

__all__ = ["Station"]


def _default_calibrator_factory() -> StreamingCalibrator:
    return StreamingCalibrator(StreamingConfig())


class Station:
    """The daemon. `await start()` connects the instruments and slots; `await close()` makes it safe."""

    def __init__(
        self,
        config: StationConfig,
        *,
        db: Database | None = None,
        bus: EventBus | None = None,
        calibrator_factory: Callable[[], Calibrator] | None = None,
        analyse_results: bool = True,
        claim: StationClaim | None = None,
    ) -> None:
        self.config = config
        self.claim = claim  # taken at start() unless given (station serve takes it before the database)
        self.bus = bus or EventBus()
        self.db = db if db is not None else open_database(None, station=config.name)
        self.storage = Storage(self.db, self.bus, config.journal_path)
        self.links = Links(config.timing.speed)
        self.profiles_by_name: dict[str, Profile] = all_profiles(config)
        factory = calibrator_factory or _default_calibrator_factory
        self.bank = SlotBank(config.slots, links=self.links, bus=self.bus, db=self.db, storage=self.storage,
                             timing=config.timing, calibrator_factory=factory,
                             route=None if config.mes.route_check is None
                             else RouteGate(config.mes.route_check, config.name, self.db))
        # what the verdict's moment reads, typed and taken here: a renamed part fails the type check
        # and the construction, not a judgement at a restart (station/decisions/verdict_context.py)
        self.verdicts = VerdictContext(db=self.db, bus=self.bus, product_for=config.product_for,
                                       profiles=self.profiles_by_name, live_link_stats=self.bank.link_stats)
        self.run_end = RunEnd(self.bank, self.storage, self.verdicts, analyse_results=analyse_results,
                              shutting_down=lambda: self._closed)
        self.desk = BatchDesk(db=self.db, bus=self.bus, slots=self.bank, storage=self.storage,
                              profiles=self.profiles_by_name, config=config, calibrator_factory=factory,
                              running=lambda: self.running)
        self.lamp: LampGuard | None = None
        self.cfx: CfxOutbox | None = None  # IPC-CFX to the line ([cfx] enabled; station/cfx, docs/cfx.md)
        self._started = False
        self._closed = False

    @property
    def slots(self) -> dict[str, SlotRuntime]:
        return self.bank.slots

    @property
    def batches(self) -> dict[int, Sequencer]:
        """The running batch and the last ended one (older ones are read from the database)."""
        return self.desk.batches

    @property
    def writer(self) -> DbWriter | None:
        """The database writer (None before start and after close)."""
        return self.storage.writer

    @property
    def running(self) -> bool:
        return self._started and not self._closed

    # ================================================================== lifecycle
    async def start(self, connect_slots: bool = True) -> None:
        """Connect Modbus instruments (the lamp relay is mandatory) and identify every slot.

        An unreachable instrument is a StationError (one line); a slot that cannot be opened or
        identified is only marked faulted (the other slots still work).
        """
        cfg = self.config
        if self.claim is None:  # one station owns its database, ports and relay (ownership.py): first
            self.claim = StationClaim.take(cfg, database_url=database_url_of(self.db))
        relay = await self.links.relay(cfg.lamp)
        thermometer = await self.links.thermometer(cfg.thermometer) if cfg.thermometer else None
        fixture = await self.links.fixture(cfg.fixture) if cfg.fixture else None
        chamber = await self.links.chamber(cfg.chamber) if cfg.chamber else None
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
        self.bank.lamp = self.lamp
        self.desk.rig = Rig(lamp=self.lamp, fixture=fixture, chamber=chamber, fixture_timeout_s=cfg.timing.fixture_timeout_s,
                            plate_again_after_s=cfg.timing.plate_again_after_s, speed=cfg.timing.speed,
                            slots=self.bank, run_end=self.run_end)
        self.storage.start()
        if cfg.cfx.enabled:
            self.cfx = CfxOutbox(self.db, self.bus, cfg)
            await self.cfx.start()
        self._started = True
        if connect_slots:
            await self.bank.connect_all()

    async def close(self, reason: str = "daemon shutdown") -> None:
        """Interrupt running batches, switch the lamp off, close every link. Idempotent."""
        if self._closed:
            return
        self._closed = True
        for seq in list(self.batches.values()):
            seq.stop("interrupted", reason)
        if self.lamp is not None:  # lamp off first, before anything that can take time
            await self.lamp.off(reason)
        for seq in list(self.batches.values()):
            if seq.task is not None:
                try:
                    await asyncio.wait_for(seq.done.wait(), 10.0)
                except asyncio.TimeoutError:
                    log.error("batch %d did not end within 10 s", seq.batch_id)
        await self.desk.close()
        if self.lamp is not None:
            await self.lamp.close(reason)
        await self.bank.close()
        await self.links.close()
        if self.cfx is not None:  # what it has not queued yet, the next start reads from the database
            await self.cfx.stop()
            self.cfx = None
        await self.storage.stop()
        if self.claim is not None:  # the last thing: nothing of this station is in use any more
            self.claim.release()
            self.claim = None

    async def __aenter__(self) -> "Station":
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # ================================================================== storage
    def storage_status(self) -> str:
        """'ok', or 'error: ...' while the writer cannot store (what /api/health reports)."""
        return storage_state(self.writer, self.storage.probe)

    async def flush_db(self) -> None:
        """Wait until every event published so far is committed (tests, --once summary)."""
        await self.storage.flush()

    # ================================================================== facade: profiles
    def profiles(self) -> list[str]:
        return list(self.profiles_by_name)

    def profiles_info(self) -> list[dict[str, object]]:
        """What GET /api/profiles lists: name, description, analysis kind, step count (the page
        shows the description so a newcomer can choose; 'none' means no calibration result)."""
        return [{"name": p.name, "description": p.description or None, "analysis": p.analysis,
                 "n_steps": len(p.steps), "builtin": p.builtin, "program_verify": p.program_step is not None}
                for p in self.profiles_by_name.values()]

    def profile(self, name: str) -> dict[str, object]:
        if name not in self.profiles_by_name:
            raise NotFound(f"unknown profile {name!r}")
        return self.profiles_by_name[name].to_json()

    # ================================================================== facade: batches
    def start_batch(self, profile: str, slots: list[str] | None = None, operator: str = "",
                    trace: Trace | None = None, by: str = "") -> int:
        """Start a batch for `operator` (required); trace: work order, part, lot, label serials."""
        return self.desk.start_batch(profile, slots, operator, trace, by)

    def retest_batch(self, batch_id: int, operator: str, by: str = "", labels: dict[str, str] | None = None,
                     slots: list[str] | None = None) -> int:
        """A new batch of the error, fail and marginal slots of an ended batch (same profile, work
        order, part, lot), with the labels scanned again (station/daemon/batches.py)."""
        return self.desk.retest_batch(batch_id, operator, by, labels=labels, slots=slots)

    def resume_batch(self, batch_id: int, operator: str = "") -> int:
        """Resume an interrupted batch (crash, restart) at the step after its last completed one,
        each interrupted DUT run as the same run (station/daemon/batches.py)."""
        return self.desk.resume_batch(batch_id, operator)

    def _batch(self, batch_id: int) -> Sequencer:
        try:
            return self.batches[int(batch_id)]
        except (KeyError, ValueError, TypeError):
            raise NotFound(f"unknown batch {batch_id}") from None

    def abort(self, batch_id: int, reason: str = "", by: str = "operator") -> None:
        """End a batch for an operator. The batch's error says who and when ("aborted by Ana at
        2026-11-23 14:02:05 UTC", then the reason if one was given): ended_by / ended_at."""
        seq = self._batch(batch_id)
        if seq.state in TERMINAL:
            raise ValueError(f"batch {batch_id} has already ended ({seq.state})")
        text = f"aborted by {by} at {wall_text(time.time())}"
        if reason and reason != "operator":
            text += f": {reason}"
        seq.stop("aborted", text, by=by)

    def prompt(self, batch_id: int) -> dict[str, object] | None:
        return self._batch(batch_id).prompt

    def answer_prompt(self, batch_id: int, prompt_id: int, answer: str = "done", by: str | None = None,
                      note: str = "") -> None:
        """done / abort / cannot (with the operator's words: the DUTs on the plate end as error)."""
        self._batch(batch_id).answer_prompt(prompt_id, answer, by=by, note=note)

    def batch_status(self, batch_id: int) -> dict[str, object]:
        seq = self._batch(batch_id)
        st = seq.status()
        for s in st["slots"]:
            stats = self.bank.link_stats(s["slot"])
            if stats is not None:
                s["link_stats"] = stats
        st.update(batch_extras(self, seq))
        if seq.state not in TERMINAL:
            st["overload"] = self.intake_status()
        return st

    def batch_marker(self, batch_id: int) -> tuple[object, ...]:
        """Cheap fingerprint of a batch's state (cache validation): changes with every
        transition, step and DUT state change."""
        seq = self._batch(batch_id)
        return (seq.state, len(seq.history), seq.step_index, tuple(d.state for d in seq.duts))

    def batch_ids(self) -> list[int]:
        return sorted(self.batches)

    def running_batch(self) -> int | None:
        """The batch that has not ended, if any (one plate, one lamp): cheap, no status rendered."""
        return self.desk.running_batch()

    def samples_taken(self, batch_id: int) -> dict[str, int]:
        """Samples each live DUT of the batch has taken in so far, by slot (cheap: a replay paces
        its recorded plant by it, station/replay/runner.py)."""
        return {d.slot: d.n_samples for d in self._batch(batch_id).duts if d.live}

    def stop_pending(self, batch_id: int, slot: str) -> bool:
        """True while the batch will still stop `slot`'s board to program it: its profile has a
        program step the sequencer has not finished and the slot's DUT is live (cheap: a replay
        holds a recorded stream at its program stop until then, station/replay/director.py)."""
        seq = self._batch(batch_id)
        ps = seq.profile.program_step
        if ps is None or seq.state in TERMINAL or not any(d.slot == slot and d.live for d in seq.duts):
            return False
        return seq.step_index < ps or (seq.step_index == ps and seq.state == "programming")

    def step_begun(self, batch_id: int) -> int | None:
        """The last step the batch has begun (logging, or programming for a program step; -1 before
        the first); None once the batch has ended (cheap: a replay holds each recorded stream at
        its recorded step start until the daemon has begun that step, station/replay/director.py)."""
        seq = self._batch(batch_id)
        if seq.state in TERMINAL:
            return None
        if seq.state in ("step_setup", "positioning", "moving", "waiting_operator"):
            return seq.step_index - 1
        return seq.step_index

    async def wait_batch(self, batch_id: int, timeout_s: float | None = None) -> dict[str, object]:
        seq = self._batch(batch_id)
        await asyncio.wait_for(seq.done.wait(), timeout_s)
        return self.batch_status(batch_id)

    def judge_interrupted(self, batch_ids: list[int], reason: str = "station restarted") -> int:
        """Error verdicts for the runs of batches a killed daemon left running, and for every run
        that ended with no verdict stored (decisions/moment.py)."""
        ids = list(batch_ids or [])
        return moment.judge_interrupted_runs(self.verdicts, ids, reason) + moment.judge_unjudged_runs(self.verdicts, ids)

    # ================================================================== facade: slots and lamp
    def slots_status(self) -> list[dict[str, object]]:
        return self.bank.status(self.batches)

    def lamp_status(self) -> dict[str, object]:
        """What the page and health show of the lamp: commanded, real state (or unknown), watchdog."""
        lamp = self.lamp
        if lamp is None:
            return {"state": "unknown", "relay_error": "station not started"}
        return {"state": lamp.state, "on_commanded": lamp.is_on, "relay_error": lamp.relay_error,
                "watchdog_s": lamp.watchdog_s if lamp.watchdog_armed else 0, "trip": lamp.trip_reason}

    def intake_status(self) -> dict[str, object]:
        """Is the station keeping up with its boards (station/daemon/intake_monitor.py): how far
        behind, what it lost to its backlog, what it follows, and the alarm in words."""
        return dataclasses.asdict(self.bank.monitor.state(time.monotonic()))

    def _on_lamp_trip(self, reason: str) -> None:
        for seq in self.batches.values():
            if seq.state not in TERMINAL:
                seq.stop("failed", f"safety trip: {reason}")
