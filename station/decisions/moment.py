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
- `batch_extras(station, seq)` for the batch status: verdict counts, the sorting list (slot ->
  tray) and the time left in the step and the batch.
Profiles without analysis (validation) are not judged: nothing was measured for a verdict.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any

from contracts.events import DutVerdict
from station.daemon.program_verify import uses_program_verify
from station.science.residual import DEFAULT_OPERATING_RANGE_C
from station.decisions.verdicts import RunRecord, final_verdict, summarize

log = logging.getLogger("station.decisions.moment")


def _spec(station: Any, identity: Any):
    sensor = getattr(identity, "sensor", None) if not isinstance(identity, dict) else identity.get("sensor")
    return station.config.product_for(sensor)


def operating_range_c(station: Any, identity: Any) -> float:
    """Full Range of eq. 10 for this DUT's product (default 70 C, martinez2022's -10..60 C)."""
    spec = _spec(station, identity)
    return float(spec.operating_range_c) if spec is not None else DEFAULT_OPERATING_RANGE_C


def attempt_of(db: Any, run_id: int | None, serial: str | None) -> int | None:
    """Attempt number of a run: the database's column, or counted in the in-memory stand-in."""
    if run_id is None:
        return None
    fn = getattr(db, "run_attempt", None)
    if fn is not None:
        try:
            return int(fn(run_id))
        except KeyError:
            return None
    runs = getattr(db, "runs", None)  # MemoryDb
    if isinstance(runs, dict) and serial:
        return sum(1 for rid, r in runs.items() if r.get("serial") == serial and rid <= run_id)
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
    return RunRecord(analysis=seq.profile.analysis, program_verify=uses_program_verify(seq.profile),
                     end_state=state, end_reason=why, result=d.result, link_stats=_link_stats(station, d),
                     n_samples=int(d.n_samples), program=d.program, verification=d.verification)


def _judge(station: Any, batch_id: int, slot: str, serial: str | None, run_id: int | None, run: RunRecord,
           identity: Any) -> dict:
    """The final verdict of one run as the MES record carries it; published when the run exists."""
    v = final_verdict(run, _spec(station, identity)).to_json()
    v["attempt"] = attempt_of(station.db, run_id, serial)
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
            run = RunRecord(analysis=analysis, program_verify=uses_program_verify(prof),
                            end_state="interrupted",
                            end_reason=f"interrupted: {reason} during the batch, DUT incomplete "
                                       "(resumable: station serve --resume)")
            _judge(station, int(bid), r.slot, r.serial, r.run_id, run, r.identity or {"sensor": r.sensor})
            n += 1
    return n


# ------------------------------------------------------------------------------- batch status
def _segment_step_need_s(d: Any, odr_hz: float) -> float | None:
    """Sample seconds this DUT still needs to log a segment, from its calibrator's state and the
    temperature trend (the filtered gradient must fall under the limit first)."""
    cal = d.calibrator
    if cal is None:
        return None
    c = cal.config
    st = getattr(cal, "state", "settling")
    n_disc = int(getattr(cal, "_n_disc", 0))
    n_avg = int(getattr(cal, "_n_avg", 0))
    need = (max(0, c.discard_samples - n_disc) + max(0, c.average_samples - n_avg)) / odr_hz
    if st == "settling":
        g = abs(float(getattr(cal, "gradient_c_per_min", 0.0)))
        lim = float(c.gradient_limit_c_per_min)
        tau_s = _gradient_tau_s(d, g)
        if g > lim:
            need += tau_s * math.log(g / lim)
    return need


def _gradient_tau_s(d: Any, g: float, default_s: float = 300.0) -> float:
    """Time constant of the gradient's decay from two looks at least 30 sample seconds apart
    (the plate approaches its temperature exponentially); a default until the trend is known."""
    now = d.last_t or 0.0
    hist = d.__dict__.setdefault("_grad_hist", [])
    if not hist or now - hist[-1][0] >= 30.0:
        hist.append((now, g))
        del hist[:-2]
    if len(hist) == 2:
        (t1, g1), (t2, g2) = hist
        if g2 > 0 and g1 > g2 and t2 > t1:
            return min(3600.0, max(30.0, (t2 - t1) / math.log(g1 / g2)))
    return default_s


def time_left(station: Any, seq: Any) -> dict:
    """Estimated sample and wall seconds left in the step and the batch.

    Step: the slowest pending DUT's need (segment: calibrator state + temperature trend; static /
    none: dwell left), capped by the step timeout. Later steps: static/none their settle + dwell;
    segment steps the mean duration of this batch's completed segment steps of the same kind
    (changing the plate temperature or not; else half the timeout), capped by their timeouts.
    Wall = sample time / the configured speed."""
    from station.daemon.sequencer import TERMINAL

    steps = seq.profile.steps
    speed = float(station.config.timing.speed) or 1.0
    if seq.state in TERMINAL or seq.step is None:
        return {"step_s": 0.0 if seq.state in TERMINAL else None, "batch_s": 0.0 if seq.state in TERMINAL else None,
                "step_wall_s": None, "batch_wall_s": None}
    step = seq.step
    elapsed = max(0.0, seq.clock_s() - seq.step_clock_start) if seq.state == "logging" else 0.0
    needs = []
    for d in seq.live_duts:
        if seq.state == "logging" and seq.dut_step_done(d, step):
            continue
        odr = float(getattr(d.identity, "odr_hz", 0) or 3.125)
        if step.require == "segment":
            n = _segment_step_need_s(d, odr)
        else:
            n = max(0.0, step.dwell_s + (step.settle_s if step.require == "static" else 0.0) - elapsed)
        if n is not None:
            needs.append(n)
    step_left = min(max(needs, default=0.0), max(0.0, step.timeout_s - elapsed))
    def heats(i: int) -> bool:  # the step changes the plate's temperature (lamp or set point)
        prev_lamp, prev_sp = (steps[i - 1].lamp, steps[i - 1].chamber_setpoint_c) if i > 0 else (False, None)
        return steps[i].lamp != prev_lamp or steps[i].chamber_setpoint_c != prev_sp

    done: dict[bool, list[float]] = {True: [], False: []}
    for i in range(seq.step_index):
        if steps[i].require != "segment":
            continue
        spans = [d.step_windows[i] for d in seq.duts if i in d.step_windows and math.isfinite(d.step_windows[i][0])]
        done[heats(i)] += [b - a for a, b in spans]
    rest = 0.0
    for i in range(seq.step_index + 1, len(steps)):
        s = steps[i]
        if s.require == "segment":
            # like the completed steps of the same kind (temperature change or not), else half the timeout
            seen = done[heats(i)]
            rest += min(s.timeout_s, sum(seen) / len(seen) if seen else s.timeout_s / 2)
        else:
            rest += min(s.timeout_s, s.settle_s + s.dwell_s)
    batch_left = step_left + rest
    return {"step_s": step_left, "batch_s": batch_left, "step_wall_s": step_left / speed,
            "batch_wall_s": batch_left / speed, "estimated_at": time.time()}


def batch_extras(station: Any, seq: Any) -> dict:
    """Decision summary, sorting list and time left for GET /api/batches/{id}."""
    verdicts = [getattr(d, "verdict", None) for d in seq.duts]
    sorting = [
        {"slot": d.slot, "serial": d.serial, "verdict": v.get("verdict"), "grade": v.get("grade"), "tray": v.get("tray"),
         "reason": v.get("reason"), "attempt": v.get("attempt")}
        for d, v in zip(seq.duts, verdicts) if v
    ]
    try:
        left = time_left(station, seq)
    except Exception as exc:  # noqa: BLE001 - an estimate must never break the status
        left = {"error": f"{type(exc).__name__}: {exc}"}
    return {"decision": summarize(verdicts), "sorting": sorting, "time_left": left}


__all__ = ["judge_final", "judge_interrupted_runs", "run_record", "end_of", "slim", "batch_extras", "operating_range_c",
           "attempt_of", "time_left"]
