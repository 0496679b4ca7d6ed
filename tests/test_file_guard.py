"""db.file_guard (issue 37): a SQLite file deleted, replaced or moved under the station is noticed at
once, the still-open file's content (WAL included) is rescued, and a start on a missing/smaller
database is refused unless a new database is asked for."""

from __future__ import annotations

import json
import logging
import os
import re
import sqlite3
import sys
import threading
import time
from pathlib import Path

import pytest

from contracts.types import StationError
from db.file_guard import StoreFile

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs /proc/self/fd")


def wal_db(path: Path, rows_checkpointed: int = 5, rows_in_wal: int = 7) -> sqlite3.Connection:
    """A WAL database with an open connection: the first rows checkpointed into the main file, the
    rest only in the -wal (autocheckpoint off)."""
    conn = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
    assert conn.execute("PRAGMA journal_mode=WAL").fetchone()[0] == "wal"
    conn.execute("PRAGMA wal_autocheckpoint=0")
    conn.execute("CREATE TABLE batch (id INTEGER PRIMARY KEY, note TEXT)")
    for i in range(1, rows_checkpointed + 1):
        conn.execute("INSERT INTO batch (id, note) VALUES (?, ?)", (i, f"main {i}"))
    conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    for i in range(rows_checkpointed + 1, rows_checkpointed + rows_in_wal + 1):
        conn.execute("INSERT INTO batch (id, note) VALUES (?, ?)", (i, "wal " + "x" * 2000))
    return conn


def rows_of(path: Path) -> list[int]:
    conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        return [r[0] for r in conn.execute("SELECT id FROM batch ORDER BY id")]
    finally:
        conn.close()


def remove_database(path: Path) -> None:
    """What `rm station.db*` does."""
    for suffix in ("", "-wal", "-shm"):
        Path(f"{path}{suffix}").unlink(missing_ok=True)


# -- of_url -----------------------------------------------------------------------------------------


def test_of_url(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    assert StoreFile.of_url(f"sqlite:///{tmp_path}/a.db").path == tmp_path / "a.db"
    assert StoreFile.of_url("sqlite:///~/b.db").path == tmp_path / "b.db"
    monkeypatch.chdir(tmp_path)
    assert StoreFile.of_url("sqlite:///rel/c.db").path == tmp_path / "rel" / "c.db"
    assert StoreFile.of_url(f"sqlite:///file:{tmp_path}/d.db?mode=rwc&uri=true").path == tmp_path / "d.db"
    for url in ("sqlite://", "sqlite:///:memory:", "sqlite:///file:x?mode=memory&uri=true",
                "postgresql+psycopg://u:p@localhost/station", "not a url"):
        assert StoreFile.of_url(url) is None, url


# -- problem() and rescue() -------------------------------------------------------------------------


@linux_only
def test_deleted_is_reported_at_once_and_rescued_with_wal_rows(tmp_path):
    path = tmp_path / "station.db"
    conn = wal_db(path)
    guard = StoreFile(path)
    guard.opened()
    assert guard.problem() is None
    assert guard.rescue() is None  # nothing to rescue while the file is in place
    assert Path(f"{path}-wal").stat().st_size > 0  # rows 6..12 live only in the WAL

    remove_database(path)
    assert guard.problem() == f"the database file {path} was deleted while the station used it"

    rescued = guard.rescue()
    assert rescued is not None and rescued.parent == tmp_path
    assert re.fullmatch(r"station\.db\.rescued-\d{8}T\d{6}", rescued.name)
    assert rows_of(rescued) == list(range(1, 13))
    assert not Path(f"{rescued}-wal").exists()  # one self-contained file
    assert sorted(p.name for p in tmp_path.iterdir()) == [rescued.name]  # no work files left

    # the station's own connection is unharmed: it still writes (to the deleted file) and reads
    conn.execute("INSERT INTO batch (id, note) VALUES (13, 'after')")
    assert conn.execute("SELECT count(*) FROM batch").fetchone()[0] == 13
    second = guard.rescue()
    assert second is not None and second != rescued
    assert rows_of(second) == list(range(1, 14))
    conn.close()


@linux_only
def test_only_the_main_file_deleted_still_rescues_the_wal(tmp_path):
    path = tmp_path / "station.db"
    conn = wal_db(path, rows_checkpointed=2, rows_in_wal=3)
    guard = StoreFile(path)
    guard.opened()
    path.unlink()  # the -wal and -shm stay at their names
    assert "was deleted" in guard.problem()
    assert rows_of(guard.rescue()) == [1, 2, 3, 4, 5]
    conn.close()


@linux_only
def test_rescue_while_the_station_keeps_writing(tmp_path):
    """Writes (with autocheckpoints, so WAL restarts) continue during the copy: the rescued file is
    intact and holds at least every row committed before rescue() was called."""
    path = tmp_path / "station.db"
    conn = wal_db(path, rows_checkpointed=1, rows_in_wal=1)
    conn.execute("PRAGMA wal_autocheckpoint=20")
    guard = StoreFile(path)
    guard.opened()
    remove_database(path)
    stop = threading.Event()
    committed = [2]

    def writer() -> None:
        i = 3
        while not stop.is_set():
            conn.execute("INSERT INTO batch (id, note) VALUES (?, ?)", (i, "y" * 3000))
            committed[0] = i
            i += 1

    t = threading.Thread(target=writer)
    t.start()
    try:
        time.sleep(0.05)
        results = []
        for _ in range(5):
            before = committed[0]
            rescued = guard.rescue()
            ids = rows_of(rescued)
            results.append((before, ids))
    finally:
        stop.set()
        t.join()
    for before, ids in results:
        assert ids == list(range(1, len(ids) + 1)) and len(ids) >= before
    conn.close()


@linux_only
def test_replaced_is_reported(tmp_path):
    path = tmp_path / "station.db"
    conn = wal_db(path)
    guard = StoreFile(path)
    guard.opened()
    other = tmp_path / "backup.db"
    sqlite3.connect(other).close()
    os.replace(other, path)  # e.g. a restore copied over the live file
    msg = guard.problem()
    assert msg == (f"the database file {path} was replaced by another file while the station used it "
                   f"(the one in use was deleted)")
    assert rows_of(guard.rescue()) == list(range(1, 13))
    conn.close()


@linux_only
def test_written_anew_is_reported_as_replaced(tmp_path):
    path = tmp_path / "station.db"
    conn = wal_db(path)
    guard = StoreFile(path)
    guard.opened()
    remove_database(path)
    path.write_bytes(b"not even sqlite")  # another file written at the path
    assert guard.problem().startswith(f"the database file {path} was replaced by another file")
    conn.close()


@linux_only
def test_moved_is_reported_with_the_new_name(tmp_path):
    path = tmp_path / "station.db"
    conn = wal_db(path)
    guard = StoreFile(path)
    guard.opened()
    moved = tmp_path / "elsewhere.db"
    path.rename(moved)
    assert guard.problem() == f"the database file {path} was moved to {moved} while the station used it"
    moved.rename(path)  # put back: all well again
    assert guard.problem() is None
    path.rename(moved)
    sqlite3.connect(path).close()  # and a new file where it was
    assert guard.problem() == (f"the database file {path} was replaced by another file while the station used "
                               f"it (the one in use is now {moved})")
    conn.close()


def test_no_open_descriptor_says_gone(tmp_path):
    path = tmp_path / "station.db"
    sqlite3.connect(path).execute("CREATE TABLE t (x)").connection.close()
    guard = StoreFile(path)
    assert guard.problem() is None  # not opened yet: nothing to compare
    guard.opened()
    path.unlink()
    assert guard.problem() == (f"the database file {path} disappeared (deleted or moved) while the station "
                               f"used it")
    assert guard.rescue() is None


@linux_only
def test_works_through_a_sqlalchemy_engine(tmp_path):
    from sqlalchemy import create_engine, text

    path = tmp_path / "station.db"
    engine = create_engine(f"sqlite:///{path}")
    with engine.begin() as c:
        c.execute(text("PRAGMA journal_mode=WAL"))
        c.execute(text("CREATE TABLE batch (id INTEGER PRIMARY KEY)"))
        c.execute(text("INSERT INTO batch (id) VALUES (1), (2), (3)"))
    guard = StoreFile.of_url(str(engine.url))
    guard.opened()
    remove_database(path)
    assert "was deleted" in guard.problem()
    assert rows_of(guard.rescue()) == [1, 2, 3]
    engine.dispose()


# -- marker -----------------------------------------------------------------------------------------


def test_marker_round_trip(tmp_path):
    guard = StoreFile(tmp_path / "station.db")
    assert guard.read_marker() is None
    guard.write_marker(3, 7, schema="0009")
    m = guard.read_marker()
    assert (m.path, m.batches, m.max_batch_id, m.schema) == (str(tmp_path / "station.db"), 3, 7, "0009")
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", m.created_utc)
    assert json.loads(guard.marker_path.read_text())["batches"] == 3
    assert guard.marker_path.name == "station.db.marker.json"

    first_created = m.created_utc
    guard.write_marker(4, 8)
    m = guard.read_marker()
    assert (m.batches, m.max_batch_id, m.created_utc, m.schema) == (4, 8, first_created, "0009")
    assert [p.name for p in tmp_path.iterdir()] == ["station.db.marker.json"]  # no tmp files left


def test_no_marker_passes_and_records(tmp_path):
    guard = StoreFile(tmp_path / "station.db")
    guard.check_before_open(allow_new=False)  # first start: no file, no marker
    guard.check_at_open(0, 0, allow_new=False)
    m = guard.read_marker()
    assert (m.batches, m.max_batch_id) == (0, 0)


def test_missing_or_empty_file_is_refused(tmp_path):
    path = tmp_path / "station.db"
    guard = StoreFile(path)
    guard.write_marker(12, 57)
    with pytest.raises(StationError) as err:
        guard.check_before_open(allow_new=False)
    msg = str(err.value)
    assert "\n" not in msg and "is missing" in msg and "12 batches (highest id 57)" in msg
    assert "restore the file from a backup" in msg and "--new-database" in msg

    path.touch()  # what the engine would create
    with pytest.raises(StationError, match="is empty"):
        guard.check_before_open(allow_new=False)
    assert guard.read_marker().batches == 12  # untouched by a refusal


def test_fewer_batches_or_lower_max_id_is_refused(tmp_path):
    path = tmp_path / "station.db"
    wal_db(path).close()
    guard = StoreFile(path)
    guard.write_marker(12, 57)
    guard.check_before_open(allow_new=False)  # the file has data: the count check decides
    with pytest.raises(StationError, match=r"holds 3 batches \(highest id 57\).*--new-database"):
        guard.check_at_open(3, 57, allow_new=False)
    with pytest.raises(StationError, match=r"holds 12 batches \(highest id 3\)"):
        guard.check_at_open(12, 3, allow_new=False)
    guard.check_at_open(13, 60, allow_new=False)  # grew: fine, and recorded
    assert (guard.read_marker().batches, guard.read_marker().max_batch_id) == (13, 60)


def test_allow_new_warns_and_rewrites_the_marker(tmp_path, caplog):
    path = tmp_path / "station.db"
    guard = StoreFile(path)
    guard.write_marker(12, 57)
    old_created = guard.read_marker().created_utc
    caplog.set_level(logging.WARNING, logger="db.file_guard")
    guard.check_before_open(allow_new=True)
    assert "is missing" in caplog.text and "--new-database" in caplog.text
    assert (guard.read_marker().batches, guard.read_marker().max_batch_id) == (0, 0)
    guard.check_at_open(0, 0, allow_new=False)  # the new empty database then opens normally

    guard.write_marker(12, 57)
    caplog.clear()
    guard.check_at_open(2, 2, allow_new=True, schema="0009")
    assert "holds 2 batches" in caplog.text
    m = guard.read_marker()
    assert (m.batches, m.max_batch_id, m.schema) == (2, 2, "0009")
    assert m.created_utc >= old_created


def test_unreadable_marker(tmp_path):
    guard = StoreFile(tmp_path / "station.db")
    guard.marker_path.write_text("{not json")
    with pytest.raises(StationError, match="unreadable"):
        guard.check_before_open(allow_new=False)
    guard.check_before_open(allow_new=True)  # ignored as asked
    guard.check_at_open(1, 1, allow_new=True)
    assert guard.read_marker().batches == 1
