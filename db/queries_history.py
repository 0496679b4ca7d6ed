"""History queries: DUTs by serial, their runs, a run's segments and results, batches and replays.

Why a module of its own: this is what the operator page and the REST API's history routes read
(design 5.3): one DUT, one run, one batch at a time, every answer a JSON-ready dict (db/row_json.py
shapes) or None for an unknown serial / run / batch so the web layer can answer 404. The MES feed
is db/queries_mes.py, yields and SPC db/queries_records.py.

Runs of replays (Batch.replay_of) and runs stopped for a label mismatch (attempt NO_ATTEMPT) are in
the history but are no attempt of their serial: real_batches() and is_attempt() say which are.
"""

from __future__ import annotations

from sqlalchemy import ColumnElement, Select, Subquery, func, or_, select

from db.database import Database
from db.models import NO_ATTEMPT, Batch, Dut, DutRun, ProgramVerifyRow, SampleChunk, SegmentRow, SfemResultRow, ThermalResultRow
from db.row_json import (
    JsonAnswer,
    VALID_VERDICTS,
    iso,
    program_verify_json,
    run_json,
    run_results,
    segment_json,
    trace_json,
    verdict_json,
)

def program_record(db: Database, run_id: int) -> JsonAnswer | None:
    """The program step's own record of one run (what the driver reported: the coefficients
    written, comp_from_t, error kind), as the daemon stored it; None if the run was not programmed."""
    with db.session() as s:
        row = s.scalars(select(ProgramVerifyRow).where(ProgramVerifyRow.run_id == run_id)).one_or_none()
        return None if row is None else dict(row.program or {})


def _nseg_subquery() -> Subquery:
    return select(SegmentRow.run_id, func.count(SegmentRow.id).label("n")).group_by(SegmentRow.run_id).subquery()


def dut_by_serial(db: Database, serial: str) -> JsonAnswer | None:
    """The DUT with the results of its latest run that has any (design 5.3 GET /api/duts/{serial})."""
    with db.session() as s:
        dut = s.scalars(select(Dut).where(Dut.serial == serial)).one_or_none()
        if dut is None:
            return None
        n_runs = s.scalar(select(func.count(DutRun.id)).where(DutRun.dut_id == dut.id,
                                                              DutRun.batch_id.in_(real_batches()))) or 0
        # a run stopped for a label mismatch (attempt 0) is in the history, but it never tested the part
        n_attempts = s.scalar(select(func.count(DutRun.id)).where(DutRun.dut_id == dut.id, is_attempt(),
                                                                  DutRun.batch_id.in_(real_batches()))) or 0
        # the DUT's result is its latest VALID attempt (judged pass/marginal/fail); a retest that
        # faulted does not hide the attempt before it. Never judged: the latest attempt with a record
        # or with results.
        latest = s.scalars(
            select(DutRun).where(DutRun.dut_id == dut.id, DutRun.verdict.in_(VALID_VERDICTS),
                                 DutRun.batch_id.in_(real_batches())).order_by(DutRun.id.desc())
        ).first()
        if latest is None:  # results are data of their run (no result_seq until its verdict)
            with_results = select(ThermalResultRow.run_id).union(select(SfemResultRow.run_id))
            latest = s.scalars(
                select(DutRun).where(DutRun.dut_id == dut.id, is_attempt(),
                                     or_(DutRun.result_seq.is_not(None), DutRun.id.in_(with_results)))
                .order_by(DutRun.id.desc())
            ).first()
        out: JsonAnswer = {
            "serial": dut.serial,
            "sensor": dut.sensor,
            "first_seen": iso(dut.first_seen),
            "last_seen": iso(dut.last_seen),
            "n_runs": n_runs,
            "result_run_id": None if latest is None else latest.id,
            "thermal": None,
            "thermal_method": None,
            "thermal_by_method": {},
            "sfem": None,
            "attempts": n_attempts,
        }
        if latest is not None:
            out.update(run_results(s, latest.id))
            out.update(verdict_json(latest))
        return out


def search_duts(db: Database, serial_like: str | None = None, limit: int = 50) -> list[JsonAnswer]:
    """DUT summaries whose serial contains serial_like (case-insensitive), most recently seen first."""
    with db.session() as s:
        nruns = select(DutRun.dut_id, func.count(DutRun.id).label("n")).group_by(DutRun.dut_id).subquery()
        q = select(Dut, nruns.c.n).outerjoin(nruns, nruns.c.dut_id == Dut.id)
        if serial_like:
            q = q.where(func.lower(Dut.serial).contains(serial_like.lower(), autoescape=True))
        q = q.order_by(Dut.last_seen.desc(), Dut.id.desc()).limit(max(1, min(limit, 1000)))
        return [
            {"serial": d.serial, "sensor": d.sensor, "first_seen": iso(d.first_seen), "last_seen": iso(d.last_seen),
             "n_runs": int(n or 0)}
            for d, n in s.execute(q).all()
        ]


def runs_of_dut(db: Database, serial: str) -> list[JsonAnswer] | None:
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
        return [run_json(r, dut.serial, int(n or 0)) for r, n in rows]


def run_detail(db: Database, run_id: int) -> JsonAnswer | None:
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
        out = run_json(r, serial, int(n))
        out["profile"] = b.profile
        out["operator"] = b.operator
        out.update(trace_json(b, with_labels=False))
        out["verdict_detail"] = r.verdict_detail  # every check: value, sigma, limits, outcome
        out.update(run_results(s, run_id))
        return out


def segments_of_run(db: Database, run_id: int) -> list[JsonAnswer] | None:
    """Segments of a run in the order they were logged; None for an unknown run."""
    with db.session() as s:
        if s.get(DutRun, run_id) is None:
            return None
        rows = s.scalars(select(SegmentRow).where(SegmentRow.run_id == run_id).order_by(SegmentRow.id)).all()
        return [segment_json(g) for g in rows]


def real_batches() -> Select[int]:
    """Batches of real parts: a replay (Batch.replay_of) is no attempt, yield or SPC point."""
    return select(Batch.id).where(Batch.replay_of.is_(None))


def is_attempt() -> ColumnElement[bool]:
    """Runs that tested their part: not a run stopped for a label mismatch (attempt NO_ATTEMPT)."""
    return DutRun.attempt > NO_ATTEMPT


def batch_detail(db: Database, batch_id: int) -> JsonAnswer | None:
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
            "created_at": iso(b.created_at),
            "ended_at": iso(b.ended_at),
            **trace_json(b),
            "runs": [run_json(r, serial, int(n or 0)) for r, serial, n in rows],
        }
        pv = {row.run_id: program_verify_json(row) for row in s.scalars(
            select(ProgramVerifyRow).where(ProgramVerifyRow.run_id.in_([r.id for r, _, _ in rows]))).all()}
        for run in out["runs"]:
            run["program_verify"] = pv.get(run["id"])
        return out


def replays(db: Database, limit: int = 50) -> list[JsonAnswer]:
    """Replay batches (station replay), newest first, with the summary of their comparison."""
    with db.session() as s:
        q = (select(Batch).where(Batch.replay_of.is_not(None)).order_by(Batch.id.desc())
             .limit(max(1, min(int(limit), 1000))))
        out = []
        for b in s.scalars(q):
            diff = b.replay_diff or {}
            out.append({"batch_id": b.id, "station": b.station, "profile": b.profile, "state": b.state,
                        "replay_of": b.replay_of, "created_at": iso(b.created_at), "ended_at": iso(b.ended_at),
                        "summary": diff.get("summary"), "plate_agrees": (diff.get("agreement") or {}).get("agrees")})
        return out


def replay_diff(db: Database, batch_id: int) -> JsonAnswer | None:
    """The stored comparison of one replay batch; None when the batch is no replay (or unknown)."""
    with db.session() as s:
        b = s.get(Batch, batch_id)
        if b is None or b.replay_of is None:
            return None
        return {"batch_id": b.id, "replay_of": b.replay_of, "state": b.state, "created_at": iso(b.created_at),
                "diff": b.replay_diff}


def list_batches(db: Database, limit: int = 50, before_id: int | None = None) -> list[JsonAnswer]:
    with db.session() as s:
        q = select(Batch).order_by(Batch.id.desc()).limit(max(1, min(limit, 1000)))
        if before_id is not None:
            q = q.where(Batch.id < before_id)
        return [
            {"id": b.id, "station": b.station, "profile": b.profile, "operator": b.operator, "state": b.state, "step_index": b.step_index,
             "last_completed_step": b.last_completed_step, "created_at": iso(b.created_at), "ended_at": iso(b.ended_at),
             "replay_of": b.replay_of, **trace_json(b, with_labels=False)}
            for b in s.scalars(q)
        ]


def run_sample_bytes(db: Database, run_id: int) -> int:
    """Stored bytes of a run's compressed sample stream."""
    with db.session() as s:
        return int(s.scalar(select(func.coalesce(func.sum(func.length(SampleChunk.data)), 0)).where(SampleChunk.run_id == run_id)))


__all__ = ["real_batches", "is_attempt", "program_record", "dut_by_serial", "search_duts", "runs_of_dut", "run_detail",
           "segments_of_run", "batch_detail", "replays", "replay_diff", "list_batches", "run_sample_bytes"]
