"""Hooks between the daemon and the decision (station/decisions/verdicts.py, which stays pure).

The verdict's moment (design 8): a run is judged ONCE, when it ends, from everything it stored
(`verdicts.final_verdict` of a `RunRecord`), never earlier. The supervisor calls:
- `judge_final(station, seq)` when the batch releases its DUTs, after every DUT's end state is set
  (done, faulted, interrupted by an abort, a failure, a daemon stop): each run gets its verdict, on
  the DUT for the batch status and as one DutVerdict event: the one record the database numbers for
  the MES (result_seq) and the webhook sends. The analysis before it publishes results WITHOUT a
  verdict, so a later fault, abort or failed verification can never leave a pass behind;
- `judge_interrupted_runs(station, batch_ids)` at daemon start, for the runs a killed daemon left
  running (marked interrupted by the database): error, "interrupted: station restarted". A batch
  resumed later judges its runs again at its end: a new record that supersedes the error;
(The batch status's verdict counts, sorting list and time left are station/daemon/progress.py.)
Profiles without analysis (validation) are not judged: nothing was measured for a verdict.
"""

from __future__ import annotations

import logging
from typing import Any

from contracts.events import DutVerdict
from station.science.residual import DEFAULT_OPERATING_RANGE_C
from station.decisions.verdicts import RunRecord, final_verdict

log = logging.getLogger("station.decisions.moment")


def _spec(station: Any, identity: Any):
    sensor = getattr(identity, "sensor", None) if not isinstance(identity, dict) else identity.get("sensor")
    return station.config.product_for(sensor)


def operating_range_c(station: Any, identity: Any) -> float:
    """Full Range of eq. 10 for this DUT's product (default 70 C, martinez2022's -10..60 C)."""
    spec = _spec(station, identity)
    return float(spec.operating_range_c) if spec is not None else DEFAULT_OPERATING_RANGE_C


def attempt_of(db: Any, run_id: int | None) -> int | None:
    """Attempt number of a run (the database's column); None for a run the database does not know."""
    if run_id is None:
        return None
    try:
        return int(db.run_attempt(run_id))
    except KeyError:
        return None


def _link_stats(station: Any, d: Any) -> dict:
    slot = station.slots.get(d.slot)
    drv = getattr(slot, "driver", None)
    if drv is not None and hasattr(drv, "stats"):
        return drv.stats.as_dict()
    return dict(d.link_stats or {})


def slim(v: dict) -> dict:
    """The verdict without the list of every passing check: what the batch status carries for each
    slot (polled by every page; the full list is stored with the run, verdict_detail)."""
    return {k: x for k, x in v.items() if k != "checks"}


def end_of(seq: Any, d: Any) -> tuple[str, str]:
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


def run_record(station: Any, seq: Any, d: Any) -> RunRecord:
    state, why = end_of(seq, d)
    return RunRecord(analysis=seq.profile.analysis, program_verify=seq.profile.program_step is not None,
                     end_state=state, end_reason=why, result=d.result, link_stats=_link_stats(station, d),
                     n_samples=int(d.n_samples), program=d.program, verification=d.verification)


def _judge(station: Any, batch_id: int, slot: str, serial: str | None, run_id: int | None, run: RunRecord,
           identity: Any) -> dict:
    """The final verdict of one run as the MES record carries it; published when the run exists."""
    v = final_verdict(run, _spec(station, identity)).to_json()
    v["attempt"] = attempt_of(station.db, run_id)
    v["run_id"] = run_id
    if run_id is not None:
        station.bus.publish(DutVerdict(batch_id, slot=slot, serial=serial, verdict=v))
    return v


def judge_final(station: Any, seq: Any) -> None:
    """The final verdict of every DUT of a released batch (see module doc), once per run."""
    if seq.profile.analysis == "none":
        return
    for d in seq.duts:
        if getattr(d, "verdict", None) is not None:
            continue  # judged once (release runs once; a second call must not send a second record)
        d.verdict = slim(_judge(station, seq.batch_id, d.slot, d.serial, d.run_id, run_record(station, seq, d),
                                d.identity))


def judge_interrupted_runs(station: Any, batch_ids: list[int], reason: str = "station restarted") -> int:
    """Error verdicts for the runs a killed daemon left running (the database marked them
    interrupted at start): their end is now. Returns how many runs were judged."""
    n = 0
    resume_point = getattr(station.db, "resume_point", None)
    if resume_point is None:
        return 0
    profiles = getattr(station, "_profiles", {})
    for bid in batch_ids:
        try:
            rp = resume_point(int(bid))
        except KeyError:
            continue
        prof = profiles.get(rp.profile)
        analysis = prof.analysis if prof is not None else "thermal"
        if analysis == "none":
            continue
        for r in rp.runs:
            if r.state != "interrupted":
                continue
            run = RunRecord(analysis=analysis, program_verify=getattr(prof, "program_step", None) is not None,
                            end_state="interrupted",
                            end_reason=f"interrupted: {reason} during the batch, DUT incomplete "
                                       "(resumable: station serve --resume)")
            _judge(station, int(bid), r.slot, r.serial, r.run_id, run, r.identity or {"sensor": r.sensor})
            n += 1
    return n


__all__ = ["judge_final", "judge_interrupted_runs", "run_record", "end_of", "slim", "operating_range_c", "attempt_of"]
