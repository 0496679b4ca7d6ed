"""What a replay plays back: per DUT the raw counts, identity and sample clock, plus the plate.

Two sources:
- a stored batch (`from_database`): every run's sample chunks (db/codec.py keeps them at the log's
  precision, which is finer than any sensor's LSB, so the counts come back exactly), its identity
  as the board reported it, its link (serial or CAN, from the batch's config snapshot), the
  lamp and position the station recorded beside every sample, and the outcome it stored;
- design-5.1 logs (`from_logs`): a log holds g and C, not counts, so its replay board reports an
  identity with the log's own precision as LSB (0.1 ug, 0.1 mC): the values go over the wire
  unchanged. The outcome to compare with is the offline science on the same file
  (`station calibrate`), since a log carries no stored result.
"""

from __future__ import annotations

import dataclasses

from pathlib import Path
from typing import Any

import numpy as np

from contracts.logfile import DutLog, read_log
from contracts.recording import LOG_T_LSB_PER_C, LOG_UG_PER_LSB, RecordedDut, Recording, to_counts
from contracts.types import Identity, StationError
from db.database import plain_url
from station.daemon.identity_check import serial_problem


def _identity(d: dict[str, Any], serial: str) -> Identity:
    keys = ("sensor", "fw", "ug_per_lsb", "t_lsb_per_c", "t_lsb_at_25c", "odr_hz")
    return Identity(serial=serial, **{k: d[k] for k in keys if d.get(k) is not None})


# ---- from the station database ----------------------------------------------------------------
def _slot_links(snapshot: dict[str, Any]) -> dict[str, str]:
    return {s.get("name"): ("can" if s.get("can") else "serial") for s in snapshot.get("slots") or []}


def open_source(db_url: str, station: str = "replay") -> tuple[Any, str, Any]:
    """The database a recording is read from, opened read-only: never created, never migrated.
    A SQLite file of an older schema (a copy from a station on an older release) is read through a
    migrated temporary copy; (database, note, cleanup)."""
    import shutil
    import sqlite3
    import tempfile

    from db.database import Database

    src = Database(db_url, station=station, read_only=True)
    try:
        rev = src.current_revision()
        if rev is None:
            raise StationError(f"database {plain_url(db_url)} holds no station data (no schema): nothing to replay")
        src._refuse_unknown(rev)
        head = src.head_revision()
        if rev == head:
            return src, "", None
        if not src.is_sqlite:
            raise StationError(f"database {plain_url(db_url)} has schema {rev}, this software reads {head}: "
                               "a replay never migrates its source: upgrade it (station db upgrade) or replay a copy")
        folder = tempfile.mkdtemp(prefix="station-replay-")
        copy = Path(folder) / "source.db"
        with src.engine.connect() as conn:
            raw = conn.connection.driver_connection
            dst = sqlite3.connect(copy)
            try:
                raw.backup(dst)
            finally:
                dst.close()
    finally:
        src.dispose()
    db = Database(f"sqlite:///{copy}", station=station)
    db.upgrade()
    note = f"read through a migrated copy (schema {rev} -> {head}); the source file is unchanged"
    return db, note, lambda: shutil.rmtree(folder, ignore_errors=True)


def from_database(db_url: str, batch_id: int, station: str = "replay") -> Recording:
    """A stored batch (also from a database copied from another station), read without changing it."""
    from db import repository as R
    from db.export import run_samples

    db, source_note, cleanup = open_source(db_url, station)
    try:
        batch = R.batch_detail(db, int(batch_id))
        if batch is None:
            raise StationError(f"no batch {batch_id} in {db_url}")
        snapshot = dict(batch.get("config_snapshot") or {})
        links = _slot_links(snapshot)
        last_run: dict[str, dict] = {}
        for run in batch["runs"]:  # the last run of each slot (a reconnect makes no new run, a retest does)
            last_run[run["slot"]] = run
        duts, skipped = [], []
        for slot, run in last_run.items():
            serial = run["serial"]
            if run.get("samples_pruned_at"):
                skipped.append(f"{slot} {serial}: samples pruned on {run['samples_pruned_at'][:10]}")
                continue
            smp = run_samples(db, run["id"])
            if not len(smp):
                skipped.append(f"{slot} {serial}: no samples recorded ({run['state']}: {run['fault_reason'] or '-'})")
                continue
            ident = _identity(run.get("identity") or {}, serial)
            acc, tc = to_counts(ident, smp.acc_g, smp.temp_c, f"batch {batch_id} slot {slot}")
            outcome = run_outcome(db, run)
            program = R.program_record(db, run["id"]) or {}
            duts.append(RecordedDut(
                slot=slot, serial=serial, link=links.get(slot, "serial"), identity=ident, time_s=smp.time_s,
                acc_counts=acc, temp_counts=tc, lamp=smp.lamp.astype(np.int8), position=smp.position.astype(np.int64),
                lost_samples=int(run.get("lost_samples") or 0), source_run_id=run["id"], outcome=outcome,
                restart_after_t=program.get("comp_from_t") if program.get("programmed") else None,
                program_error_kind=None if program.get("programmed") else program.get("error_kind"),
                unplugged_at_end=run["state"] == "faulted" and "link lost" in (run.get("fault_reason") or ""),
                step_start_t=_step_starts(batch.get("step_windows") or {}, slot)))
        if not duts:
            raise StationError(f"batch {batch_id}: nothing to replay ({'; '.join(skipped) or 'no runs'})")
        where = batch.get("station") or "?"
        kind = f"replay of {batch['replay_of']}" if batch.get("replay_of") else f"batch {batch_id} of {where}"
        return Recording(f"{kind} ({plain_url(db_url)})", batch["profile"], duts, snapshot, skipped,
                         batch_state=batch["state"], batch_error=batch.get("reason") or "", source_note=source_note)
    finally:
        db.dispose()
        if cleanup is not None:
            cleanup()


def _step_starts(step_windows: dict, slot: str) -> dict[int, float]:
    """{step: board time the step began at} for one slot, from a batch's step_windows
    ({"<step>": {"<slot>": [from_s, to_s]}}); steps without a finite start are left out."""
    out = {}
    for k, by_slot in step_windows.items():
        w = (by_slot or {}).get(slot)
        if w and w[0] is not None and np.isfinite(float(w[0])):
            out[int(k)] = float(w[0])
    return out


def run_outcome(db: Any, run: dict[str, Any]) -> dict[str, Any]:
    """What a stored run came to (compare.py's input): its state, verdict and grade, and its
    results as the repository reports them. The recording and the replay are read the same way."""
    from db import repository as R

    with db.session() as s:
        results = R._run_results(s, run["id"])
    return {"state": run["state"], "verdict": run.get("verdict"), "grade": run.get("grade"), **results}


# ---- from design-5.1 logs ---------------------------------------------------------------------
def _odr_of(log: DutLog) -> float:
    if log.meta.get("odr_hz"):
        try:
            return float(log.meta["odr_hz"])
        except ValueError:
            pass
    dt = np.diff(log.time_s)
    dt = dt[dt > 0]
    if not len(dt):
        raise StationError(f"log of {log.serial or '?'}: fewer than two distinct sample times")
    return float(1.0 / np.median(dt))


def log_outcome(log: DutLog, positions: list[int] | None = None) -> dict[str, Any]:
    """The outcome to compare a log's replay with: the offline science on the file itself. A log
    without a position column is placed as the station places a run of the profile (`positions`,
    its steps' positions in order: station/science/placement.sequence_labels), so the samples a
    turn or a settling plate measured are left out as the replaying station leaves them out."""
    from station.science.placement import sequence_labels
    from station.science.thermal_calibration import calibrate, fit_samples, placed_only

    if log.position is None and positions:
        log = dataclasses.replace(log, position=sequence_labels(log.time_s, log.acc_g, positions))
    ends = [s["t_end_s"] for s in calibrate(log)["segments"]]
    placed, _ = placed_only(log.block(), log.position)
    res = calibrate(fit_samples(placed, ends))  # the station's rule (fit_samples)
    by_method = {m: {ax: {k: v[k] for k in ("tdb_mg_per_c", "tdsf_ppm_per_c")} for ax, v in res[m]["axes"].items()}
                 for m in ("offline", "streaming")}
    return {"partial": True, "thermal_by_method": by_method}


def from_logs(paths: list[str | Path], profile: str | None = None, compare: bool = True) -> Recording:
    """Design-5.1 CSV logs, one per DUT (serial from `# serial:` or the file name)."""
    if not paths:
        raise StationError("no log files given")
    duts, prof_meta = [], set()
    logs: list[DutLog] = []
    seen: set[str] = set()
    for k, p in enumerate(paths):
        log = read_log(p)
        if not len(log):
            raise StationError(f"{p}: no samples")
        if np.any(np.diff(log.time_s) <= 0):
            raise StationError(f"{p}: sample times must increase")
        serial = log.serial or Path(p).stem
        problem = serial_problem(serial)
        if problem is not None:  # the replayed board would be refused at the batch's start (design 3.1)
            raise StationError(f"{p}: the log's serial {problem}; give it a '# serial:' line the station accepts")
        if serial in seen:
            raise StationError(f"{p}: serial {serial} is in two logs")
        seen.add(serial)
        if log.meta.get("profile"):
            prof_meta.add(log.meta["profile"])
        ident = Identity(serial=serial, sensor=(log.meta.get("sensor") or "LOG")[:16], fw="replay",
                         ug_per_lsb=LOG_UG_PER_LSB, t_lsb_per_c=LOG_T_LSB_PER_C, t_lsb_at_25c=0.0, odr_hz=_odr_of(log))
        acc, tc = to_counts(ident, np.round(log.acc_g, 7), np.round(log.temp_c, 4), str(p))
        logs.append(log)
        duts.append(RecordedDut(
            slot=f"r{k + 1:02d}", serial=serial, link="serial", identity=ident, time_s=np.round(log.time_s, 6),
            acc_counts=acc, temp_counts=tc, lamp=log.lamp, position=log.position, outcome={}))
    if profile is None:
        if len(prof_meta) != 1:
            raise StationError("the logs name no single profile (# profile: ...): give --profile")
        profile = prof_meta.pop()
    if compare:
        from station.profiles import BUILTIN_PROFILES

        prof = BUILTIN_PROFILES.get(profile)
        positions = [s.position for s in prof.steps] if prof is not None else None
        for d, log in zip(duts, logs):
            d.outcome = log_outcome(log, positions)
    return Recording(f"{len(duts)} CSV log{'s' if len(duts) > 1 else ''}", profile, duts, {},
                     before_label="offline fit of the log")
