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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from station.logfile import DutLog, read_log
from station.types import T_REF_C, Identity, StationError

# The identity of a board replaying a log: one count = the log's stored precision (logfile.py).
LOG_UG_PER_LSB = 0.1
LOG_T_LSB_PER_C = 1e4
COUNT_LIMIT = (1 << 31) - 1  # serial frames carry int32 counts


@dataclass
class RecordedDut:
    """One DUT's recorded stream, ready for a replay board (counts in its identity's LSBs)."""

    slot: str
    serial: str
    link: str  # "serial" or "can"
    identity: Identity
    time_s: np.ndarray  # (n,) the board's own sample clock
    acc_counts: np.ndarray  # (n, 3) int64
    temp_counts: np.ndarray  # (n,) int64
    lamp: np.ndarray | None = None  # (n,) 0/1 as the station recorded it
    position: np.ndarray | None = None  # (n,) -1 while moving/unknown
    lost_samples: int = 0
    source_run_id: int | None = None
    outcome: dict[str, Any] = field(default_factory=dict)  # the stored (or offline) result, see compare.py
    # The board time of the last sample before the station stopped the board to program it (the
    # program record's comp_from_t): the record pauses there until the replaying daemon stops it.
    restart_after_t: float | None = None
    # How the recorded board answered the calibration write when it failed (CAL_ERROR_KINDS): the
    # replay board answers the same way (drivers/sim/replay.py).
    program_error_kind: str | None = None
    # The recorded run was faulted because its link was lost (a board unplugged, a cable pulled):
    # the replay board is unplugged where the record ends, so the replaying daemon faults it at the
    # same point of the stream. (A board that only went silent is faulted by the wall-clock stall
    # timeout, whose point in sample time depends on the speed and the load: not reproducible.)
    unplugged_at_end: bool = False

    def __len__(self) -> int:
        return int(self.time_s.shape[0])

    def restart_index(self) -> int | None:
        """Index of the first sample after the recorded program stop (None: no stop recorded, or
        the record ends there)."""
        if self.restart_after_t is None:
            return None
        k = int(np.searchsorted(self.time_s, float(self.restart_after_t), side="right"))
        return k if 0 < k < len(self) else None

    def seq_index(self) -> np.ndarray:
        """Frame sequence number of every sample: gaps in the clock longer than 1.5 sample periods
        are samples the link lost, so the replay board skips as many sequence numbers (the
        station then counts them lost, as it did when the data were recorded). The gap where the
        station stopped the board to program it is no loss: the board measured nothing then."""
        n = len(self)
        if n == 0:
            return np.zeros(0, dtype=np.int64)
        dt = np.diff(self.time_s) * self.identity.odr_hz
        gaps = np.where(dt > 1.5, np.rint(dt) - 1, 0).astype(np.int64)
        k = self.restart_index()
        if k is not None:
            gaps[k - 1] = 0
        return np.concatenate([[0], np.cumsum(gaps + 1)])


def answer_index(position: np.ndarray | None, start: int, wanted: int) -> int | None:
    """Where a recorded operator's answer to "turn the plate to `wanted`" took effect: the first
    recorded sample at or after `start` that the station stored at that position (while a prompt
    waits the station stores -1, unknown). None: the recording never reached it (the recorded
    batch ended at that prompt, or the record is over)."""
    if position is None:
        return None
    hit = np.flatnonzero(np.asarray(position[start:]) == int(wanted))
    return int(start + hit[0]) if len(hit) else None


@dataclass
class Recording:
    """A batch to replay: its DUTs, the profile it ran and where it came from."""

    source: str  # e.g. "batch 12 of line-A (sqlite:///var/station.db)" or "3 CSV logs"
    profile: str
    duts: list[RecordedDut]
    config_snapshot: dict[str, Any] = field(default_factory=dict)
    skipped: list[str] = field(default_factory=list)  # DUTs that cannot be replayed, with the reason
    before_label: str = "recorded"
    batch_state: str = "finished"  # how the recorded batch ended (logs: expected to finish)
    batch_error: str = ""  # why, if it did not finish ("aborted by Ana at ...", "safety trip: ...")
    source_note: str = ""  # how the source was read, e.g. through a migrated copy of an older schema

    def only(self, serials: list[str] | None) -> "Recording":
        """Keep the DUTs whose serial (or slot) is listed; unknown names are an error."""
        if not serials:
            return self
        known = {d.serial for d in self.duts} | {d.slot for d in self.duts}
        unknown = [s for s in serials if s not in known]
        if unknown:
            raise StationError(f"--only: {', '.join(unknown)} not in the recording "
                               f"(it has {', '.join(d.serial for d in self.duts)})")
        keep = [d for d in self.duts if d.serial in serials or d.slot in serials]
        return dataclasses.replace(self, duts=keep)


# ---- counts ---------------------------------------------------------------------------------
def to_counts(identity: Identity, acc_g: np.ndarray, temp_c: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """g and C back to the board's counts. The stored values are counts x LSB at 1e-7 g / 1e-4 C,
    so rounding recovers the counts exactly; a value off its LSB grid is refused (it was not
    recorded by a board with this identity, and replaying it would change the data)."""
    lsb_g = identity.ug_per_lsb / 1e6
    acc = np.rint(np.asarray(acc_g, dtype=np.float64) / lsb_g)
    tc = np.rint((np.asarray(temp_c, dtype=np.float64) - T_REF_C) * identity.t_lsb_per_c + identity.t_lsb_at_25c)
    if len(acc):
        err_g = float(np.max(np.abs(acc * lsb_g - acc_g)))
        err_c = float(np.max(np.abs(identity.temp_c(tc) - temp_c)))
        if err_g > 0.51e-7 + 1e-12 or err_c > 0.51e-4 + 1e-12:
            raise StationError(f"{what}: the samples are not on the board's LSB grid "
                               f"({err_g * 1e6:.3g} ug, {err_c * 1e3:.3g} mC off): cannot replay them as counts")
        if np.max(np.abs(acc)) > COUNT_LIMIT or np.max(np.abs(tc)) > COUNT_LIMIT:
            raise StationError(f"{what}: counts beyond int32")
    return acc.astype(np.int64), tc.astype(np.int64)


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
            raise StationError(f"database {_plain_url(db_url)} holds no station data (no schema): nothing to replay")
        src._refuse_unknown(rev)
        head = src.head_revision()
        if rev == head:
            return src, "", None
        if not src.is_sqlite:
            raise StationError(f"database {_plain_url(db_url)} has schema {rev}, this software reads {head}: "
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
                unplugged_at_end=run["state"] == "faulted" and "link lost" in (run.get("fault_reason") or "")))
        if not duts:
            raise StationError(f"batch {batch_id}: nothing to replay ({'; '.join(skipped) or 'no runs'})")
        where = batch.get("station") or "?"
        kind = f"replay of {batch['replay_of']}" if batch.get("replay_of") else f"batch {batch_id} of {where}"
        return Recording(f"{kind} ({_plain_url(db_url)})", batch["profile"], duts, snapshot, skipped,
                         batch_state=batch["state"], batch_error=batch.get("reason") or "", source_note=source_note)
    finally:
        db.dispose()
        if cleanup is not None:
            cleanup()


def run_outcome(db: Any, run: dict[str, Any]) -> dict[str, Any]:
    """What a stored run came to (compare.py's input): its state, verdict and grade, and its
    results as the repository reports them. The recording and the replay are read the same way."""
    from db import repository as R

    with db.session() as s:
        results = R._run_results(s, run["id"])
    return {"state": run["state"], "verdict": run.get("verdict"), "grade": run.get("grade"), **results}


def _plain_url(url: str) -> str:
    """A database URL without its password (it is stored with the replay batch)."""
    from sqlalchemy.engine import make_url

    try:
        return make_url(url).render_as_string(hide_password=True)
    except Exception:  # noqa: BLE001 - a malformed URL failed earlier, when it was opened
        return url


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


def log_outcome(log: DutLog) -> dict[str, Any]:
    """The outcome to compare a log's replay with: the offline science on the file itself."""
    from station.science.thermal_calibration import calibrate, fit_samples

    ends = [s["t_end_s"] for s in calibrate(log)["segments"]]
    res = calibrate(fit_samples(log.block(), ends))  # the station's rule (fit_samples)
    by_method = {m: {ax: {k: v[k] for k in ("tdb_mg_per_c", "tdsf_ppm_per_c")} for ax, v in res[m]["axes"].items()}
                 for m in ("offline", "streaming")}
    return {"partial": True, "thermal_by_method": by_method}


def from_logs(paths: list[str | Path], profile: str | None = None, compare: bool = True) -> Recording:
    """Design-5.1 CSV logs, one per DUT (serial from `# serial:` or the file name)."""
    if not paths:
        raise StationError("no log files given")
    duts, prof_meta = [], set()
    seen: set[str] = set()
    for k, p in enumerate(paths):
        log = read_log(p)
        if not len(log):
            raise StationError(f"{p}: no samples")
        if np.any(np.diff(log.time_s) <= 0):
            raise StationError(f"{p}: sample times must increase")
        serial = log.serial or Path(p).stem
        if serial in seen:
            raise StationError(f"{p}: serial {serial} is in two logs")
        seen.add(serial)
        if log.meta.get("profile"):
            prof_meta.add(log.meta["profile"])
        ident = Identity(serial=serial[:32], sensor=(log.meta.get("sensor") or "LOG")[:16], fw="replay",
                         ug_per_lsb=LOG_UG_PER_LSB, t_lsb_per_c=LOG_T_LSB_PER_C, t_lsb_at_25c=0.0, odr_hz=_odr_of(log))
        acc, tc = to_counts(ident, np.round(log.acc_g, 7), np.round(log.temp_c, 4), str(p))
        duts.append(RecordedDut(
            slot=f"r{k + 1:02d}", serial=serial, link="serial", identity=ident, time_s=np.round(log.time_s, 6),
            acc_counts=acc, temp_counts=tc, lamp=log.lamp, position=log.position,
            outcome=log_outcome(log) if compare else {}))
    if profile is None:
        if len(prof_meta) != 1:
            raise StationError("the logs name no single profile (# profile: ...): give --profile")
        profile = prof_meta.pop()
    return Recording(f"{len(duts)} CSV log{'s' if len(duts) > 1 else ''}", profile, duts, {},
                     before_label="offline fit of the log")
