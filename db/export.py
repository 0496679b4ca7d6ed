"""A stored run's sample stream back as a DutLog / design 5.1 CSV, and retention (prune).

The CSV of a run exported from the database is byte-identical to the CSV the station would have
written from the samples directly (contracts.logfile.format_log), because chunks hold the samples
as integers at exactly the CSV's precision (db/codec.py).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
from sqlalchemy import delete, exists, func, or_, select, update

from db import codec
from db.database import RUN_ACTIVE_STATES, Database
from db.models import Batch, Dut, DutRun, SampleChunk, utcnow
from contracts.logfile import DutLog, write_log
from contracts.positions import GRAVITY_DIRECTIONS
from contracts.types import NotFound, StationError
from contracts.filenames import safe_name

log = logging.getLogger(__name__)


def run_samples(db: Database, run_id: int) -> codec.Samples:
    """All stored samples of a run in order (chunks by seq)."""
    parts = []
    with db.engine.connect() as conn:
        for (data,) in conn.execute(
            select(SampleChunk.data).where(SampleChunk.run_id == run_id).order_by(SampleChunk.seq)
        ):
            parts.append(codec.decode(data))
    if not parts:
        return codec.Samples.concat([])
    return codec.Quantized.concat(parts).samples()


def run_log(db: Database, run_id: int) -> DutLog:
    """The run as a DutLog with `# key: value` metadata; KeyError for an unknown run,
    StationError when its samples were pruned."""
    with db.session() as s:
        row = s.execute(
            select(DutRun, Dut.serial, Dut.sensor, Batch.profile)
            .join(Dut, Dut.id == DutRun.dut_id)
            .join(Batch, Batch.id == DutRun.batch_id)
            .where(DutRun.id == run_id)
        ).first()
        if row is None:
            raise NotFound(f"no run {run_id}")
        run, serial, sensor, profile = row
    if run.samples_pruned_at is not None:
        raise StationError(
            f"run {run_id}: its samples were pruned on {run.samples_pruned_at:%Y-%m-%d} "
            "(segments and results are kept; the exported CSV is wherever prune --export put it)"
        )
    smp = run_samples(db, run_id)
    meta = {
        "serial": serial,
        "sensor": sensor or str((run.identity or {}).get("sensor", "")),
        "profile": profile,
        "batch": str(run.batch_id),
        "run": str(run.id),
        "slot": run.slot,
        "started": run.started_at.isoformat() if run.started_at else "",
    }
    if run.lost_samples:
        meta["lost_samples"] = str(run.lost_samples)
    out = DutLog(time_s=smp.time_s, acc_g=smp.acc_g, temp_c=smp.temp_c, meta=meta)
    if len(smp):
        out.lamp = smp.lamp.astype(np.int8)
        out.position = smp.position.astype(np.int64)
        pos = smp.position
        if (pos >= 0).all() and (pos < len(GRAVITY_DIRECTIONS)).all():
            out.ref_dir = GRAVITY_DIRECTIONS[pos.astype(np.int64)]
    return out


def export_run_csv(db: Database, run_id: int, path: str | Path) -> Path:
    """Write a run's log CSV (design 5.1) atomically; returns the path."""
    p = Path(path)
    write_log(p, run_log(db, run_id))
    return p


@dataclass
class PruneReport:
    cutoff: datetime
    runs: list[int] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)
    chunks_deleted: int = 0
    bytes_deleted: int = 0


def prune(
    db: Database,
    older_than_days: float,
    export_dir: str | Path | None = None,
    now: datetime | None = None,
    vacuum: bool = False,
) -> PruneReport:
    """Delete the sample streams of runs that ended more than `older_than_days` ago, keeping the
    runs, segments and results. With export_dir, each run's CSV is written (and replaced
    atomically) before its chunks are deleted; a run whose export fails keeps its samples."""
    if older_than_days < 0:
        raise StationError("--older-than must be >= 0 days")
    cutoff = (now or utcnow()) - timedelta(days=older_than_days)
    report = PruneReport(cutoff=cutoff)
    end_time = func.coalesce(DutRun.ended_at, Batch.ended_at)
    with db.session() as s:
        candidates = s.execute(
            select(DutRun.id, Dut.serial)
            .join(Dut, Dut.id == DutRun.dut_id)
            .join(Batch, Batch.id == DutRun.batch_id)
            .where(
                DutRun.samples_pruned_at.is_(None),
                end_time.is_not(None),
                end_time < cutoff,
                or_(DutRun.state.not_in(RUN_ACTIVE_STATES), Batch.ended_at.is_not(None)),
                exists().where(SampleChunk.run_id == DutRun.id),
            )
            .order_by(DutRun.id)
        ).all()
    out_dir = Path(export_dir) if export_dir is not None else None
    for run_id, serial in candidates:
        if out_dir is not None:
            path = out_dir / f"run{run_id:06d}_{safe_name(serial, empty='dut')}.csv"
            try:
                export_run_csv(db, run_id, path)
            except OSError as exc:
                raise StationError(f"cannot write {path}: {exc}") from None
            report.files.append(path)
        with db.session() as s:
            n, size = s.execute(
                select(func.count(SampleChunk.id), func.coalesce(func.sum(func.length(SampleChunk.data)), 0))
                .where(SampleChunk.run_id == run_id)
            ).one()
            s.execute(delete(SampleChunk).where(SampleChunk.run_id == run_id))
            s.execute(update(DutRun).where(DutRun.id == run_id).values(samples_pruned_at=utcnow()))
        report.runs.append(run_id)
        report.chunks_deleted += int(n)
        report.bytes_deleted += int(size)
    if vacuum and report.runs and db.is_sqlite:
        with db.engine.connect().execution_options(isolation_level="AUTOCOMMIT") as conn:
            conn.exec_driver_sql("VACUUM")
    return report


__all__ = ["run_samples", "run_log", "export_run_csv", "prune", "PruneReport"]
