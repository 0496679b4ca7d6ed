"""Alembic migrations: a fresh database upgrades to head on SQLite and PostgreSQL, the models match
the hand-written revision, and a database from newer software is refused with a clear message."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import inspect, text

from db import Database, DbWriter
from db import repository as repo
from db.export import run_log
from db.models import SCHEMA_REVISION, Base
from contracts.events import DutResult, DutVerdict, SamplesReceived, SegmentLogged, SlotStateChanged
from contracts.run_records import ThermalReport
from contracts.sfem_result import SfemResult
from contracts.logfile import ACC_DECIMALS, TEMP_DECIMALS
from contracts.types import SampleBlock, StationError
from db_helpers import SFEM_JSON, THERMAL_JSON, lis3dsh_stream, pg_database, pg_reachable, segment

TABLES = {"dut", "batch", "dut_run", "segment", "thermal_result", "sfem_result", "sample_chunk", "outbox", "alembic_version",
          "result_counter", "audit", "verdict_history", "writer_commit",
          "program_verify"}


def _assert_schema_matches_models(db: Database) -> None:
    with db.engine.connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn, opts={"compare_type": True}), Base.metadata)
    assert diff == [], diff


def _stamp(db: Database, rev: str) -> None:
    with db.engine.begin() as conn:
        conn.execute(text("UPDATE alembic_version SET version_num = :v"), {"v": rev})


def test_fresh_sqlite_upgrade(tmp_path):
    db = Database(f"sqlite:///{tmp_path / 'sub' / 'station.db'}")  # parent directory created
    assert db.current_revision() is None
    assert db.upgrade() == SCHEMA_REVISION == db.head_revision()
    assert set(inspect(db.engine).get_table_names()) == TABLES
    _assert_schema_matches_models(db)
    assert db.check() == SCHEMA_REVISION
    assert db.upgrade() == SCHEMA_REVISION  # idempotent
    with db.engine.connect() as conn:
        assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
        assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
        assert conn.exec_driver_sql("PRAGMA synchronous").scalar() == 2  # FULL
    assert db.sqlite_integrity_check() == "ok"


def test_foreign_keys_are_enforced(tmp_path):
    db = Database(f"sqlite:///{tmp_path / 'x.db'}")
    db.upgrade()
    with pytest.raises(Exception, match="FOREIGN KEY"):
        db.create_run(12345, "s1", "SIM1", "LIS3DSH", {})


def test_newer_database_is_refused(tmp_path):
    db = Database(f"sqlite:///{tmp_path / 'x.db'}")
    db.upgrade()
    _stamp(db, "9999_from_the_future")
    for call in (db.upgrade, db.check):
        with pytest.raises(StationError) as exc:
            call()
        msg = str(exc.value)
        assert "'9999_from_the_future'" in msg and "newer than" in msg and f"'{SCHEMA_REVISION}'" in msg
    # the schema was not touched
    with db.engine.connect() as conn:
        assert conn.exec_driver_sql("SELECT version_num FROM alembic_version").scalar() == "9999_from_the_future"
    r = subprocess.run([sys.executable, "-m", "cli", "db", "--url", str(db.engine.url), "upgrade"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "newer than" in r.stderr


def test_outdated_database_check_asks_for_upgrade(tmp_path):
    db = Database(f"sqlite:///{tmp_path / 'x.db'}")
    with pytest.raises(StationError, match="station db upgrade"):
        db.check()


def _round_trip(db: Database) -> None:
    """Writer, repository and export on this backend."""
    batch = db.create_batch("fast-thermal", "op", {"database_url": "x", "nested": {"a": [1, 2]}})
    run = db.create_run(batch, "s1", "PG0001", "LIS3DSH", {"serial": "PG0001"})
    time_s, acc, temp = lis3dsh_stream(3000)
    w = DbWriter(db, interval_s=0.05, seal_samples=1000)
    w.bind_run(batch, "s1", run)
    for i in range(0, 3000, 37):
        w.submit(SamplesReceived(batch, "s1", "PG0001", 0, SampleBlock(time_s[i:i + 37], acc[i:i + 37], temp[i:i + 37]), position=0))
    w.submit(SegmentLogged(batch, "s1", "PG0001", 0, segment(0)))
    w.submit(DutResult(batch, "s1", "PG0001", thermal=ThermalReport.from_json(THERMAL_JSON), sfem=SfemResult.from_json(SFEM_JSON)))
    w.submit(SlotStateChanged(batch, "s1", "PG0001", "done"))
    w.submit(DutVerdict(batch, "s1", "PG0001", verdict={"verdict": "pass", "grade": "A", "tray": "T1"}))  # the MES record
    w.close()
    out = run_log(db, run)
    assert np.array_equal(out.acc_g, np.round(acc, ACC_DECIMALS))
    assert np.array_equal(out.temp_c, np.round(temp, TEMP_DECIMALS))
    d = repo.dut_by_serial(db, "PG0001")
    assert d["thermal_method"] == "offline" and d["thermal"]["z"]["tdsf_ppm_per_c"] == -299.0
    assert d["thermal_by_method"]["streaming"]["y"]["tdsf_clamped"] is True
    assert d["sfem"]["steps"][1]["temp_c"] == 45.0 and d["sfem"]["thermal"]["coef"]["scale"][1][0] == 1e-5
    assert repo.segments_of_run(db, run)[0]["acc_mean_g"][1] == 0.578
    assert repo.batch_detail(db, batch)["config_snapshot"]["nested"] == {"a": [1, 2]}
    assert [(r["run_id"], r["revision"], r["verdict"]) for r in repo.results_since(db, 0)] == [(run, 1, "pass")]


def test_sqlite_round_trip(tmp_path):
    db = Database(f"sqlite:///{tmp_path / 'x.db'}")
    db.upgrade()
    _round_trip(db)


@pytest.mark.postgres
def test_postgresql_fresh_upgrade_round_trip_and_refusal():
    if not pg_reachable():
        pytest.skip("PostgreSQL not reachable on 127.0.0.1:5432")
    with pg_database() as url:
        db = Database(url)
        try:
            assert db.current_revision() is None
            assert db.upgrade() == SCHEMA_REVISION
            assert set(inspect(db.engine).get_table_names()) == TABLES
            _assert_schema_matches_models(db)
            _round_trip(db)
            _stamp(db, "9999_from_the_future")
            with pytest.raises(StationError, match="newer than"):
                db.upgrade()
        finally:
            db.dispose()
