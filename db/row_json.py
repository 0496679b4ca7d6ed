"""The read side's JSON shapes: a row (or a run's result rows) as the dict the REST API, the page
and the MES feed answer with.

Why a module of its own: every query module (db/queries_*.py) answers in these shapes, and the
web's pydantic schemas (web/schemas_history.py) are written against them; one place keeps a run,
a verdict or a result shaped the same wherever it appears. Times are ISO 8601 UTC strings. The
only query here is run_results (a run's latest results, shaped), which every run-level answer
embeds.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from contracts.sfem_result import SFEM_RESULT_SHAPE
from contracts.trace import Trace
from contracts.types import AXES
from db.models import Batch, DutRun, Outbox, ProgramVerifyRow, SegmentRow, SfemResultRow, ThermalResultRow, VerdictHistoryRow

PREFERRED_THERMAL = ("offline", "streaming")  # the offline fit is the better estimate when both exist

# One JSON answer of the read side (a row, a run, a batch, a feed record): str keys, values of many
# shapes. Unlike contracts.json_safe.JsonDict (dict[str, object]) the values are left unchecked (Any)
# on purpose: the daemon, held to mypy --strict, indexes into these answers (station/daemon/batches.py
# batch_detail and segments_of_run, station/decisions/limits_audit.py audit_list); a TypedDict per
# shape is what would check them.
JsonAnswer = dict[str, Any]


def iso(t: datetime | None) -> str | None:
    return None if t is None else t.isoformat()


def thermal_json(row: ThermalResultRow) -> JsonAnswer:
    out: dict[str, object] = {"id": row.id, "method": row.method, "n_segments": row.n_segments, "created_at": iso(row.created_at)}
    for ax in AXES:
        out[ax] = {
            "tdb_mg_per_c": getattr(row, f"tdb_{ax}_mg_per_c"),
            "tdsf_ppm_per_c": getattr(row, f"tdsf_{ax}_ppm_per_c"),
            "tdb_sigma_mg_per_c": getattr(row, f"tdb_sigma_{ax}_mg_per_c"),
            "tdsf_sigma_ppm_per_c": getattr(row, f"tdsf_sigma_{ax}_ppm_per_c"),
            "tdsf_clamped": getattr(row, f"tdsf_clamped_{ax}"),
        }
    return out


def sfem_json(rows: Sequence[SfemResultRow]) -> JsonAnswer | None:
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


def run_results(s: Session, run_id: int) -> JsonAnswer:
    """Latest thermal result per method and the latest SFEM rows of one run."""
    rows = s.scalars(select(ThermalResultRow).where(ThermalResultRow.run_id == run_id).order_by(ThermalResultRow.id)).all()
    by_method: dict[str, JsonAnswer] = {}
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

def program_verify_json(row: ProgramVerifyRow) -> JsonAnswer:
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
        "updated_at": iso(row.updated_at),
    }


VALID_VERDICTS = ("pass", "marginal", "fail")  # an attempt that ended in error is not a valid result


def verdict_json(r: DutRun) -> JsonAnswer:
    """The station's decision on a run (None fields while it is not judged)."""
    return _decision_json(r, r.attempt, r.verdict_reason)


def record_verdict_json(h: VerdictHistoryRow, attempt: int) -> JsonAnswer:
    """The decision of one verdict record (verdict_history row), shaped as verdict_json."""
    return _decision_json(h, attempt, h.reason)


def _decision_json(row: DutRun | VerdictHistoryRow, attempt: int, reason: str | None) -> JsonAnswer:
    """A dut_run or verdict_history row's decision columns (the two name the reason differently)."""
    return {
        "attempt": attempt,
        "verdict": row.verdict,
        "grade": row.grade,
        "tray": row.tray,
        "reason": reason or None,
        "limits_name": row.limits_name,
        "limits_version": row.limits_version,
        "judged_at": iso(row.judged_at),
    }


def run_json(r: DutRun, serial: str, n_segments: int | None = None) -> JsonAnswer:
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
        "samples_pruned_at": iso(r.samples_pruned_at),
        "result_seq": r.result_seq,
        "started_at": iso(r.started_at),
        "ended_at": iso(r.ended_at),
        "label_serial": r.label_serial,
        # what measured it (None: not stored, a run from before migration 0009)
        "software_version": r.software_version,
        "firmware_version": r.firmware_version,
        "holder": r.holder,
        # the MES's route check (None: none asked, or a run from before migration 0011)
        "route_check": r.route_check,
        "route_reason": r.route_reason or "",
        **verdict_json(r),
    }
    if n_segments is not None:
        out["n_segments"] = n_segments
    return out


def trace_json(b: Batch, with_labels: bool = True) -> JsonAnswer:
    """A batch's traceability fields (contracts/trace.py): work order, part number, revision, lot
    (and the label serials scanned per slot)."""
    out: dict[str, object] = dict(Trace.of(b).fields())
    if with_labels:
        out["labels"] = dict(b.labels or {})
    return out

def segment_json(g: SegmentRow) -> JsonAnswer:
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
        "created_at": iso(g.created_at),
    }

def outbox_json(o: Outbox) -> JsonAnswer:
    return {
        "id": o.id,
        "idempotency_key": o.idempotency_key,
        "topic": o.topic,
        "payload": o.payload,
        "attempts": o.attempts,
        "next_attempt_at": iso(o.next_attempt_at),
        "delivered_at": iso(o.delivered_at),
        "last_error": o.last_error,
        "created_at": iso(o.created_at),
    }


__all__ = ["JsonAnswer", "PREFERRED_THERMAL", "VALID_VERDICTS", "iso", "thermal_json", "sfem_json", "run_results", "program_verify_json",
           "verdict_json", "record_verdict_json", "run_json", "trace_json", "segment_json", "outbox_json"]
