"""Hooks between the daemon and the decision (station/decisions/verdicts.py, which stays pure).

The verdict's moment (design 8): a run is judged ONCE, when it ends, from everything it stored
(`verdicts.final_verdict` of a `RunRecord`), never earlier. The daemon calls:
- `judge_final(ctx, seq)` when the batch releases its DUTs (station/daemon/run_end.py
  `RunEnd.release_duts`, its last line), after every DUT's end state is set (done, faulted,
  interrupted by an abort, a failure, a daemon stop): each run gets its verdict, on the DUT for
  the batch status and as one DutVerdict event: the one record the database numbers for the MES
  (result_seq) and the webhook sends. The analysis before it publishes results WITHOUT a verdict,
  so a later fault, abort or failed verification can never leave a pass behind;
- `judge_interrupted_runs(ctx, batch_ids)` at daemon start (`Station.judge_interrupted`), for the
  runs a killed daemon left running (marked interrupted by the database): error, "interrupted:
  station restarted". A batch resumed later judges its runs again at its end: a new record that
  supersedes the error;
(The batch status's verdict counts, sorting list and time left are station/daemon/progress.py.)
Profiles without analysis (validation) are not judged, at the end or at a restart: nothing was
measured for a verdict. A batch whose profile is known neither to the station nor to the config
stored with the batch is not judged at a restart either (logged): guessing "thermal" sent
validation runs to the MES as errors (verdict_context.py says how).

`ctx` is a VerdictContext (verdict_context.py): every part of the station read here, typed, so a
renamed station attribute fails where the Station is built, not at a restart.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from contracts.events import DutVerdict
from contracts.types import Identity
from station.config import ProfileConfig
from station.decisions.limits import ProductSpec
from contracts.selfcal_opinion import SELFCAL_OPINION_SHAPE
from station.decisions.verdict_context import BoardOpinions, EndedBatch, VerdictContext, VerdictStore
from station.decisions.verdicts import RunRecord, final_verdict
from station.profiles import Profile, profile_from_config
from station.science.residual import DEFAULT_OPERATING_RANGE_C

if TYPE_CHECKING:  # the records the moment reads, never builds
    from station.daemon.dut_run import DutRun

log = logging.getLogger("station.decisions.moment")

# A DUT's identity as the moment meets it: the board's reply on a live run, the dict stored with a
# run the database hands back at a restart, or nothing (a board that never answered).
IdentityLike = Identity | Mapping[str, object] | None


def _sensor(identity: IdentityLike) -> str | None:
    """The sensor of an identity (contracts.types.Identity, or the dict stored with a run)."""
    if identity is None:
        return None
    if isinstance(identity, Identity):
        return identity.sensor
    sensor = identity.get("sensor")
    return sensor if isinstance(sensor, str) else None


def spec_of(ctx: VerdictContext, identity: IdentityLike, part_number: str = "") -> ProductSpec | None:
    """The product whose limits judge this DUT: its batch's part number first, else its sensor."""
    return ctx.product_for(_sensor(identity), part_number or None)


def operating_range_c(ctx: VerdictContext, identity: IdentityLike, part_number: str = "") -> float:
    """Full Range of eq. 10 for this DUT's product (default 70 C, martinez2022's -10..60 C)."""
    spec = spec_of(ctx, identity, part_number)
    return float(spec.operating_range_c) if spec is not None else DEFAULT_OPERATING_RANGE_C


def attempt_of(db: VerdictStore, run_id: int | None) -> int | None:
    """Attempt number of a run (the database's column); None for a run the database does not know
    or cannot tell now (a database error is logged: the verdict still goes out, without attempt,
    and the other DUTs of the batch are still judged)."""
    if run_id is None:
        return None
    try:
        return int(db.run_attempt(run_id))
    except KeyError:
        return None
    except Exception:  # noqa: BLE001 - any driver's error: one run's attempt, not every verdict
        log.warning("run %s: attempt number not read from the database", run_id, exc_info=True)
        return None


def _link_stats(ctx: VerdictContext, d: DutRun) -> dict[str, Any]:
    live = ctx.live_link_stats(d.slot)
    return dict(live) if live is not None else dict(d.link_stats or {})


def slim(v: Mapping[str, object]) -> dict[str, object]:
    """The verdict without the list of every passing check: what the batch status carries for each
    slot (polled by every page; the full list is stored with the run, verdict_detail)."""
    return {k: x for k, x in v.items() if k != "checks"}


def end_of(seq: EndedBatch, d: DutRun) -> tuple[str, str]:
    """(end state, reason) of a DUT run once its batch has released it. Only a DUT that ended
    `done` in a batch that finished can pass; every other end names why it is error."""
    ending = seq.ending or seq.state
    if d.state == "faulted":
        return "faulted", f"faulted: {d.fault_reason}" if d.fault_reason else "faulted"
    if d.state == "done" and ending == "finished":
        return "done", ""
    why = d.fault_reason or f"batch {ending}" + (f": {seq.error}" if seq.error else "")
    if ending == "interrupted":
        why += " (resumable: station serve --resume)"
    return (d.state if d.state != "done" else ending), f"{why}, DUT incomplete"


def board_opinion(seq: EndedBatch, d: DutRun) -> dict[str, object] | None:
    """The board calibrator's opinion of this run (profile option board_selfcal; the batch's
    station/daemon/board_selfcal.py BoardCalibrators), None with the option off. With the option on
    and no reading at all (a batch that kept none), an error opinion: never a pass."""
    if not seq.profile.board_selfcal:
        return None
    cal = getattr(seq, "board_calibrators", None)  # a Sequencer's; a test's plain batch may have none
    if isinstance(cal, BoardOpinions):
        return dict(cal.opinion_of(d.slot))
    return {"shape": SELFCAL_OPINION_SHAPE, "applicable": True, "error": "the batch kept no board calibrator readings"}


def programmed_by_profile(seq: EndedBatch, d: DutRun) -> bool:
    """Does this run's verdict require program and verify? Its profile's program step, unless the
    board could not take what the step writes: an SFEM profile's board without the version-2 record
    (its program record says `not_applicable`) is judged as an SFEM run only (issue 42)."""
    if seq.profile.program_step is None:
        return False
    return not (d.program is not None and not d.program.programmed and d.program.readback.get("not_applicable") is True)


def run_record(ctx: VerdictContext, seq: EndedBatch, d: DutRun) -> RunRecord:
    """The run as the verdict reads it: its records in the JSON form they are stored in, so a run
    judged live and one judged again from the database read the very same figures (readings.py
    reads them by each measurement's declaration)."""
    state, why = end_of(seq, d)
    return RunRecord(analysis=seq.profile.analysis, program_verify=programmed_by_profile(seq, d),
                     end_state=state, end_reason=why, result=None if d.result is None else d.result.to_json(),
                     link_stats=_link_stats(ctx, d), n_samples=int(d.n_samples),
                     program=None if d.program is None else d.program.to_json(), verification=d.verification,
                     board_selfcal=board_opinion(seq, d))


def _judge(ctx: VerdictContext, batch_id: int, slot: str, serial: str | None, run_id: int | None, run: RunRecord,
           spec: ProductSpec | None, attempt: int | None) -> dict[str, Any]:
    """The final verdict of one run as the MES record carries it; published when the run exists.
    No database call: the verdict must go out (to the journal) while the database is down."""
    v = final_verdict(run, spec).to_json()
    v["attempt"] = attempt
    v["run_id"] = run_id
    if run_id is not None:
        ctx.bus.publish(DutVerdict(batch_id, slot=slot, serial=serial, verdict=v))
    return v


def judge_final(ctx: VerdictContext, seq: EndedBatch) -> None:
    """The final verdict of every DUT of a released batch (see module doc), once per run."""
    if seq.profile.analysis == "none":
        return
    part = seq.trace.part_number
    for d in seq.duts:
        if d.verdict is not None:
            continue  # judged once (release runs once; a second call must not send a second record)
        d.verdict = slim(_judge(ctx, seq.batch_id, d.slot, d.serial, d.run_id, run_record(ctx, seq, d),
                                spec_of(ctx, d.identity, part), d.attempt))


def profile_of_batch(ctx: VerdictContext, name: str, snapshot: Mapping[str, object] | None) -> Profile | None:
    """The profile a stored batch ran: the station's by name, else the one in the config stored
    with the batch (a site profile removed from the config since); None when neither knows it."""
    prof = ctx.profiles.get(name)
    if prof is not None:
        return prof
    profiles = (snapshot or {}).get("profiles")
    stored = profiles.get(name) if isinstance(profiles, dict) else None
    if not isinstance(stored, dict):
        return None
    try:
        return profile_from_config(name, ProfileConfig.model_validate(stored))
    except ValueError:  # pydantic's ValidationError: a snapshot this software cannot read
        return None


def judge_interrupted_runs(ctx: VerdictContext, batch_ids: list[int], reason: str = "station restarted") -> int:
    """Error verdicts for the runs a killed daemon left running (the database marked them
    interrupted at start): their end is now. Runs of a profile with no analysis are not judged
    (see the module doc). Returns how many runs were judged."""
    n = 0
    for bid in batch_ids:
        try:
            rp = ctx.db.resume_point(int(bid))
            part = ctx.db.batch_trace(int(bid)).part_number
        except KeyError:
            continue
        except Exception:  # noqa: BLE001 - a database error on one batch: the others are still judged
            log.warning("batch %s: interrupted runs not judged (database)", bid, exc_info=True)
            continue
        prof = profile_of_batch(ctx, rp.profile, rp.config_snapshot)
        if prof is None:
            log.warning("batch %s: profile %r unknown to this station and its stored config: its interrupted "
                        "runs are not judged", bid, rp.profile)
            continue
        if prof.analysis == "none":
            continue
        for r in rp.runs:
            if r.state != "interrupted":
                continue
            run = RunRecord(analysis=prof.analysis, program_verify=prof.program_step is not None,
                            end_state="interrupted",
                            end_reason=f"interrupted: {reason} during the batch, DUT incomplete "
                                       "(resumable: station serve --resume)")
            identity = r.identity or {"sensor": r.sensor}
            _judge(ctx, int(bid), r.slot, r.serial, r.run_id, run, spec_of(ctx, identity, part),
                   attempt_of(ctx.db, r.run_id))
            n += 1
    return n


def judge_unjudged_runs(ctx: VerdictContext, exclude_batches: list[int]) -> int:
    """At daemon start: every run that ended with no verdict stored gets one now (error: what
    was decided then is gone, the part is retested), so every run that ended reaches the MES with
    exactly one final verdict, whatever failed when. With the station's journal a verdict is lost
    only when the journal's own disk failed too. Returns how many runs were judged."""
    try:
        lost = ctx.db.unjudged_runs(list(exclude_batches))
    except Exception:  # noqa: BLE001 - logged; the next start tries again
        log.warning("runs without a verdict not looked up (database)", exc_info=True)
        return 0
    n = 0
    for bid, run_ids in lost.items():
        try:
            rp = ctx.db.resume_point(int(bid))
            part = ctx.db.batch_trace(int(bid)).part_number
        except Exception:  # noqa: BLE001 - one batch; the others are still judged
            log.warning("batch %s: runs without a verdict not judged (database)", bid, exc_info=True)
            continue
        prof = profile_of_batch(ctx, rp.profile, rp.config_snapshot)
        if prof is None or prof.analysis == "none":
            continue
        wanted = set(run_ids)
        for r in rp.runs:
            if r.run_id not in wanted:
                continue
            why = (f"{r.fault_reason}; " if r.fault_reason else "") + \
                "its verdict was not stored before the station stopped (judged at restart): retest"
            run = RunRecord(analysis=prof.analysis, program_verify=prof.program_step is not None,
                            end_state="interrupted" if r.state == "done" else r.state, end_reason=why)
            _judge(ctx, int(bid), r.slot, r.serial, r.run_id, run, spec_of(ctx, r.identity or {"sensor": r.sensor}, part),
                   attempt_of(ctx.db, r.run_id))
            log.warning("batch %s run %s (%s): no verdict was stored: judged error at restart", bid, r.run_id, r.serial)
            n += 1
    return n


__all__ = ["judge_final", "judge_interrupted_runs", "judge_unjudged_runs", "run_record", "board_opinion",
           "programmed_by_profile", "end_of", "slim", "operating_range_c", "attempt_of",
           "spec_of", "profile_of_batch"]
