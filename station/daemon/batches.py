"""Starting a batch, or resuming one a stopped daemon interrupted.

A batch is one profile run on a set of slots by one sequencer (one plate, one lamp: one batch at a
time). Every request is checked here before anything moves; a bad one is a ValueError with the
reason the page shows (unknown profile or slot, a slot listed twice, a chamber the profile needs
but the station lacks, a batch already running).

Resume (design 6): each DUT run that was interrupted goes on as the SAME run. Its stored samples
are replayed through a fresh calibrator (pure science: the state it had before the stop), the live
stream is appended after them, and the board must answer with the same serial.

`BatchDesk` owns the batches this daemon runs and has run: the running one, and the last one that
ended (what the page shows until the next start). An ended batch leaves memory once everything it
published is durable (stored, or in the station's journal) and a newer one has ended: its raw
samples are released at once, and the page and the API read older batches from the database.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from contracts.events import EventBus
from contracts.types import NotFound, SampleBlock, StorageUnavailable
from contracts.trace import Trace, label_mismatch
from db import repository as repo
from db.database import Database, ResumePoint, RunPoint
from db.export import run_log
from db.repository import segments_of_run
from station.config import StationConfig
from station.daemon.dut_run import Calibrator, DutRun, annotate_segment
from station.daemon.rig import Rig
from station.daemon.sequencer import Sequencer
from station.daemon.slots import SlotBank
from station.daemon.states import TERMINAL
from station.daemon.storage import Storage
from station.profiles import Profile
from station.science.placement import label_cuts

log = logging.getLogger(__name__)


# The verdicts "Retest failed" takes again: error (faulted or incomplete: nothing valid was measured),
# fail (outside a limit: a part badly seated, a label mixed up, a plate not flat can do that, and the
# retest is the second look; first-pass yield keeps the first verdict) and marginal (the interval
# crosses a limit: its tray is "hold (review / retest)", and a new measurement is the way out of
# hold). A pass is final. docs/verdicts.md, docs/operator-page.md.
RETEST_VERDICTS = ("error", "fail", "marginal")


@dataclass(frozen=True)
class EndedRun:
    """What a retest needs of one slot of an ended batch: its verdict, the label scanned for it
    and the serial its board answered with (None: it never identified)."""

    slot: str
    verdict: str | None
    label_serial: str | None
    board_serial: str | None


@dataclass(frozen=True)
class EndedBatch:
    profile: str
    runs: list[EndedRun]
    trace: Trace


class BatchDesk:
    """Start, retest and resume batches; hold the running one and the last ended (module doc)."""

    def __init__(self, *, db: Database, bus: EventBus, slots: SlotBank, storage: Storage,
                 profiles: Mapping[str, Profile], config: StationConfig,
                 calibrator_factory: Callable[[], Calibrator], running: Callable[[], bool]) -> None:
        self.db = db
        self.bus = bus
        self.slots = slots
        self.storage = storage
        self.profiles = profiles
        self.config = config
        self.calibrator_factory = calibrator_factory
        self.running = running
        self.rig: Rig | None = None  # the station's instruments, once it has started
        self.batches: dict[int, Sequencer] = {}
        self._forgetting: set[asyncio.Task[None]] = set()

    # ------------------------------------------------------------------ checks
    def _require_running(self) -> Rig:
        if not self.running() or self.rig is None:
            raise ValueError("the station is not running")
        why = self.storage.blocked()
        if why is not None:
            raise StorageUnavailable(f"no new batch can start: {why} (a batch's runs are numbered in the database; "
                                     "running batches go on and their records wait in the station's journal)")
        return self.rig

    @staticmethod
    def _require_chamber(rig: Rig, profile: Profile) -> None:
        if any(s.chamber_setpoint_c is not None for s in profile.steps) and rig.chamber is None:
            raise ValueError(f"profile {profile.name!r} needs a thermal chamber and none is configured")

    def running_batch(self) -> int | None:
        """The batch that has not ended (one plate, one lamp: at most one), or None."""
        return next((bid for bid, seq in self.batches.items() if seq.state not in TERMINAL), None)

    def _require_capacity(self, names: list[str]) -> None:
        """Refuse a batch whose boards demand more samples per second than this PC follows
        (station/daemon/intake_monitor.py): it would fall behind them and lose their samples. The
        rates are the boards' own (identified at the daemon's start or after the last batch); a
        board not identified yet is not counted, and the run's own monitor says so if it falls behind.
        A replay is not refused: its plant waits for the daemon (station/replay), so its speed is no
        demand the boards make."""
        if self.config.replay_of is not None:
            return
        odr = [float(rt.identity.odr_hz) for n in names
               if (rt := self.slots.slots[n]).identity is not None and rt.identity.odr_hz]
        refusal = self.slots.monitor.refuse_start(odr)
        if refusal is not None:
            raise ValueError(refusal)

    def _require_no_batch(self) -> None:
        if self.running_batch() is not None:
            raise ValueError("a batch is already running on this station (one plate, one lamp)")

    def _run(self, rig: Rig, seq: Sequencer) -> None:
        self.slots.bind(seq)
        self.batches[seq.batch_id] = seq
        rig.lamp.reset(seq.batch_id, seq.clock_s())
        seq.start()
        task = asyncio.get_running_loop().create_task(self._forget_when_stored(seq), name=f"forget-{seq.batch_id}")
        self._forgetting.add(task)
        task.add_done_callback(self._forgetting.discard)

    async def _forget_when_stored(self, seq: Sequencer) -> None:
        """Once the batch has ended and everything it published is durable: its raw samples leave
        memory (its results, segments and verdicts stay on the runs), and every batch that ended
        before it leaves this daemon: the page and the API read those from the database."""
        await seq.done.wait()
        try:
            await self.storage.flush()
        except Exception:  # noqa: BLE001 - not durable yet: keep it in memory, the page still shows it
            return
        for d in seq.duts:
            d.release_samples()
        for bid in [b for b, other in self.batches.items() if b < seq.batch_id and other.state in TERMINAL]:
            del self.batches[bid]

    async def close(self) -> None:
        for t in list(self._forgetting):
            t.cancel()

    # ------------------------------------------------------------------ start
    def start_batch(self, profile: str, slots: list[str] | None = None, operator: str = "",
                    trace: Trace | None = None, by: str = "") -> int:
        """Start `profile` on `slots` (None: every slot) for `operator`, the person who runs it
        (required). `trace`: work order, part, lot and label serials (contracts/trace.py). `by`: how it
        was started (a token's name, 'station demo', 'station replay'); the audit's batch.start names
        the person and this."""
        trace = trace or Trace()
        rig = self._require_running()
        if profile not in self.profiles:
            raise ValueError(f"unknown profile {profile!r} (known: {', '.join(self.profiles)})")
        prof = self.profiles[profile]
        self._require_chamber(rig, prof)
        self._require_no_batch()
        names = list(self.slots.slots) if slots is None else list(slots)
        if slots is not None:
            unknown = [n for n in names if n not in self.slots.slots]
            if unknown:
                raise ValueError(f"unknown slot(s): {', '.join(unknown)}")
            if len(set(names)) != len(names):
                raise ValueError("a slot is listed twice")
        if not names:
            raise ValueError("no slots selected")
        if not operator.strip():
            raise ValueError("the operator's name is required: the person who runs the batch is on every record")
        stray = sorted(set(trace.labels) - set(names))
        if stray:
            raise ValueError(f"label serial(s) given for slot(s) not in the batch: {', '.join(stray)}")
        self._require_capacity(names)
        batch_id = int(self.db.create_batch(profile, operator, self.config.snapshot(),
                                            replay_of=self.config.replay_of, trace=trace))
        duts = [DutRun(slot=n, link=self.slots.slots[n].cfg.link, label_serial=trace.labels.get(n)) for n in names]
        self._run(rig, Sequencer(batch_id, prof, duts, rig, self.bus, operator=operator, trace=trace))
        log.info("batch %d: profile %s on %d slot(s) by %r", batch_id, profile, len(names), operator)
        self._audit_start(batch_id, operator, by, {"profile": profile, "slots": slots, **trace.to_json()})
        return batch_id

    def _audit_start(self, batch_id: int, operator: str, by: str, detail: dict[str, object]) -> None:
        """batch.start in the audit trail for every start (REST, demo, replay): the actor is the
        person; `via` says through what. Logged loudly, never raised: the batch has started."""
        try:
            repo.audit_append(self.db, operator, "batch.start", f"batch {batch_id}",
                              {**detail, "operator": operator, "via": by or "station"})
        except Exception:  # noqa: BLE001
            log.critical("audit: could not record the start of batch %d", batch_id, exc_info=True)

    # ------------------------------------------------------------------ retest and resume
    def ended_batch(self, batch_id: int) -> EndedBatch:
        """An ended batch as a retest reads it: from this daemon's sequencer, or from the database
        for a batch a stopped daemon ran (after a restart the failed slots are still retested, not
        404). KeyError: no such batch; ValueError: it has not ended, or another station ran it."""
        seq = self.batches.get(int(batch_id))
        if seq is not None:
            if seq.state not in TERMINAL:
                raise ValueError(f"batch {batch_id} is still {seq.state}: retest once it has ended")
            return EndedBatch(seq.profile.name, [EndedRun(d.slot, (d.verdict or {}).get("verdict"), d.label_serial,
                                                          d.serial if d.identity is not None else None)
                                                 for d in seq.duts], seq.trace)
        detail = repo.batch_detail(self.db, int(batch_id))
        if detail is None:
            raise NotFound(f"unknown batch {batch_id}")
        if detail["state"] not in TERMINAL:
            raise ValueError(f"batch {batch_id} is {detail['state']} in the database: retest once it has ended")
        if detail.get("station") not in (None, "", self.db.station):  # '' : a row from before migration 0005
            raise ValueError(f"batch {batch_id} ran on station {detail['station']!r}: retest it there")
        last: dict[str, dict[str, Any]] = {}  # a stored batch's runs as the database reads them (JSON)
        for run in detail["runs"]:  # the last run of each slot
            last[run["slot"]] = run
        runs = [EndedRun(r["slot"], r.get("verdict"), r.get("label_serial"), r["serial"] if r.get("identity") else None)
                for r in last.values()]
        return EndedBatch(detail["profile"], runs, self.db.batch_trace(int(batch_id)))


    def retest_batch(self, batch_id: int, operator: str, by: str = "", labels: dict[str, str] | None = None,
                     slots: list[str] | None = None) -> int:
        """A new batch of the slots that ended error, fail or marginal in `batch_id` (ended; `slots`:
        some of them), with its profile, work order, part and lot; `operator` runs it.

        `labels` (slot -> label serial) are the parts' labels scanned again for the retest: a slot
        without one runs unchecked, as in any batch. None (a client that does not scan again): the
        labels scanned for the batch, except that a label its board contradicted is refused, never
        reused (scan the part's label again: that is how a label mismatch is mended)."""
        ended = self.ended_batch(batch_id)
        again = [r.slot for r in ended.runs if r.verdict in RETEST_VERDICTS]
        if not again:
            raise ValueError(f"batch {batch_id} has no slot that ended error, fail or marginal to retest")
        if slots is not None:
            others = [n for n in slots if n not in again]
            if others:
                raise ValueError(f"slot(s) {', '.join(others)} did not end error, fail or marginal in batch {batch_id}: "
                                 f"a retest takes {', '.join(again)}")
            again = [n for n in again if n in slots]
            if not again:
                raise ValueError("no slots selected")
        missing = [n for n in again if n not in self.slots.slots]
        if missing:
            raise ValueError(f"slot(s) {', '.join(missing)} are no longer in this config")
        t = ended.trace
        if labels is None:
            wrong = [(r.slot, r.label_serial, r.board_serial) for r in ended.runs if r.slot in again and r.label_serial
                     and r.board_serial is not None and label_mismatch(r.label_serial, r.board_serial) is not None]
            if wrong:
                raise ValueError("; ".join(f"the label scanned for {slot} ({label!r}) is not its board's serial "
                                           f"({serial!r})" for slot, label, serial in wrong)
                                 + ": scan the part's label again (labels)")
            labels = {k: v for k, v in t.labels.items() if k in again}
        trace = Trace.of({**t.fields(), "labels": labels})
        return self.start_batch(ended.profile, again, operator, trace, by=f"{by or 'station'} (retest of batch {batch_id})")


    def resume_batch(self, batch_id: int, operator: str = "") -> int:
        """Resume an interrupted batch at the step after its last completed one. Faulted or finished
        runs stay as they are. Returns the batch id."""
        rig = self._require_running()
        self._require_no_batch()
        rp = self.db.resume_point(int(batch_id))  # KeyError for an unknown batch
        if rp.state != "interrupted":
            raise ValueError(f"batch {batch_id} is {rp.state}: only an interrupted batch can be resumed")
        prof = self.profiles.get(rp.profile)
        if prof is None:
            raise ValueError(f"batch {batch_id} ran profile {rp.profile!r}, which this config does not have")
        self._require_chamber(rig, prof)
        runs = [r for r in rp.runs if r.state == "interrupted"]
        missing = [r.slot for r in runs if r.slot not in self.slots.slots]
        if missing:
            raise ValueError(f"batch {batch_id}: slot(s) {', '.join(missing)} are not in this config")
        if not runs:
            raise ValueError(f"batch {batch_id} has no interrupted DUT run to resume")
        self._require_capacity([r.slot for r in runs])
        duts = [self.restored_dut(r, rp) for r in runs]
        self._run(rig, Sequencer(batch_id, prof, duts, rig, self.bus, operator=operator or rp.operator,
                           start_step=min(rp.next_step, len(prof.steps)), trace=self.db.batch_trace(batch_id)))
        log.info("batch %d: resumed at step %d of %s with %d DUT(s)", batch_id, rp.next_step, rp.profile, len(duts))
        return batch_id


    def restored_dut(self, r: RunPoint, rp: ResumePoint) -> DutRun:
        """A DutRun carrying what the stored run already holds: samples, calibrator state, segments."""
        d = DutRun(slot=r.slot, link=self.slots.slots[r.slot].cfg.link, run_id=r.run_id, expected_serial=r.serial,
                   label_serial=r.label_serial)
        for step, windows in (rp.step_windows or {}).items():
            w = windows.get(r.slot)
            if w and None not in w:
                d.step_windows[int(step)] = (float(w[0]), float(w[1]))
        stored = run_log(self.db, r.run_id)
        if len(stored) == 0:
            return d
        block = SampleBlock(stored.time_s, stored.acc_g, stored.temp_c)
        d.t0, d.last_t, d.resume_t = float(block.time_s[0]), float(block.time_s[-1]), float(block.time_s[-1])
        d.n_samples = len(block)
        d.calibrator = calibrator = self.calibrator_factory()
        # The calibrator is fed as it was live (intake._take): placed samples only, its window starting
        # over after every run of samples that were not placed.
        labels = stored.position if stored.position is not None else np.zeros(len(block), dtype=np.int64)
        replayed = []
        for a, b in label_cuts(labels):
            part = SampleBlock(block.time_s[a:b], block.acc_g[a:b], block.temp_c[a:b])
            d.blocks.append(part)
            d.block_steps.append(max(rp.next_step - 1, 0))
            d.block_positions.append(max(int(labels[a]), -1))
            if labels[a] >= 0:
                calibrator.restart_window()
                replayed += calibrator.update_batch(part.time_s, part.acc_g, part.temp_c)
        steps = {g["index"]: (g["step_index"], g["position"]) for g in (segments_of_run(self.db, r.run_id) or [])}
        for seg in replayed:
            if seg.index in steps:
                step, pos = steps[seg.index]
                d.segments.append(annotate_segment(seg, pos))
                d.segment_steps.append(step)
            else:
                # Logged from samples whose segment event the stop did not let commit: it belongs to
                # the interrupted step (a completed step's segments commit before its end) and to the
                # position the stored samples were taken at.
                k = min(int(np.searchsorted(stored.time_s, seg.t_end_s)), len(stored) - 1)
                pos = int(stored.position[k]) if stored.position is not None and stored.position[k] >= 0 else None
                d.unstored_segments.append((annotate_segment(seg, pos), rp.next_step))
        d.hold_calibrator = True  # fed again once the resumed step is logging (intake.ingest)
        return d
