"""Records queries: yield (first pass, final) and the judged runs SPC, Pareto and the Records view
read (station/records/spc.py, pareto.py), with the facets to filter them by.

Why a module of its own: these count parts, not rows: every attempt of a DUT, replays and label
mismatches left out (db/queries_history.py real_batches, is_attempt), filters by product, work order
and limit set applied before the limit so one product's runs never crowd out another's.
"""

from __future__ import annotations

from datetime import datetime
from typing import TypeVar

from sqlalchemy import Select, func, select

from contracts.trace import Trace
from db.database import Database
from db.models import Batch, Dut, DutRun
from db.queries_history import is_attempt, real_batches
from db.row_json import JsonAnswer, VALID_VERDICTS, iso, trace_json

Q = TypeVar("Q", bound=Select)  # a query of judged runs, whatever its columns


def yields(db: Database, batch_id: int | None = None) -> JsonAnswer:
    """First-pass and final yield over the DUTs judged at least once (those with a run in
    `batch_id` when given), counting every attempt of each DUT.

    first pass: the DUT's first judged attempt is `pass` (an error, marginal or fail on the first
    attempt is not first pass). final: its latest VALID attempt (pass/marginal/fail; errors are
    skipped) is `pass`; a DUT with errors only is not a final pass. Runs not judged yet
    (running, interrupted) are left out, and so are runs that never tested their part (a label
    mismatch, attempt NO_ATTEMPT): a wrong label is not a failed part."""
    with db.session() as s:
        q = (select(DutRun.dut_id, DutRun.id, DutRun.verdict).where(DutRun.verdict.is_not(None), is_attempt())
             .where(DutRun.batch_id.in_(real_batches())).order_by(DutRun.id))
        if batch_id is not None:
            q = q.where(DutRun.dut_id.in_(select(DutRun.dut_id).where(DutRun.batch_id == batch_id, is_attempt())))
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


# ---- yield and SPC ----------------------------------------------------------------------------
def _judged_filters(q: Q, station: str | None = None, judged_from: datetime | None = None,
                    judged_to: datetime | None = None, part_number: str | None = None,
                    part_revision: str | None = None, work_order: str | None = None,
                    limits_name: str | None = None, limits_version: str | None = None) -> Q:
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
                limits_version: str | None = None) -> list[JsonAnswer]:
    """The newest `limit` judged runs under the filters, oldest first, with their verdict checks
    (each judged measurement with its value and the limits it was judged by), the batch's product
    and traceability, the run's end state and verdict reasons: the input of
    station/records/spc.py and pareto.py. Filters (None = any): station, judged_at from (inclusive)
    / to (exclusive), part number and revision, work order, limits set name and version; the
    limit applies after them, so a product's newest runs are never crowded out by another's."""
    with db.session() as s:
        q = (select(DutRun, Dut.serial, Batch).join(Dut, Dut.id == DutRun.dut_id).join(Batch, Batch.id == DutRun.batch_id)
             .where(DutRun.verdict.is_not(None)).where(DutRun.batch_id.in_(real_batches())))
        q = _judged_filters(q, station, judged_from, judged_to, part_number, part_revision, work_order, limits_name,
                            limits_version)
        rows = s.execute(q.order_by(DutRun.judged_at.desc(), DutRun.id.desc()).limit(max(1, min(int(limit), 100_000)))).all()
        out = [{"run_id": r.id, "batch_id": r.batch_id, "station": r.station, "slot": r.slot, "serial": serial,
                "attempt": r.attempt, "judged_at": iso(r.judged_at), "verdict": r.verdict, "grade": r.grade, "limits_name": r.limits_name,
                "limits_version": r.limits_version, "checks": list((r.verdict_detail or {}).get("checks") or []),
                "reasons": list((r.verdict_detail or {}).get("reasons") or []), "state": r.state,
                "fault_reason": r.fault_reason or "",
                "profile": b.profile, **trace_json(b, with_labels=False), "product": Trace.of(b).product}
               for r, serial, b in rows]
    out.reverse()
    return out


def judged_facets(db: Database, judged_from: datetime | None = None, judged_to: datetime | None = None) -> list[JsonAnswer]:
    """What the judged runs in a date range can be filtered by: one row per distinct (station, part
    number, revision, work order, limits name, version) with its run count. Fills the Records
    view's selects from the data, independent of the other filters (choosing a product must not
    empty the product list)."""
    cols = (DutRun.station, Batch.part_number, Batch.part_revision, Batch.work_order, DutRun.limits_name,
            DutRun.limits_version)
    with db.session() as s:
        q = (select(*cols, func.count(DutRun.id)).join(Batch, Batch.id == DutRun.batch_id)
             .where(DutRun.verdict.is_not(None)).where(DutRun.batch_id.in_(real_batches())))
        q = _judged_filters(q, judged_from=judged_from, judged_to=judged_to).group_by(*cols)
        return [{"station": st or "", "part_number": pn or "", "part_revision": rev or "", "work_order": wo or "",
                 "product": Trace(part_number=pn or "", part_revision=rev or "").product, "limits_name": ln or "",
                 "limits_version": lv or "", "runs": int(n)} for st, pn, rev, wo, ln, lv, n in s.execute(q).all()]


__all__ = ["yields", "judged_runs", "judged_facets"]
