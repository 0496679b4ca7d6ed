"""Replay reproduces what the line did (issue 22), where something went wrong: a program-and-verify
batch in which one board refused its calibration write, and a batch in which one board was unplugged.
And the source of a replay is only ever read: never created, never migrated.

Independent truth: the recorded and the replayed database rows (program records with their CRC,
run states), and the source file's bytes.
"""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest

from replay_line_checks import assert_tight_limits_name_the_changed_verdicts, assert_unchanged, recorded_batch, replay
from replay_recorder import Script, station_cli


def _db(url: str):
    from db.database import Database

    return Database(url)


def _program_rows(url: str, batch: int) -> dict[str, tuple]:
    from sqlalchemy import select

    from db.models import DutRun, ProgramVerifyRow

    db = _db(url)
    try:
        with db.session() as s:
            rows = s.execute(select(DutRun.slot, ProgramVerifyRow.programmed, ProgramVerifyRow.crc,
                                    ProgramVerifyRow.error_kind, ProgramVerifyRow.verified)
                             .join(ProgramVerifyRow, ProgramVerifyRow.run_id == DutRun.id)
                             .where(DutRun.batch_id == batch)).all()
        return {r[0]: tuple(r[1:]) for r in rows}
    finally:
        db.dispose()


@pytest.fixture(scope="module")
def verified_batch(tmp_path_factory):
    return recorded_batch(tmp_path_factory, "verified", Script(profile="fast-thermal-verified", refuse_write_slot=1))


def test_a_verified_batch_with_a_refused_write_replays_unchanged(verified_batch):
    folder, url, rec = verified_batch
    assert rec["slots"]["s02"]["verdict"] == "error" and rec["slots"]["s02"]["state"] == "faulted", rec
    good = [k for k, v in rec["slots"].items() if k != "s02"]
    assert all(rec["slots"][k]["verdict"] in ("pass", "marginal") for k in good), rec
    p, diff = replay(url, rec["batch"], folder / "same.json")
    assert_unchanged(p, diff, rec)
    before = _program_rows(url, rec["batch"])
    after = _program_rows(url, diff["replay_batch_id"])
    # the coefficients written now are those written then, to the bit (CRC-32 over float32)
    for slot in good:
        programmed, crc, error_kind, verified = before[slot]
        assert programmed is True and crc and error_kind in ("", None) and verified is True, before
        assert after[slot] == before[slot], (slot, before, after)
    # the refused write is refused again, and that part stays error
    assert before["s02"][0] is False and before["s02"][2] == "refused", before
    assert after["s02"][0] is False and after["s02"][2] == "refused", after
    verdicts = {d["slot"]: d for d in diff["duts"]}
    assert "program: refused" in verdicts["s02"]["note"], verdicts["s02"]


def test_a_verified_batch_under_another_limits_set_names_the_changed_verdicts(verified_batch):
    folder, url, rec = verified_batch
    diff = assert_tight_limits_name_the_changed_verdicts(url, rec["batch"], folder, rec)
    s02 = next(d for d in diff["duts"] if d["slot"] == "s02")
    assert s02["changed"] is False  # error stays error


@pytest.fixture(scope="module")
def faulted_batch(tmp_path_factory):
    folder, url, rec = recorded_batch(tmp_path_factory, "faulted",
                                      Script(profile="fast-thermal", unplug_slot=2, unplug_at_sample_s=300.0))
    assert rec["slots"]["s03"]["state"] == "faulted", rec
    return folder, url, rec


def test_a_batch_with_a_faulted_slot_replays_unchanged(faulted_batch):
    folder, url, rec = faulted_batch
    p, diff = replay(url, rec["batch"], folder / "same.json")
    assert_unchanged(p, diff, rec)
    s03 = next(d for d in diff["duts"] if d["slot"] == "s03")
    assert "faulted" not in [c["after"] for c in s03["changes"]]
    from db import repository as R

    db = _db(url)
    try:
        runs = {r["slot"]: r for r in R.batch_detail(db, diff["replay_batch_id"])["runs"]}
    finally:
        db.dispose()
    assert runs["s03"]["state"] == "faulted" and runs["s03"]["verdict"] == "error", runs["s03"]
    assert "link lost" in runs["s03"]["fault_reason"], runs["s03"]  # unplugged again, as recorded
    assert all(runs[s]["state"] == "done" for s in runs if s != "s03"), runs


def test_a_batch_with_a_faulted_slot_under_another_limits_set_names_the_changed_verdicts(faulted_batch):
    folder, url, rec = faulted_batch
    assert_tight_limits_name_the_changed_verdicts(url, rec["batch"], folder, rec)


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_the_source_database_is_read_only_never_created_or_migrated(faulted_batch, tmp_path):
    from alembic import command

    folder, url, rec = faulted_batch
    missing = tmp_path / "nope.db"
    p = station_cli("replay", "--db", f"sqlite:///{missing}", "--batch", "1")
    assert p.returncode == 2 and "no such file" in p.stderr and "Traceback" not in p.stderr, p.stderr
    assert not missing.exists()

    # a copy from a station on the previous release: one schema revision older
    old = tmp_path / "old.db"
    shutil.copy(Path(url[len("sqlite:///"):]), old)
    db = _db(f"sqlite:///{old}")
    try:
        with db.engine.begin() as conn:
            command.downgrade(db._alembic_config(conn), "-1")
        rev = db.current_revision()
    finally:
        db.dispose()
    assert rev != db.head_revision()
    digest = _sha(old)
    p = station_cli("replay", "--db", f"sqlite:///{old}", "--batch", str(rec["batch"]))
    assert p.returncode == 2 and "never migrates its source" in p.stderr, p.stderr
    assert _sha(old) == digest
    out = tmp_path / "replays.db"
    p, diff = replay(f"sqlite:///{out}", rec["batch"], tmp_path / "old.json", "--source-db", f"sqlite:///{old}")
    assert_unchanged(p, diff, rec)
    assert "migrated copy" in p.stderr and _sha(old) == digest
