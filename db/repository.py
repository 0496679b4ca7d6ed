"""Read side for the web page, REST API and MES, plus the MES outbox.

Every function takes a db.Database and returns plain JSON-ready dicts (times as ISO 8601 UTC), or
None for an unknown serial / run / batch so the web layer can answer 404.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import func, insert, or_, select, update
from sqlalchemy.orm import aliased

from db.database import Database
from db.models import (
    NO_ATTEMPT,
    Batch,
    Dut,
    DutRun,
    Outbox,
    ProgramVerifyRow,
    SampleChunk,
    SegmentRow,
    SfemResultRow,
    ThermalResultRow,
    utcnow,
)
from contracts.sfem_result import SFEM_RESULT_SHAPE
from contracts.trace import Trace
from contracts.types import AXES

PREFERRED_THERMAL = ("offline", "streaming")  # the offline fit is the better estimate when both exist


def _iso(t: datetime | None) -> str | None:
    return None if t is None else t.isoformat()


def thermal_json(row: ThermalResultRow) -> dict:
    out: dict[str, Any] = {"id": row.id, "method": row.method, "n_segments": row.n_segments, "created_at": _iso(row.created_at)}
    for ax in AXES:
        out[ax] = {
            "tdb_mg_per_c": getattr(row, f"tdb_{ax}_mg_per_c"),
            "tdsf_ppm_per_c": getattr(row, f"tdsf_{ax}_ppm_per_c"),
            "tdb_sigma_mg_per_c": getattr(row, f"tdb_sigma_{ax}_mg_per_c"),
            "tdsf_sigma_ppm_per_c": getattr(row, f"tdsf_sigma_{ax}_ppm_per_c"),
            "tdsf_clamped": getattr(row, f"tdsf_clamped_{ax}"),
        }
    return out


def sfem_json(rows: list[SfemResultRow]) -> dict | None:
    """The SFEM result as reported: the record the writer stored (contracts/sfem_result.py
    SfemResult: its record row plus one row per step, put back together), or, for rows stored
    before that shape, one fit or {"steps": [...], "polynomial_coefficients": ...}."""
    if not rows:
        return None
    steps = [r for r in rows if r.temperature_step is not None]
    record = next((r for r in rows if r.temperature_step is None
                   and (r.parameters or {}).get("shape") == SFEM_RESULT_SHAPE), None)
    if record is not None:
        ordered = sorted(steps, key=lambda r: (r.temperature_step, r.id))
        return {**dict(record.parameters or {}), "steps": [dict(r.parameters or {}) for r in ordered]}
    poly = [r for r in rows if r.polynomial_coefficients is not None]
    if len(rows) == 1 and (len(steps) <= 1):
        out = dict(rows[0].parameters or {})
        out.setdefault("temperature_step", rows[0].temperature_step)
        return out
    out = {"steps": [dict(r.parameters or {}) for r in sorted(steps, key=lambda r: (r.temperature_step, r.id))]}
    if poly:
        out["polynomial_coefficients"] = poly[-1].polynomial_coefficients
    return out


def _run_results(s: Any, run_id: int) -> dict:
    """Latest thermal result per method and the latest SFEM rows of one run."""
    rows = s.scalars(select(ThermalResultRow).where(ThermalResultRow.run_id == run_id).order_by(ThermalResultRow.id)).all()
    by_method: dict[str, dict] = {}
    for r in rows:
        by_method[r.method] = thermal_json(r)
    preferred = next((m for m in PREFERRED_THERMAL if m in by_method), next(iter(by_method), None))
    sfem_rows = s.scalars(select(SfemResultRow).where(SfemResultRow.run_id == run_id).order_by(SfemResultRow.id)).all()
    if sfem_rows:  # only the rows of the newest report (same created_at)
        newest = sfem_rows[-1].created_at
        sfem_rows = [r for r in sfem_rows if r.created_at == newest]
    thermal = None
    if preferred is not None:
        thermal = {ax: by_method[preferred][ax] for ax in AXES}
    pv = s.scalars(select(ProgramVerifyRow).where(ProgramVerifyRow.run_id == run_id)).one_or_none()
    return {"thermal": thermal, "thermal_method": preferred, "thermal_by_method": by_method, "sfem": sfem_json(sfem_rows),
            "program_verify": None if pv is None else program_verify_json(pv)}


def program_record(db: Database, run_id: int) -> dict | None:
    """The program step's own record of one run (what the driver reported: the coefficients
    written, comp_from_t, error kind), as the daemon stored it; None if the run was not programmed."""
    with db.session() as s:
        row = s.scalars(select(ProgramVerifyRow).where(ProgramVerifyRow.run_id == run_id)).one_or_none()
        return None if row is None else dict(row.program or {})


def program_verify_json(row: ProgramVerifyRow) -> dict:
    """Program and verify of one run: programmed (CRC written = read back), compensation on, the
    coefficients written (TDB mg/C, TDSF ppm/C per axis), and the verified drift error E
    before/after per axis (mg)."""
    prog = row.program or {}
    return {
        "programmed": row.programmed,
        "written": {k: dict(zip(AXES, prog[k])) for k in ("tdb_mg_per_c", "tdsf_ppm_per_c")
                    if isinstance(prog.get(k), list) and len(prog[k]) == 3} or None,
        "crc": row.crc,
        "readback_crc": row.readback_crc,
        "readback_identical": bool(row.programmed and row.crc is not None and row.crc == row.readback_crc),
        "comp_on": row.comp_on,
        "attempts": row.attempts,
        "error_kind": row.error_kind or None,
        "error": row.error or None,
        "verified": row.verified,
        "e_before_mg": {ax: getattr(row, f"e_before_{ax}_mg") for ax in AXES},
        "e_after_mg": {ax: getattr(row, f"e_after_{ax}_mg") for ax in AXES},
        "flags": list(row.flags or []),
        "updated_at": _iso(row.updated_at),
    }


VALID_VERDICTS = ("pass", "marginal", "fail")  # an attempt that ended in error is not a valid result


def verdict_json(r: DutRun) -> dict:
    """The station's decision on a run (None fields while it is not judged)."""
    return _decision_json(r, r.attempt, r.verdict_reason)


def record_verdict_json(h: Any, attempt: int) -> dict:
    """The decision of one verdict record (verdict_history row), shaped as verdict_json."""
    return _decision_json(h, attempt, h.reason)


def _decision_json(row: Any, attempt: int, reason: str | None) -> dict:
    """A dut_run or verdict_history row's decision columns (the two name the reason differently)."""
    return {
        "attempt": attempt,
        "verdict": row.verdict,
        "grade": row.grade,
        "tray": row.tray,
        "reason": reason or None,
        "limits_name": row.limits_name,
        "limits_version": row.limits_version,
        "judged_at": _iso(row.judged_at),
    }


def _run_json(r: DutRun, serial: str, n_segments: int | None = None) -> dict:
    out = {
        "id": r.id,
        "batch_id": r.batch_id,
        "station": r.station,
        "slot": r.slot,
        "serial": serial,
        "state": r.state,
        "fault_reason": r.fault_reason,
        "identity": r.identity,
        "n_samples": r.n_samples,
        "lost_samples": r.lost_samples,
        "samples_pruned_at": _iso(r.samples_pruned_at),
        "result_seq": r.result_seq,
        "started_at": _iso(r.started_at),
        "ended_at": _iso(r.ended_at),
        "label_serial": r.label_serial,
        # what measured it (None: not stored, a run from before migration 0009)
        "software_version": r.software_version,
        "firmware_version": r.firmware_version,
        "holder": r.holder,
        **verdict_json(r),
    }
    if n_segments is not None:
        out["n_segments"] = n_segments
    return out


def trace_json(b: Batch, with_labels: bool = True) -> dict:
    """A batch's traceability fields (contracts/trace.py): work order, part number, revision, lot
    (and the label serials scanned per slot)."""
    out: dict[str, Any] = dict(Trace.of(b).fields())
    if with_labels:
        out["labels"] = dict(b.labels or {})
    return out


def _nseg_subquery() -> Any:
    return select(SegmentRow.run_id, func.count(SegmentRow.id).label("n")).group_by(SegmentRow.run_id).subquery()


def dut_by_serial(db: Database, serial: str) -> dict | None:
    """The DUT with the results of its latest run that has any (design 5.3 GET /api/duts/{serial})."""
    with db.session() as s:
        dut = s.scalars(select(Dut).where(Dut.serial == serial)).one_or_none()
        if dut is None:
            return None
        n_runs = s.scalar(select(func.count(DutRun.id)).where(DutRun.dut_id == dut.id,
                                                              DutRun.batch_id.in_(_real_batches()))) or 0
        # a run stopped for a label mismatch (attempt 0) is in the history, but it never tested the part
        n_attempts = s.scalar(select(func.count(DutRun.id)).where(DutRun.dut_id == dut.id, _is_attempt(),
                                                                  DutRun.batch_id.in_(_real_batches()))) or 0
        # the DUT's result is its latest VALID attempt (judged pass/marginal/fail); a retest that
        # faulted does not hide the attempt before it. Never judged: the latest attempt with a record
        # or with results.
        latest = s.scalars(
            select(DutRun).where(DutRun.dut_id == dut.id, DutRun.verdict.in_(VALID_VERDICTS),
                                 DutRun.batch_id.in_(_real_batches())).order_by(DutRun.id.desc())
        ).first()
        if latest is None:  # results are data of their run (no result_seq until its verdict)
            with_results = select(ThermalResultRow.run_id).union(select(SfemResultRow.run_id))
            latest = s.scalars(
                select(DutRun).where(DutRun.dut_id == dut.id, _is_attempt(),
                                     or_(DutRun.result_seq.is_not(None), DutRun.id.in_(with_results)))
                .order_by(DutRun.id.desc())
            ).first()
        out = {
            "serial": dut.serial,
            "sensor": dut.sensor,
            "first_seen": _iso(dut.first_seen),
            "last_seen": _iso(dut.last_seen),
            "n_runs": n_runs,
            "result_run_id": None if latest is None else latest.id,
            "thermal": None,
            "thermal_method": None,
            "thermal_by_method": {},
            "sfem": None,
            "attempts": n_attempts,
        }
        if latest is not None:
            out.update(_run_results(s, latest.id))
            out.update(verdict_json(latest))
        return out


def search_duts(db: Database, serial_like: str | None = None, limit: int = 50) -> list[dict]:
    """DUT summaries whose serial contains serial_like (case-insensitive), most recently seen first."""
    with db.session() as s:
        nruns = select(DutRun.dut_id, func.count(DutRun.id).label("n")).group_by(DutRun.dut_id).subquery()
        q = select(Dut, nruns.c.n).outerjoin(nruns, nruns.c.dut_id == Dut.id)
        if serial_like:
            q = q.where(func.lower(Dut.serial).contains(serial_like.lower(), autoescape=True))
        q = q.order_by(Dut.last_seen.desc(), Dut.id.desc()).limit(max(1, min(limit, 1000)))
        return [
            {"serial": d.serial, "sensor": d.sensor, "first_seen": _iso(d.first_seen), "last_seen": _iso(d.last_seen),
             "n_runs": int(n or 0)}
            for d, n in s.execute(q).all()
        ]


def runs_of_dut(db: Database, serial: str) -> list[dict] | None:
    """Every run of a serial, newest first; None for an unknown serial."""
    with db.session() as s:
        dut = s.scalars(select(Dut).where(Dut.serial == serial)).one_or_none()
        if dut is None:
            return None
        nseg = _nseg_subquery()
        rows = s.execute(
            select(DutRun, nseg.c.n)
            .outerjoin(nseg, nseg.c.run_id == DutRun.id)
            .where(DutRun.dut_id == dut.id)
            .order_by(DutRun.id.desc())
        ).all()
        return [_run_json(r, dut.serial, int(n or 0)) for r, n in rows]


def run_detail(db: Database, run_id: int) -> dict | None:
    """One run with its results and its batch's profile."""
    with db.session() as s:
        row = s.execute(
            select(DutRun, Dut.serial, Batch).join(Dut, Dut.id == DutRun.dut_id).join(Batch, Batch.id == DutRun.batch_id)
            .where(DutRun.id == run_id)
        ).first()
        if row is None:
            return None
        r, serial, b = row
        n = s.scalar(select(func.count(SegmentRow.id)).where(SegmentRow.run_id == run_id)) or 0
        out = _run_json(r, serial, int(n))
        out["profile"] = b.profile
        out["operator"] = b.operator
        out.update(trace_json(b, with_labels=False))
        out["verdict_detail"] = r.verdict_detail  # every check: value, sigma, limits, outcome
        out.update(_run_results(s, run_id))
        return out


def segment_json(g: SegmentRow) -> dict:
    return {
        "id": g.id,
        "run_id": g.run_id,
        "step_index": g.step_index,
        "position": g.position,
        "index": g.seg_index,
        "orientation": g.orientation,
        "n_samples": g.n_samples,
        "t_start_s": g.t_start_s,
        "t_end_s": g.t_end_s,
        "acc_mean_g": [g.acc_mean_x_g, g.acc_mean_y_g, g.acc_mean_z_g],
        "acc_std_g": [g.acc_std_x_g, g.acc_std_y_g, g.acc_std_z_g],
        "temp_mean_c": g.temp_mean_c,
        "temp_std_c": g.temp_std_c,
        "created_at": _iso(g.created_at),
    }


def segments_of_run(db: Database, run_id: int) -> list[dict] | None:
    """Segments of a run in the order they were logged; None for an unknown run."""
    with db.session() as s:
        if s.get(DutRun, run_id) is None:
            return None
        rows = s.scalars(select(SegmentRow).where(SegmentRow.run_id == run_id).order_by(SegmentRow.id)).all()
        return [segment_json(g) for g in rows]


def result_key(run_id: int, result_seq: int) -> str:
    """Idempotency key of one verdict record (a superseding record gets a new key); the web's
    feed and webhook use db.writer.record_key instead (web/db_repo.py)."""
    return f"run-{run_id}-result-{result_seq}"


def revision_of(run_id: Any, result_seq: Any) -> Any:
    """The revision of verdict record (run_id, result_seq) as a scalar subquery: how many records
    the MES has for that run up to and including it (1 = the first final verdict). Columns or
    plain values: the feed asks it per row, the writer for the record it just stored."""
    from db.models import VerdictHistoryRow

    earlier = aliased(VerdictHistoryRow)
    return (select(func.count(earlier.id)).where(earlier.run_id == run_id, earlier.result_seq.is_not(None),
                                                 earlier.result_seq <= result_seq).scalar_subquery())


def results_since(db: Database, since: int = 0, limit: int = 100, since_time: datetime | None = None,
                  station: str | None = None) -> list[dict]:
    """The MES feed: verdict records (a run's final verdict, and each later one that supersedes it)
    stored after cursor `since`, in increasing `id` (= the record's result_seq). Page on with
    since = the last id. Safe with many stations writing: result_seq is taken in commit order
    (db.writer.take_result_seq), so a record committed after this read gets a number above every
    one returned here. Each record carries `revision` (1, 2, ... per run) and `supersedes` (the
    idempotency key of the record it replaces, or None): a client keeps the latest revision per
    run_id. since_time (optional) also requires the record to be judged at/after that time."""
    from db.models import VerdictHistoryRow as H

    limit = max(1, min(int(limit), 1000))
    with db.session() as s:
        q = (
            select(H, revision_of(H.run_id, H.result_seq), DutRun, Dut.serial, Batch)
            .join(DutRun, DutRun.id == H.run_id)
            .join(Dut, Dut.id == DutRun.dut_id)
            .join(Batch, Batch.id == DutRun.batch_id)
            .where(H.result_seq > int(since))
            .order_by(H.result_seq)
            .limit(limit)
        )
        if station:
            q = q.where(DutRun.station == station)
        if since_time is not None:
            q = q.where(H.judged_at >= since_time)
        out = []
        for h, rev, r, serial, b in s.execute(q).all():
            item = {
                "id": h.result_seq,
                "idempotency_key": result_key(r.id, h.result_seq),
                "revision": int(rev),
                "supersedes_seq": h.supersedes_seq,
                "supersedes": None if h.supersedes_seq is None else result_key(r.id, h.supersedes_seq),
                "created_at": _iso(h.judged_at),
                "run_id": r.id,
                "batch_id": r.batch_id,
                "station": r.station,
                "slot": r.slot,
                "serial": serial,
                "sensor": (r.identity or {}).get("sensor"),
                "profile": b.profile,
                "operator": b.operator,
                "state": r.state,
                "ended_at": _iso(r.ended_at),
                **trace_json(b, with_labels=False),
                "label_serial": r.label_serial,
                **record_verdict_json(h, r.attempt),
            }
            item.update(_run_results(s, r.id))
            out.append(item)
        return out


def _real_batches() -> Any:
    """Batches of real parts: a replay (Batch.replay_of) is no attempt, yield or SPC point."""
    return select(Batch.id).where(Batch.replay_of.is_(None))


def _is_attempt() -> Any:
    """Runs that tested their part: not a run stopped for a label mismatch (attempt NO_ATTEMPT)."""
    return DutRun.attempt > NO_ATTEMPT


def yields(db: Database, batch_id: int | None = None) -> dict:
    """First-pass and final yield over the DUTs judged at least once (those with a run in
    `batch_id` when given), counting every attempt of each DUT.

    first pass: the DUT's first judged attempt is `pass` (an error, marginal or fail on the first
    attempt is not first pass). final: its latest VALID attempt (pass/marginal/fail; errors are
    skipped) is `pass`; a DUT with errors only is not a final pass. Runs not judged yet
    (running, interrupted) are left out, and so are runs that never tested their part (a label
    mismatch, attempt NO_ATTEMPT): a wrong label is not a failed part."""
    with db.session() as s:
        q = (select(DutRun.dut_id, DutRun.id, DutRun.verdict).where(DutRun.verdict.is_not(None), _is_attempt())
             .where(DutRun.batch_id.in_(_real_batches())).order_by(DutRun.id))
        if batch_id is not None:
            q = q.where(DutRun.dut_id.in_(select(DutRun.dut_id).where(DutRun.batch_id == batch_id, _is_attempt())))
        per: dict[int, list[str]] = {}
        for dut_id, _run_id, verdict in s.execute(q).all():
            per.setdefault(dut_id, []).append(verdict)
    n = len(per)
    first = sum(1 for v in per.values() if v[0] == "pass")
    final = 0
    retested = 0
    for v in per.values():
        valid = [x for x in v if x in VALID_VERDICTS]
        final += bool(valid) and valid[-1] == "pass"
        retested += len(v) > 1
    return {
        "batch_id": batch_id,
        "duts": n,
        "attempts": sum(len(v) for v in per.values()),
        "retested": retested,
        "first_pass": first,
        "final_pass": final,
        "first_pass_yield": first / n if n else None,
        "final_yield": final / n if n else None,
    }


def batch_detail(db: Database, batch_id: int) -> dict | None:
    with db.session() as s:
        b = s.get(Batch, batch_id)
        if b is None:
            return None
        nseg = _nseg_subquery()
        rows = s.execute(
            select(DutRun, Dut.serial, nseg.c.n)
            .join(Dut, Dut.id == DutRun.dut_id)
            .outerjoin(nseg, nseg.c.run_id == DutRun.id)
            .where(DutRun.batch_id == batch_id)
            .order_by(DutRun.id)
        ).all()
        out = {
            "id": b.id,
            "station": b.station,
            "profile": b.profile,
            "operator": b.operator,
            "state": b.state,
            "reason": b.reason,
            "step_index": b.step_index,
            "last_completed_step": b.last_completed_step,
            "config_snapshot": b.config_snapshot,
            "replay_of": b.replay_of,
            "replay_diff": b.replay_diff,
            "step_windows": b.step_windows or {},
            "schema_version": b.schema_version,
            "created_at": _iso(b.created_at),
            "ended_at": _iso(b.ended_at),
            **trace_json(b),
            "runs": [_run_json(r, serial, int(n or 0)) for r, serial, n in rows],
        }
        pv = {row.run_id: program_verify_json(row) for row in s.scalars(
            select(ProgramVerifyRow).where(ProgramVerifyRow.run_id.in_([r.id for r, _, _ in rows]))).all()}
        for run in out["runs"]:
            run["program_verify"] = pv.get(run["id"])
        return out


def replays(db: Database, limit: int = 50) -> list[dict]:
    """Replay batches (station replay), newest first, with the summary of their comparison."""
    with db.session() as s:
        q = (select(Batch).where(Batch.replay_of.is_not(None)).order_by(Batch.id.desc())
             .limit(max(1, min(int(limit), 1000))))
        out = []
        for b in s.scalars(q):
            diff = b.replay_diff or {}
            out.append({"batch_id": b.id, "station": b.station, "profile": b.profile, "state": b.state,
                        "replay_of": b.replay_of, "created_at": _iso(b.created_at), "ended_at": _iso(b.ended_at),
                        "summary": diff.get("summary"), "plate_agrees": (diff.get("agreement") or {}).get("agrees")})
        return out


def replay_diff(db: Database, batch_id: int) -> dict | None:
    """The stored comparison of one replay batch; None when the batch is no replay (or unknown)."""
    with db.session() as s:
        b = s.get(Batch, batch_id)
        if b is None or b.replay_of is None:
            return None
        return {"batch_id": b.id, "replay_of": b.replay_of, "state": b.state, "created_at": _iso(b.created_at),
                "diff": b.replay_diff}


def list_batches(db: Database, limit: int = 50, before_id: int | None = None) -> list[dict]:
    with db.session() as s:
        q = select(Batch).order_by(Batch.id.desc()).limit(max(1, min(limit, 1000)))
        if before_id is not None:
            q = q.where(Batch.id < before_id)
        return [
            {"id": b.id, "station": b.station, "profile": b.profile, "operator": b.operator, "state": b.state, "step_index": b.step_index,
             "last_completed_step": b.last_completed_step, "created_at": _iso(b.created_at), "ended_at": _iso(b.ended_at),
             "replay_of": b.replay_of, **trace_json(b, with_labels=False)}
            for b in s.scalars(q)
        ]


def run_sample_bytes(db: Database, run_id: int) -> int:
    """Stored bytes of a run's compressed sample stream."""
    with db.session() as s:
        return int(s.scalar(select(func.coalesce(func.sum(func.length(SampleChunk.data)), 0)).where(SampleChunk.run_id == run_id)))


# ---- yield and SPC ----------------------------------------------------------------------------
def _judged_filters(q: Any, station: str | None = None, judged_from: datetime | None = None,
                    judged_to: datetime | None = None, part_number: str | None = None,
                    part_revision: str | None = None, work_order: str | None = None,
                    limits_name: str | None = None, limits_version: str | None = None) -> Any:
    """The WHERE of judged_runs / judged_facets. None = no filter; '' is a value (runs whose batch
    carried no part number or work order). judged_from inclusive, judged_to exclusive."""
    if station:
        q = q.where(DutRun.station == station)
    if judged_from is not None:
        q = q.where(DutRun.judged_at >= judged_from)
    if judged_to is not None:
        q = q.where(DutRun.judged_at < judged_to)
    for col, v in ((Batch.part_number, part_number), (Batch.part_revision, part_revision),
                   (Batch.work_order, work_order), (DutRun.limits_name, limits_name),
                   (DutRun.limits_version, limits_version)):
        if v is not None:
            q = q.where(col == v)
    return q


def judged_runs(db: Database, limit: int = 5000, station: str | None = None, *, judged_from: datetime | None = None,
                judged_to: datetime | None = None, part_number: str | None = None, part_revision: str | None = None,
                work_order: str | None = None, limits_name: str | None = None,
                limits_version: str | None = None) -> list[dict]:
    """The newest `limit` judged runs under the filters, oldest first, with their verdict checks
    (each judged measurement with its value and the limits it was judged by), the batch's product
    and traceability, the run's end state and verdict reasons: the input of
    station/records/spc.py and pareto.py. Filters (None = any): station, judged_at from (inclusive)
    / to (exclusive), part number and revision, work order, limits set name and version; the
    limit applies after them, so a product's newest runs are never crowded out by another's."""
    with db.session() as s:
        q = (select(DutRun, Dut.serial, Batch).join(Dut, Dut.id == DutRun.dut_id).join(Batch, Batch.id == DutRun.batch_id)
             .where(DutRun.verdict.is_not(None)).where(DutRun.batch_id.in_(_real_batches())))
        q = _judged_filters(q, station, judged_from, judged_to, part_number, part_revision, work_order, limits_name,
                            limits_version)
        rows = s.execute(q.order_by(DutRun.judged_at.desc(), DutRun.id.desc()).limit(max(1, min(int(limit), 100_000)))).all()
        out = [{"run_id": r.id, "batch_id": r.batch_id, "station": r.station, "slot": r.slot, "serial": serial,
                "attempt": r.attempt, "judged_at": _iso(r.judged_at), "verdict": r.verdict, "grade": r.grade, "limits_name": r.limits_name,
                "limits_version": r.limits_version, "checks": list((r.verdict_detail or {}).get("checks") or []),
                "reasons": list((r.verdict_detail or {}).get("reasons") or []), "state": r.state,
                "fault_reason": r.fault_reason or "",
                "profile": b.profile, **trace_json(b, with_labels=False), "product": Trace.of(b).product}
               for r, serial, b in rows]
    out.reverse()
    return out


def judged_facets(db: Database, judged_from: datetime | None = None, judged_to: datetime | None = None) -> list[dict]:
    """What the judged runs in a date range can be filtered by: one row per distinct (station, part
    number, revision, work order, limits name, version) with its run count. Fills the Records
    view's selects from the data, independent of the other filters (choosing a product must not
    empty the product list)."""
    cols = (DutRun.station, Batch.part_number, Batch.part_revision, Batch.work_order, DutRun.limits_name,
            DutRun.limits_version)
    with db.session() as s:
        q = (select(*cols, func.count(DutRun.id)).join(Batch, Batch.id == DutRun.batch_id)
             .where(DutRun.verdict.is_not(None)).where(DutRun.batch_id.in_(_real_batches())))
        q = _judged_filters(q, judged_from=judged_from, judged_to=judged_to).group_by(*cols)
        return [{"station": st or "", "part_number": pn or "", "part_revision": rev or "", "work_order": wo or "",
                 "product": Trace(part_number=pn or "", part_revision=rev or "").product, "limits_name": ln or "",
                 "limits_version": lv or "", "runs": int(n)} for st, pn, rev, wo, ln, lv, n in s.execute(q).all()]


# ---- audit trail ------------------------------------------------------------------------------
def audit_append(db: Database, actor: str, action: str, target: str = "", detail: dict | None = None,
                 station: str | None = None, conn: Any = None) -> int:
    """One audit row (who did what); station defaults to the database's. With `conn` the row goes
    into that connection's transaction (the db writer's: it is stored with what it records, and a
    second transaction would wait on SQLite's write lock the writer holds)."""
    from db.models import AuditRow
    from contracts.json_safe import plain_json

    values = {"at": utcnow(), "station": (station if station is not None else getattr(db, "station", "")) or "",
              "actor": actor[:128], "action": action[:64], "target": target[:128], "detail": plain_json(detail or {})}
    if conn is not None:
        return int(conn.execute(insert(AuditRow).values(**values)).inserted_primary_key[0])
    with db.session() as s:
        return int(s.execute(insert(AuditRow).values(**values)).inserted_primary_key[0])


def audit_list(db: Database, limit: int = 100, before_id: int | None = None, station: str | None = None) -> list[dict]:
    """Audit rows, newest first; page back with before_id = the last id of a page."""
    from db.models import AuditRow

    with db.session() as s:
        q = select(AuditRow).order_by(AuditRow.id.desc()).limit(max(1, min(int(limit), 1000)))
        if before_id is not None:
            q = q.where(AuditRow.id < int(before_id))
        if station:
            q = q.where(AuditRow.station == station)
        return [{"id": a.id, "at": _iso(a.at), "station": a.station, "actor": a.actor, "action": a.action,
                 "target": a.target, "detail": a.detail or {}} for a in s.scalars(q)]


# ---- MES outbox --------------------------------------------------------------------------------
def outbox_json(o: Outbox) -> dict:
    return {
        "id": o.id,
        "idempotency_key": o.idempotency_key,
        "topic": o.topic,
        "payload": o.payload,
        "attempts": o.attempts,
        "next_attempt_at": _iso(o.next_attempt_at),
        "delivered_at": _iso(o.delivered_at),
        "last_error": o.last_error,
        "created_at": _iso(o.created_at),
    }


def outbox_enqueue(db: Database, idempotency_key: str, payload: dict, topic: str = "result") -> int:
    """Queue a message; enqueueing the same key again returns the existing message's id. Insert-or-get
    by the database itself (ON CONFLICT DO NOTHING): two stations' MES workers may enqueue the same
    record at the same moment."""
    return outbox_enqueue_new(db, idempotency_key, payload, topic)[0]


def outbox_enqueue_new(db: Database, idempotency_key: str, payload: dict, topic: str = "result") -> tuple[int, bool]:
    """(message id, True when this call queued it; False when the key was queued already)."""
    from db.database import insert_ignore
    from contracts.json_safe import plain_json

    now = utcnow()
    with db.session() as s:
        res = s.execute(insert_ignore(s, Outbox, ["idempotency_key"]).values(
            idempotency_key=idempotency_key, topic=topic, payload=plain_json(payload), attempts=0,
            next_attempt_at=now, last_error="", created_at=now,
        ))
        added = bool(res.rowcount)
        oid = s.scalar(select(Outbox.id).where(Outbox.idempotency_key == idempotency_key))
        return int(oid), added


def outbox_pending(db: Database, limit: int = 50, now: datetime | None = None) -> list[dict]:
    """Undelivered messages due now (next_attempt_at <= now), oldest first."""
    now = now or utcnow()
    with db.session() as s:
        rows = s.scalars(
            select(Outbox)
            .where(Outbox.delivered_at.is_(None), Outbox.next_attempt_at <= now)
            .order_by(Outbox.next_attempt_at, Outbox.id)
            .limit(max(1, limit))
        ).all()
        return [outbox_json(o) for o in rows]


def outbox_mark_delivered(db: Database, outbox_id: int) -> None:
    with db.session() as s:
        res = s.execute(
            update(Outbox).where(Outbox.id == outbox_id)
            .values(delivered_at=utcnow(), attempts=Outbox.attempts + 1, last_error="")
        )
        if res.rowcount == 0:
            raise KeyError(f"no outbox message {outbox_id}")


def outbox_mark_failed(db: Database, outbox_id: int, error: str, next_attempt_at: datetime) -> None:
    """One failed delivery: count it, keep the error, retry at next_attempt_at (caller's backoff)."""
    with db.session() as s:
        res = s.execute(
            update(Outbox).where(Outbox.id == outbox_id)
            .values(attempts=Outbox.attempts + 1, last_error=str(error)[:2000], next_attempt_at=next_attempt_at)
        )
        if res.rowcount == 0:
            raise KeyError(f"no outbox message {outbox_id}")


__all__ = [
    "search_duts",
    "result_key",
    "dut_by_serial",
    "runs_of_dut",
    "run_detail",
    "segments_of_run",
    "results_since",
    "revision_of",
    "audit_append",
    "outbox_enqueue_new",
    "judged_runs",
    "judged_facets",
    "audit_list",
    "batch_detail",
    "yields",
    "verdict_json",
    "list_batches",
    "run_sample_bytes",
    "outbox_enqueue",
    "outbox_pending",
    "outbox_mark_delivered",
    "outbox_mark_failed",
]
