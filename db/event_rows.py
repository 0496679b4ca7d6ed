"""Pure row shaping: what the daemon's events become as table rows, with no database in sight.

Why a module of its own: how an event's payload maps onto columns (which keys, which units, what is
clipped to a column's width, what NaN becomes) is a contract with the read side (db/repository.py
puts the rows back together) and is testable without a connection; the writer (db/event_store.py)
only decides when and where the rows go. Every function here returns plain dicts for
`insert(...).values(**row)` / `update(...).values(**row)`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from datetime import datetime

from contracts.events import DutProgrammed, DutVerdict, DutVerified, SegmentLogged, StepCompleted
from contracts.json_safe import finite_or_none as _num, plain_json
from contracts.run_records import ThermalReport
from contracts.sfem_result import SfemResult
from contracts.types import AXES

# the verdict keys an MES message carries (the outbox payload) besides the record's identity
VERDICT_FIELDS = ("verdict", "grade", "tray", "reason", "attempt", "limits_name", "limits_version")


def thermal_rows(thermal: ThermalReport | None) -> list[dict[str, object]]:
    """Rows for thermal_result from a DUT's thermal report: one per method result it holds
    (streaming, offline), each with its TDB/TDSF per axis and the method's JSON as detail."""
    if thermal is None:
        return []
    rows = []
    for res in thermal.methods.values():
        row: dict[str, object] = {"method": res.method[:16], "n_segments": res.n_segments}
        for ax in AXES:
            a = res.axes[ax]
            row[f"tdb_{ax}_mg_per_c"] = _num(a.tdb_mg_per_c)
            row[f"tdsf_{ax}_ppm_per_c"] = _num(a.tdsf_ppm_per_c)
            row[f"tdb_sigma_{ax}_mg_per_c"] = _num(a.tdb_sigma_mg_per_c)
            row[f"tdsf_sigma_{ax}_ppm_per_c"] = _num(a.tdsf_sigma_ppm_per_c)
            row[f"tdsf_clamped_{ax}"] = a.tdsf_clamped
        row["detail"] = plain_json(res.detail)
        rows.append(row)
    return rows


def sfem_rows(sfem: SfemResult | None) -> list[dict[str, object]]:
    """Rows for sfem_result from the SFEM record (contracts/sfem_result.py SfemResult, the one
    shape the daemon and `station sfem --json` give): one row per temperature step (its fit) and
    one row for the record (temperature_step None: the reference step's headline figures, the
    record's own keys and, in polynomial_coefficients, the thermal model). db/row_json.py
    sfem_json puts them back together."""
    if sfem is None:
        return []
    rec = sfem
    rows: list[dict[str, object]] = [
        {
            "temperature_step": st.temperature_step,
            "temp_c": st.temp_c,
            "rmse_before_mg": st.rmse_before_mg,
            "rmse_after_mg": st.rmse_after_mg,
            "parameters": st.to_json(),
            "polynomial_coefficients": None,
        }
        for st in rec.steps
    ]
    ref = rec.reference
    rows.append(
        {
            "temperature_step": None,
            "temp_c": ref.temp_c,
            "rmse_before_mg": ref.rmse_before_mg,
            "rmse_after_mg": ref.rmse_after_mg,
            "parameters": rec.record_row_json(),
            "polynomial_coefficients": None if rec.thermal is None else plain_json(rec.thermal),
        }
    )
    return rows


def verdict_columns(verdict: Mapping[str, object]) -> dict[str, object]:
    """dut_run columns of a verdict dict (station/decisions/moment.py)."""
    return {
        "verdict": str(verdict.get("verdict") or "")[:16] or None,
        "grade": None if verdict.get("grade") is None else str(verdict["grade"])[:16],
        "tray": None if verdict.get("tray") is None else str(verdict["tray"])[:64],
        "verdict_reason": str(verdict.get("reason") or ""),
        "verdict_detail": plain_json(verdict),
        "limits_name": None if verdict.get("limits_name") is None else str(verdict["limits_name"])[:64],
        "limits_version": None if verdict.get("limits_version") is None else str(verdict["limits_version"])[:32],
    }


def segment_values(run_id: int, ev: SegmentLogged, now: datetime) -> dict[str, object]:
    """The segment row of one SegmentLogged."""
    sg = ev.segment
    values: dict[str, object] = {
        "run_id": run_id,
        "step_index": int(ev.step_index),
        "position": None if sg.position is None else int(sg.position),
        "seg_index": int(sg.index),
        "orientation": int(sg.orientation),
        "n_samples": int(sg.n_samples),
        "temp_mean_c": float(sg.temp_mean_c),
        "temp_std_c": float(sg.temp_std_c),
        "t_start_s": float(sg.t_start_s),
        "t_end_s": float(sg.t_end_s),
        "created_at": now,
    }
    for k, ax in enumerate(AXES):
        values[f"acc_mean_{ax}_g"] = float(sg.acc_mean_g[k])
        values[f"acc_std_{ax}_g"] = float(sg.acc_std_g[k])
    return values


def program_verify_defaults(now: datetime) -> dict[str, object]:
    """A new program_verify row before either half (program, verify) has reported."""
    return {"programmed": False, "comp_on": False, "attempts": 0, "error_kind": "", "error": "", "flags": [],
            "program": {}, "created_at": now}


def program_verify_values(ev: DutProgrammed | DutVerified, now: datetime) -> dict[str, object]:
    """The program_verify columns one half reports: the program step (DutProgrammed) or the
    verification (DutVerified); the row is upserted with them."""
    if isinstance(ev, DutProgrammed):
        rec = ev.program
        p = rec.to_json()
        return {
            "programmed": rec.programmed, "crc": p.get("crc"), "readback_crc": p.get("readback_crc"),
            "comp_on": bool(rec.comp), "attempts": int(rec.attempts or 0),
            "error_kind": rec.error_kind or "", "error": rec.error or "", "program": p,
            "updated_at": now,
        }
    v = plain_json(ev.verification)
    before, after = v.get("e_before_mg") or {}, v.get("e_after_mg") or {}
    values: dict[str, object] = {"verified": bool(v.get("passed")), "flags": list(v.get("flags") or []),
                                 "verification": v, "updated_at": now}
    for ax in AXES:
        values[f"e_before_{ax}_mg"] = _num(before.get(ax))
        values[f"e_after_{ax}_mg"] = _num(after.get(ax))
    return values


def step_windows(stored: Mapping[str, object] | None, ev: StepCompleted) -> dict[str, object]:
    """A batch's step_windows with the step `ev` completed added: {"<step>": {"<slot>": [from_s,
    to_s]}}, a bound that is not finite stored as None."""
    windows = dict(stored or {})
    windows[str(ev.step_index)] = {
        slot: [float(a) if math.isfinite(a) else None, float(b) if math.isfinite(b) else None]
        for slot, (a, b) in ev.windows.items()
    }
    return windows


def superseded_detail(run_id: int, ev: DutVerdict, old: Mapping[str, object], old_key: str, seq: int, new_key: str,
                      cols: Mapping[str, object]) -> dict[str, object]:
    """The audit detail of a verdict record replaced by a newer one: both records, each with its
    result_seq and idempotency key. `old` holds the run's previous result_seq, verdict, grade, tray
    and verdict_reason."""
    return {
        "run_id": run_id, "serial": ev.serial, "slot": ev.slot, "batch_id": ev.batch_id,
        "old": {"result_seq": old["result_seq"], "idempotency_key": old_key,
                "verdict": old["verdict"], "grade": old["grade"], "tray": old["tray"], "reason": old["verdict_reason"]},
        "new": {"result_seq": seq, "idempotency_key": new_key, "verdict": cols["verdict"],
                "grade": cols["grade"], "tray": cols["tray"], "reason": cols["verdict_reason"]},
    }


def outbox_payload(run_id: int, ev: DutVerdict, seq: int, revision: int, supersedes_key: str | None) -> dict[str, object]:
    """The MES message of one verdict record, as the writer queues it (DbWriter(outbox=True))."""
    return {
        "result_seq": seq, "run_id": run_id, "batch_id": ev.batch_id, "slot": ev.slot, "serial": ev.serial,
        "revision": revision, "supersedes": supersedes_key,
        **{k: (ev.verdict or {}).get(k) for k in VERDICT_FIELDS},
    }


__all__ = ["VERDICT_FIELDS", "program_verify_defaults", "thermal_rows", "sfem_rows", "verdict_columns",
           "segment_values", "program_verify_values", "step_windows", "superseded_detail", "outbox_payload"]
