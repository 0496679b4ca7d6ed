"""WebRepository on the station database (db.repository and db.export).

The MES record is a run's final verdict (design 8). Its key is `result:<run_id>:<result_seq>`
(db/mes_record.py mes_key, the one key), the same key db.writer uses when it queues the message in the verdict's own
transaction (DbWriter(outbox=True)). The webhook worker also enqueues every record under that key
(enqueue is insert-or-get on the key), so whichever path queued it, one record is one outbox row
and one MES record; the results feed carries the same key, and a superseding record names the key
of the one it replaces (`supersedes`).
"""

from __future__ import annotations

from datetime import datetime, timezone

from sqlalchemy import func, select, text

from db import repository as R
from db.database import Database
from db.models import Dut, DutRun, Outbox
from contracts.logfile import DutLog
from contracts.types import StationError
from web.repo import WebRepository


def _with_methods(d: dict) -> dict:
    by = d.get("thermal_by_method") or {}
    d.setdefault("streaming", by.get("streaming"))
    d.setdefault("offline", by.get("offline"))
    return d


class DbRepository(WebRepository):
    writes_outbox = False  # the worker enqueues too; same key, so never twice

    def __init__(self, db: Database) -> None:
        self.db = db

    def search_duts(self, serial_like: str | None, limit: int = 50) -> list[dict]:
        with self.db.session() as s:
            q = (
                select(Dut, func.count(DutRun.id), func.max(DutRun.id))
                .outerjoin(DutRun, DutRun.dut_id == Dut.id)
                .group_by(Dut.id)
                .order_by(Dut.last_seen.desc(), Dut.id.desc())
                .limit(limit)
            )
            if serial_like:
                pat = "%" + serial_like.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_") + "%"
                q = q.where(func.lower(Dut.serial).like(pat.lower(), escape="\\"))
            rows = s.execute(q).all()
            last_ids = [r[2] for r in rows if r[2] is not None]
            states = dict(s.execute(select(DutRun.id, DutRun.state).where(DutRun.id.in_(last_ids))).all()) if last_ids else {}
            return [
                {
                    "serial": d.serial,
                    "sensor": d.sensor,
                    "runs": int(n or 0),
                    "last_run_id": last,
                    "last_state": states.get(last),
                    "last_at": d.last_seen.isoformat() if d.last_seen else None,
                }
                for d, n, last in rows
            ]

    def dut(self, serial: str) -> dict | None:
        d = R.dut_by_serial(self.db, serial)
        if d is None:
            return None
        d["run_id"] = d.get("result_run_id")
        if d["run_id"] is not None:  # where the results come from: batch and time of that run
            run = R.run_detail(self.db, int(d["run_id"])) or {}
            d["batch_id"] = run.get("batch_id")
            d["finished_at"] = run.get("ended_at")
        return _with_methods(d)

    def runs_of_dut(self, serial: str) -> list[dict] | None:
        runs = R.runs_of_dut(self.db, serial)
        if runs is None:
            return None
        return [self.run(r["id"]) or r for r in runs]

    def run(self, run_id: int) -> dict | None:
        r = R.run_detail(self.db, run_id)
        if r is None:
            return None
        r["finished_at"] = r.get("ended_at")
        return _with_methods(r)

    def batch(self, batch_id: int) -> dict | None:
        b = R.batch_detail(self.db, batch_id)
        if b is None:
            return None
        b.pop("config_snapshot", None)
        b["error"] = b.get("reason") or None
        b["slots"] = [
            {"slot": r["slot"], "serial": r["serial"], "state": r["state"], "segments": r.get("n_segments", 0),
             "error": r.get("fault_reason") or None, "run_id": r["id"], "program_verify": r.get("program_verify"),
             **{k: r.get(k) for k in ("attempt", "verdict", "grade", "tray", "reason", "limits_name", "limits_version")}}
            for r in b.pop("runs", [])
        ]
        b["sorting"] = [{k: sl.get(k) for k in ("slot", "serial", "verdict", "grade", "tray", "reason", "attempt")}
                        for sl in b["slots"] if sl.get("verdict")]
        from station.decisions.verdicts import summarize

        b["decision"] = summarize(sl if sl.get("verdict") else None for sl in b["slots"])
        counts = {"running": 0, "done": 0, "faulted": 0, "interrupted": 0}  # as the live status counts
        for sl in b["slots"]:
            key = "running" if sl["state"] in ("connecting", "identified", "running") else sl["state"]
            counts[key] = counts.get(key, 0) + 1
        b["counts"] = counts
        b["stored"] = True
        return b

    def segments(self, run_id: int) -> list[dict] | None:
        return R.segments_of_run(self.db, run_id)

    def run_log(self, run_id: int) -> DutLog | None:
        from db.export import run_log

        try:
            return run_log(self.db, run_id)
        except KeyError:
            return None

    def results_since(self, after_id: int = 0, since_time: float | None = None, limit: int = 100,
                      station: str | None = None) -> list[dict]:
        t = None if since_time is None else datetime.fromtimestamp(since_time, tz=timezone.utc)
        rows = R.results_since(self.db, after_id, limit, since_time=t, station=station)
        for r in rows:  # idempotency_key and supersedes: db/mes_record.py mes_key, the one key
            r.pop("supersedes_seq", None)
            if not r.get("created_at"):
                r["created_at"] = r.get("ended_at")
            _with_methods(r)
        return rows

    def outbox_enqueue(self, idempotency_key: str, payload: dict) -> bool:
        """Insert-or-get on the key (two stations' workers may enqueue the same record at once)."""
        return R.outbox_enqueue_new(self.db, idempotency_key, payload)[1]

    def outbox_high_water(self) -> int:
        """Highest result id (result_seq) already in the outbox: a restart scans only newer ones."""
        with self.db.session() as s:
            keys = s.scalars(select(Outbox.idempotency_key).where(Outbox.topic == "result").order_by(Outbox.id.desc()).limit(50)).all()
        best = 0
        for k in keys:
            try:
                best = max(best, int(k.rsplit(":", 1)[1]))
            except (IndexError, ValueError):
                continue
        return best

    def outbox_due(self, now: float, limit: int = 20) -> list[dict]:
        return R.outbox_pending(self.db, limit, now=datetime.fromtimestamp(now, tz=timezone.utc))

    def outbox_mark_delivered(self, entry_id: int) -> None:
        R.outbox_mark_delivered(self.db, entry_id)

    def outbox_mark_failed(self, entry_id: int, error: str, next_attempt_at: float) -> None:
        R.outbox_mark_failed(self.db, entry_id, error, datetime.fromtimestamp(next_attempt_at, tz=timezone.utc))

    def outbox_list(self, limit: int = 100) -> list[dict]:
        with self.db.session() as s:
            rows = s.scalars(select(Outbox).order_by(Outbox.id.desc()).limit(limit)).all()
            out = []
            for o in rows:
                d = R.outbox_json(o)
                d["state"] = "delivered" if o.delivered_at is not None else "pending"
                d.pop("payload", None)
                out.append(d)
            return out

    def yields(self, batch_id: int | None = None) -> dict:
        return R.yields(self.db, batch_id)

    def audit_append(self, actor: str, action: str, target: str = "", detail: dict | None = None) -> None:
        R.audit_append(self.db, actor, action, target, detail)

    def audit_list(self, limit: int = 100, before_id: int | None = None, station: str | None = None) -> list[dict]:
        return R.audit_list(self.db, limit, before_id, station)

    def judged_runs(self, limit: int = 5000, station: str | None = None, **filters) -> list[dict]:
        return R.judged_runs(self.db, limit, station, **filters)

    def judged_facets(self, judged_from=None, judged_to=None) -> list[dict]:
        return R.judged_facets(self.db, judged_from, judged_to)

    def replays(self, limit: int = 50) -> list[dict]:
        return R.replays(self.db, limit)

    def replay(self, batch_id: int) -> dict | None:
        return R.replay_diff(self.db, batch_id)

    def certificate_pdf(self, serial: str) -> bytes | None:
        from station.records.certificate import certificate_for
        from station.records.certificate_pdf import render_pdf

        cert = certificate_for(self.db, serial)
        return None if cert is None else render_pdf(cert)

    def export_file(self, fmt: str, batch_id: int | None = None, run_id: int | None = None) -> bytes | None:
        from station.records.export_formats import export_format
        from station.records.export_model import ExportNotFound, load_report

        writer = export_format(fmt).write  # an unknown format is a KeyError before the database is read
        try:
            report = load_report(self.db, batch_id=batch_id, run_id=run_id)
        except ExportNotFound:
            return None
        return writer(report)

    def health(self) -> str:
        try:
            with self.db.engine.connect() as conn:
                conn.execute(text("SELECT 1"))
            return "ok"
        except Exception as exc:  # noqa: BLE001
            raise StationError(f"database unreachable: {type(exc).__name__}") from None
