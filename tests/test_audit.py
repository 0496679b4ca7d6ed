"""Audit trail (issue 13) over real HTTP: prompt answer, abort and resume through the REST API
each leave one row naming who acted (the person the page names in X-Operator with the token's
name, or the token's name alone) and the station; GET /api/audit is admin only. batch.start is
recorded by the daemon itself for every start, REST, demo or replay (tests/test_line_day.py); here
the route hands it the person and the token."""

from __future__ import annotations

from types import SimpleNamespace

import httpx

from db import Database
from web.app import create_app
from web.auth import TokenStore
from web.db_repo import DbRepository
from web_support import serve_in_thread

OP, ADMIN, MES = "operator-token-audit", "admin-token-audit", "mes-token-audit"


class _FakeStation:
    """The facade's batch methods, recorded (the audit is about the routes, not the daemon)."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def batch_ids(self):
        return []

    def running_batch(self):
        return None

    def start_batch(self, profile, slots, operator, trace=None, by=""):
        self.calls.append(("start", profile, slots, operator, by))
        return 41

    def abort(self, batch_id, reason="", by="operator"):  # the facade's signatures (station/daemon/supervisor.py)
        self.calls.append(("abort", batch_id, by))

    def answer_prompt(self, batch_id, prompt_id, answer="done", by=None, note=""):
        if prompt_id == 99:
            raise ValueError("no prompt 99 is open")
        self.calls.append(("answer", batch_id, prompt_id, answer, by))

    def resume_batch(self, batch_id, operator):
        self.calls.append(("resume", batch_id))
        return batch_id


def test_audit_trail_over_rest(tmp_path):
    db = Database(f"sqlite:///{tmp_path / 'a.db'}", station="line-3")
    db.upgrade()
    fake = _FakeStation()
    app = create_app(SimpleNamespace(config=None, bus=None, db=db, **{k: getattr(fake, k) for k in
                                     ("batch_ids", "running_batch", "start_batch", "abort", "answer_prompt", "resume_batch")}),
                     repo=DbRepository(db), outbox=False,
                     tokens=TokenStore([(OP, "operator", "anna (operator)"), (ADMIN, "admin", "lead"), (MES, "mes", "mes")]))
    url, stop_server = serve_in_thread(app)
    try:
        base = url
        op = httpx.Client(base_url=base, timeout=30, headers={"Authorization": f"Bearer {OP}"})
        admin = httpx.Client(base_url=base, timeout=30, headers={"Authorization": f"Bearer {ADMIN}"})
        r = op.post("/api/batches", json={"profile": "fast-thermal", "slots": ["s01", "s02"], "operator": "Anna K"})
        assert r.status_code == 201, r.text
        assert op.post("/api/batches/41/prompt", json={"prompt_id": 3, "answer": "done"}).status_code == 200
        assert op.post("/api/batches/41/prompt", json={"prompt_id": 99}).status_code == 409  # refused: not audited
        assert op.post("/api/batches/41/abort", headers={"X-Operator": "Anna  K"}).status_code == 200
        assert admin.post("/api/batches/41/resume").status_code == 200
        # the daemon is told who acted (the batch's ended_by / the prompt's answerer), by token name
        assert ("abort", 41, "Anna K (token anna (operator))") in fake.calls
        assert ("answer", 41, 3, "done", "anna (operator)") in fake.calls
        assert ("start", "fast-thermal", ["s01", "s02"], "Anna K", "REST: anna (operator)") in fake.calls
        # admin only
        assert op.get("/api/audit").status_code == 403
        assert httpx.get(f"{base}/api/audit", headers={"Authorization": f"Bearer {MES}"}).status_code == 403
        assert httpx.get(f"{base}/api/audit").status_code == 401
        r = admin.get("/api/audit")
        assert r.status_code == 200
        rows = r.json()
        assert [(a["action"], a["actor"], a["target"]) for a in rows] == [
            ("batch.resume", "lead", "batch 41"),
            ("batch.abort", "Anna K (token anna (operator))", "batch 41"),
            ("prompt.answer", "anna (operator)", "batch 41"),
        ]
        assert {a["station"] for a in rows} == {"line-3"}
        assert rows[2]["detail"] == {"prompt_id": 3, "answer": "done"}
        assert all(OP not in str(a) and ADMIN not in str(a) for a in rows)  # names, never tokens
        page = admin.get("/api/audit", params={"limit": 2, "before_id": rows[0]["id"]}).json()
        assert [a["action"] for a in page] == ["batch.abort", "prompt.answer"]
        assert admin.get("/api/audit", params={"station": "other"}).json() == []
        op.close()
        admin.close()
    finally:
        stop_server()
        db.dispose()


def test_limit_set_changes_are_audited_at_start(tmp_path):
    """The limits live in the config: each start compares them with the last recorded ones."""
    from db import repository as repo
    from station.config import parse_config
    from station.decisions.limits_audit import record_limit_changes
    from station.decisions.limits import default_products

    db = Database(f"sqlite:///{tmp_path / 'l.db'}", station="line-3")
    db.upgrade()
    base = {"name": "line-3", "slots": [{"name": "s1", "serial": "/dev/null"}], "lamp": {"tcp": {"host": "127.0.0.1", "port": 1}, "unit": 1}}
    first = record_limit_changes(db, parse_config(base))
    assert first is not None and "LIS3DSH" in first["added"]
    assert record_limit_changes(db, parse_config(base)) is None  # unchanged: nothing recorded
    spec = default_products()["LIS3DSH"].model_dump(mode="json")
    spec["limits"][0]["high"] = 1.2  # edited without a version bump
    changed = record_limit_changes(db, parse_config({**base, "products": {"LIS3DSH": spec}}))
    v = spec["version"]  # the built-in set's version (2 since issue 21), unchanged by the edit
    assert changed["changed"] == [{"set": "LIS3DSH", "old_version": v, "new_version": v, "version_bumped": False}]
    rows = repo.audit_list(db)
    assert [(a["action"], a["actor"], a["station"]) for a in rows] == [("limits.change", "config", "line-3")] * 2
    db.dispose()
