"""Slots: one board each, identified, bound to its DUT run, streaming, or faulted ALONE.

A slot is the fixture's place for one board and its link (serial port or CAN node). Between
batches it holds the board's identity; in a batch it carries one DUT run (station/daemon/dut_run
DutRun). A link problem faults that slot's run with the reason and nothing else: the batch goes on
with the other boards (design 1, "a fault stays in its slot").

`SlotBank` owns the slots and the pumps that read them (intake.py), and nothing above them: it
is built from the links, the event bus, the database and the timing it needs, and the run's end
(run_end.py) and program-and-verify use it through their own narrow Protocols. The Station
(supervisor.py) only wires it.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from contracts.trace import label_mismatch
from contracts.events import EventBus, SegmentLogged, SlotStateChanged
from contracts.types import Identity
from db import repository as repo
from db.database import Database
from db.models import MeasuredBy
from drivers.base import BoardDriver, DriverError
from station.config import SlotConfig, Timing
from station.daemon.dut_run import Calibrator, DutRun
from station.daemon.identity_check import batch_identity_problems, identity_change
from station.daemon.instruments import Links
from station.daemon.intake import pump
from station.daemon.intake_monitor import IntakeMonitor
from station.daemon.route_gate import RouteGate
from station.daemon.safety import LampGuard
from station.daemon.sequencer import Sequencer
from station.daemon.states import TERMINAL
from station.daemon.storage import Storage
from station.decisions.moment import attempt_of
from station.decisions.route_check import RouteAnswer, fault_words, flag_words, may_test
from station.version import software_version

log = logging.getLogger(__name__)

IDENTITY_FIELDS = ("serial", "sensor", "fw", "ug_per_lsb", "t_lsb_per_c", "t_lsb_at_25c", "odr_hz")


@dataclass
class SlotRuntime:
    cfg: SlotConfig
    driver: BoardDriver | None = None
    state: str = "disconnected"  # disconnected, identified, busy, faulted
    identity: Identity | None = None
    fault_reason: str = ""
    batch_id: int | None = None

    def status(self) -> dict[str, object]:
        return {
            "slot": self.cfg.name,
            "name": self.cfg.name,
            "link": self.cfg.link,
            "state": self.state,
            "serial": self.identity.serial if self.identity else None,
            "sensor": self.identity.sensor if self.identity else None,
            "batch_id": self.batch_id,
            "fault_reason": self.fault_reason,
            "link_stats": self.driver.stats.as_dict() if self.driver is not None else {},
        }

    async def close_driver(self) -> None:
        if self.driver is not None:
            drv, self.driver = self.driver, None
            try:
                await asyncio.wait_for(drv.close(), 2.0)
            except Exception:  # noqa: BLE001 - a link that will not close is closed for us anyway
                pass


def identity_dict(ident: Identity) -> dict[str, object]:
    return {k: getattr(ident, k) for k in IDENTITY_FIELDS}


def measured_by(seq: Sequencer, ident: Identity) -> MeasuredBy:
    """What measures a new run (stored with it): this software, the board's firmware as its identity
    reports it, and what turns the plate: the fixture when the batch has one (the sequencer moves it),
    else a person at the plate (the sequencer prompts)."""
    return MeasuredBy(software_version=software_version(), firmware_version=ident.fw,
                      holder="fixture" if seq.hw.fixture is not None else "operator")


class SlotBank:
    """Every slot of the station and the pump of each running one (see the module doc)."""

    def __init__(self, slots: list[SlotConfig], *, links: Links, bus: EventBus, db: Database, storage: Storage,
                 timing: Timing, calibrator_factory: Callable[[], Calibrator], route: RouteGate | None = None) -> None:
        self.slots: dict[str, SlotRuntime] = {s.name: SlotRuntime(s) for s in slots}
        self.route = route  # the MES's route check ([mes.route_check]), asked before each run is made
        self.links = links
        self.bus = bus
        self.db = db
        self.storage = storage
        self.timing = timing
        self.calibrator_factory = calibrator_factory
        self.lamp: LampGuard | None = None  # the station's, set when it starts (the pumps report to it)
        # how far behind its boards the station runs, what it lost, what it can follow
        self.monitor = IntakeMonitor(timing.speed, timing.intake_cost_us_per_sample, reads_per_s=timing.reads_per_s)
        self._pumps: dict[int, dict[str, asyncio.Task[None]]] = {}
        self._releasing: set[int] = set()

    # ------------------------------------------------------------------ what the pumps ask
    def releasing(self, batch_id: int) -> bool:
        """True once the batch's end has stopped its streams: a pump ends at its next turn (a
        cancel alone can be swallowed by a driver's wait)."""
        return batch_id in self._releasing

    def driver_of(self, slot: str) -> BoardDriver | None:
        rt = self.slots.get(slot)
        return rt.driver if rt is not None else None

    def link_stats(self, slot: str) -> dict[str, int] | None:
        """A slot's live link counters now (None: no driver): what the verdict's moment reads."""
        drv = self.driver_of(slot)
        return drv.stats.as_dict() if drv is not None else None

    # ------------------------------------------------------------------ between batches
    async def connect_slot(self, rt: SlotRuntime, batch_id: int = 0) -> bool:
        """Open (if needed) and identify one slot. Returns False (slot faulted) on a link problem."""
        try:
            if rt.driver is None:
                rt.driver = await self.links.board_driver(rt.cfg)
                await rt.driver.open()
            try:
                await rt.driver.stop()  # a board left streaming by a previous process
            except DriverError:
                pass
            rt.identity = await rt.driver.identify(self.timing.identify_timeout_s)
        except (DriverError, OSError) as exc:
            rt.state, rt.fault_reason = "faulted", f"{rt.cfg.link}: {exc}"
            await rt.close_driver()
            log.warning("slot %s: %s", rt.cfg.name, rt.fault_reason)
            if not batch_id:
                self.bus.publish(SlotStateChanged(0, slot=rt.cfg.name, serial=None, state="faulted",
                                                  fault_reason=rt.fault_reason))
            return False
        rt.state, rt.fault_reason = "identified", ""
        if not batch_id:  # inside a batch, connect_duts publishes once the run exists
            self.bus.publish(SlotStateChanged(0, slot=rt.cfg.name, serial=rt.identity.serial, state="identified"))
        return True

    async def connect_all(self) -> None:
        await asyncio.gather(*(self.connect_slot(rt) for rt in self.slots.values()))

    async def close(self) -> None:
        for rt in self.slots.values():
            await rt.close_driver()

    def bind(self, seq: Sequencer) -> None:
        """The batch's slots are its own from now on (GET /api/slots shows its runs' states)."""
        for d in seq.duts:
            self.slots[d.slot].batch_id = seq.batch_id

    # ------------------------------------------------------------------ one DUT
    def publish_dut(self, seq: Sequencer, d: DutRun) -> None:
        self.bus.publish(SlotStateChanged(seq.batch_id, slot=d.slot, serial=d.serial, state=d.state,
                                          fault_reason=d.fault_reason))

    def fault_dut(self, seq: Sequencer, d: DutRun, reason: str) -> None:
        """This DUT's run ends faulted with `reason`; its pump stops; the others go on."""
        if not d.live:
            return
        d.state, d.fault_reason = "faulted", reason
        log.warning("batch %d slot %s faulted: %s", seq.batch_id, d.slot, reason)
        self.publish_dut(seq, d)
        task = self._pumps.get(seq.batch_id, {}).get(d.slot)
        if task is not None and task is not asyncio.current_task():
            task.cancel()
        slot = self.slots[d.slot]
        slot.state, slot.fault_reason = "faulted", reason
        seq.notify()

    # ------------------------------------------------------------------ a batch's start and end
    async def connect_duts(self, seq: Sequencer) -> None:
        """Identify every DUT of the batch, open (or continue) its run, start its stream and its pump."""
        self._releasing.clear()  # one batch at a time: the ended ones' pumps are long gone (their DUTs ended)
        pumps = self._pumps.setdefault(seq.batch_id, {})

        async def connect(d: DutRun) -> bool:
            slot = self.slots[d.slot]
            d.state = "connecting"
            self.publish_dut(seq, d)
            if not await self.connect_slot(slot, seq.batch_id):
                self.fault_dut(seq, d, slot.fault_reason)
                return False
            slot.state = "busy"
            d.identity = slot.identity
            return True

        # Every board answers first: a serial is trusted only when it is valid and unique in the batch
        # (identity_check, design 3.1), which no slot can know alone. A refused slot gets no run (no
        # record under a serial that is not its own), never streams, and stops before the lamp heats.
        answered = [d for d, ok in zip(seq.duts, await asyncio.gather(*(connect(d) for d in seq.duts))) if ok]
        serials = {d.slot: d.identity.serial for d in answered if d.identity is not None}
        refused = batch_identity_problems(serials)
        for d in answered:
            if d.slot in refused:
                self.fault_dut(seq, d, refused[d.slot])
        if refused:
            await asyncio.to_thread(self._audit_refused, seq.batch_id, refused, serials)

        async def one(d: DutRun) -> None:
            slot = self.slots[d.slot]
            ident = d.identity
            assert ident is not None and slot.driver is not None
            if d.expected_serial is not None and ident.serial != d.expected_serial:
                self.fault_dut(seq, d, f"{d.link}: found serial {ident.serial}, the interrupted run was "
                                       f"{d.expected_serial} (board swapped?)")
                return
            d.state = "identified"
            # The label is checked before the run is made: a board that is not the labelled part is
            # never tested, so its run is no attempt of the board's serial (attempt 0: not counted in
            # attempts or yields, db/database.py). The run is still stored (faulted, judged error):
            # the MES and the audit see which board was in the slot, and why it stopped.
            mismatch = label_mismatch(d.label_serial, ident.serial)
            # The MES's route check (design 5.4), for a part that is the labelled one and whose run is
            # new (a resumed run was asked when it was made): a part the MES refuses is never tested,
            # so like a wrong label its run is stored (the record says why) but is no attempt.
            route: RouteAnswer | None = None
            stop_words: str | None = mismatch
            if mismatch is None and d.run_id is None and self.route is not None:
                part = self.route.part(ident.serial, d.slot, d.label_serial, seq.trace.work_order,
                                       seq.trace.part_number, seq.trace.lot)
                route = await self.route.ask(part, seq.batch_id)
                policy = self.route.cfg.when_unanswered
                if not may_test(route, policy):
                    stop_words = fault_words(part, route, policy)
                elif route.outcome == "unanswered":
                    d.route_flag = flag_words(part, route)
            if d.run_id is None:
                # off the event loop: the insert may wait on the database's lock (the writer's commit,
                # another station meeting the same serial) while the other slots stream
                d.run_id = int(await asyncio.to_thread(
                    self.db.create_run, seq.batch_id, d.slot, ident.serial, ident.sensor, identity_dict(ident),
                    counts_as_attempt=stop_words is None, measured_by=measured_by(seq, ident),
                    route_check=None if route is None else route.outcome,
                    route_reason="" if route is None else route.reason))
            if d.attempt is None:
                d.attempt = await asyncio.to_thread(attempt_of, self.db, d.run_id)
            if self.storage.writer is not None:
                self.storage.writer.bind_run(seq.batch_id, d.slot, d.run_id)
            if stop_words is not None:
                self.fault_dut(seq, d, stop_words)
                return
            self.publish_dut(seq, d)
            for seg, step in d.unstored_segments:
                d.segments.append(seg)
                d.segment_steps.append(step)
                self.bus.publish(SegmentLogged(seq.batch_id, slot=d.slot, serial=ident.serial, step_index=step,
                                               segment=seg))
            d.unstored_segments.clear()
            if d.calibrator is None:
                d.calibrator = self.calibrator_factory()
            # Samples still held from the board's previous run (read after its last block until its
            # STOP took effect) would open this run with that run's tail and a gap of the time between
            # the batches (the plot's first sample).
            dropped = slot.driver.discard_held()
            if dropped:
                log.info("batch %d slot %s: %d samples of the previous run discarded", seq.batch_id, d.slot, dropped)
            try:
                await slot.driver.start()
            except DriverError as exc:
                self.fault_dut(seq, d, f"{d.link}: start failed: {exc}")
                return
            d.state = "running"
            self.publish_dut(seq, d)
            pumps[d.slot] = asyncio.get_running_loop().create_task(pump(self, seq, d, slot), name=f"pump-{d.slot}")

        await asyncio.gather(*(one(d) for d in answered if d.live))

    def _audit_refused(self, batch_id: int, refused: dict[str, str], serials: dict[str, str]) -> None:
        """identity.refused in the audit trail: which boards a batch did not test, with the serial each
        reported (no run holds it). Logged loudly, never raised: the batch goes on with the others."""
        try:
            repo.audit_append(self.db, "station", "identity.refused", f"batch {batch_id}",
                              {slot: {"serial": serials.get(slot), "reason": why} for slot, why in refused.items()})
        except Exception:  # noqa: BLE001
            log.critical("audit: could not record the identities refused in batch %d", batch_id, exc_info=True)

    async def stop_streams(self, seq: Sequencer) -> None:
        """Stop every pump of the batch (each ends at its next turn at the latest)."""
        self._releasing.add(seq.batch_id)
        pumps = self._pumps.pop(seq.batch_id, {})
        for t in pumps.values():
            t.cancel()
        if pumps:
            # Python 3.11's asyncio.wait_for (inside read_block) can swallow a cancel that lands as its
            # wait completes: the pump then ends on `releasing` at its next read instead.
            _, late = await asyncio.wait(pumps.values(), timeout=10.0)
            for t in late:
                log.error("batch %d: pump %s did not stop within 10 s", seq.batch_id, t.get_name())

    async def board_changed(self, d: DutRun, when: str) -> str | None:
        """Is the board in this DUT's slot still the one its run started with? Asked `when` (at the
        end of its run, before it is programmed): its identity is read again and compared (design
        3.1). Returns the reason the run cannot stand, in words, or None. A board that does not answer
        cannot be confirmed: its data may be another board's (a swap behind a port that stayed open)."""
        drv = self.slots[d.slot].driver
        if d.identity is None:
            return None
        if drv is None:
            return f"{d.link}: the board's identity could not be read again {when}: link closed"
        try:
            now = await drv.identify(self.timing.identify_timeout_s)
        except Exception as exc:  # noqa: BLE001 - whatever the driver raises, this run cannot be confirmed
            return f"{d.link}: the board's identity could not be read again {when}: {exc}"
        change = identity_change(d.identity, now)
        if change is None:
            return None
        self.slots[d.slot].identity = now
        if now.serial != d.identity.serial:
            return (f"{d.slot} answers {now.serial} {when}, {d.identity.serial} at its start: "
                    f"a board swapped mid-run? ({change})")
        return f"{d.slot}'s board changed {when}: {change} (firmware replaced or another board?)"

    async def stop_board(self, d: DutRun) -> bool:
        """At the run's end: STOP the board and keep its link's counters with the run. True when the
        STOP went out (a serial board acknowledges it): the link is still there."""
        drv = self.slots[d.slot].driver
        if drv is None:
            return False
        answered = False
        try:
            await asyncio.wait_for(drv.stop(), 3.0)
            answered = True
        except Exception:  # noqa: BLE001 - a board that does not stop ends its run all the same
            pass
        d.link_stats = drv.stats.as_dict()
        return answered

    async def slot_free(self, d: DutRun, answered: bool, shutting_down: bool) -> None:
        """The batch is done with this DUT's slot: a busy slot is ready again; a slot faulted on a
        link that still answered is ready once its board identifies (ready_again); not at a shutdown."""
        slot = self.slots[d.slot]
        if slot.state == "busy":
            slot.state = "identified"
        elif slot.state == "faulted" and answered and not shutting_down:
            await self.ready_again(slot)

    async def ready_again(self, rt: SlotRuntime) -> bool:
        """At a batch's end, a slot faulted in it whose board still answers (its STOP was acknowledged)
        is ready for the next batch once the board identifies again: `identified`, no fault reason (the
        run keeps its own fault and verdict). A slot whose board does not answer, or whose link is gone
        (driver closed: link lost, port vanished), keeps `faulted` with its reason; it can still be
        chosen for the next batch, whose connect tries it again (connect_slot)."""
        if rt.driver is None:
            return False
        try:
            ident = await rt.driver.identify(self.timing.identify_timeout_s)
        except Exception as exc:  # noqa: BLE001 - whatever the board or driver does, the batch's end goes on
            log.info("slot %s: no identity after its fault (%s): stays faulted", rt.cfg.name, exc)
            return False
        rt.identity, rt.state, rt.fault_reason = ident, "identified", ""
        self.bus.publish(SlotStateChanged(0, slot=rt.cfg.name, serial=ident.serial, state="identified"))
        return True

    # ------------------------------------------------------------------ what GET /api/slots shows
    def status(self, batches: Mapping[int, Sequencer]) -> list[dict[str, object]]:
        """Every slot as GET /api/slots shows it: inside a running batch, its DUT run's state. An
        identified slot whose serial a batch of all identified slots would refuse (identity_check:
        shared with another slot, empty, invalid) carries `identity_problem`, so the page says so
        before Start."""
        ready = {rt.cfg.name: rt.identity.serial for rt in self.slots.values()
                 if rt.state == "identified" and rt.identity is not None}
        problems = batch_identity_problems(ready)
        out = []
        for rt in self.slots.values():
            s = rt.status()
            s["identity_problem"] = problems.get(rt.cfg.name)
            seq = batches.get(rt.batch_id) if rt.batch_id is not None else None
            if seq is not None:
                for d in seq.duts:
                    if d.slot == rt.cfg.name:
                        s["run_state"] = d.state
                        s["run_id"] = d.run_id
                        if seq.state not in TERMINAL:
                            s["state"] = "busy" if d.live else "faulted"
                            s["fault_reason"] = d.fault_reason or s["fault_reason"]
            out.append(s)
        return out
