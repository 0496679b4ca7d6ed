"""SQLAlchemy 2.0 typed models: per-serial history of DUTs, batches, runs, segments, results.

The schema itself is owned by the Alembic revisions in db/migrations/versions/ (written by hand);
these models must match them, which tests/test_db_migrations.py checks with Alembic's comparator.
All times are timezone-aware UTC. JSON columns hold what the daemon reported, verbatim, so nothing
is lost even where the typed columns summarize it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    String,
    Text,
    TypeDecorator,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship

# The revision of the newest schema this code knows (db/migrations/versions/).
SCHEMA_REVISION = "0011"
# dut_run.attempt of a run that never tested its part (the label scanned for the slot is not the
# board's serial: stopped at connect, before any data). Stored and judged error, so the MES sees which
# board was there, but no attempt of the board's serial: attempt numbers, attempts and yields skip it.
NO_ATTEMPT = 0
# dut_run.holder: what held the part while its positions were taken. 'fixture': the station's
# motorized fixture moved the plate; 'operator': a person turned the plate (no fixture configured).
HOLDERS = ("fixture", "operator")


@dataclass(frozen=True)
class MeasuredBy:
    """What measured a run, stored with it when it is made (Database.create_run): the software's
    version, the board firmware's (None: the board reports none) and the holder (HOLDERS)."""

    software_version: str | None = None
    firmware_version: str | None = None
    holder: str | None = None

    def __post_init__(self) -> None:
        if self.holder is not None and self.holder not in HOLDERS:
            raise ValueError(f"holder {self.holder!r} is none of {', '.join(HOLDERS)}")

    def columns(self) -> dict[str, str | None]:
        """dut_run's columns ('' stored as NULL: not reported is not known)."""
        return {k: (v or None) for k, v in asdict(self).items()}

NAMING_CONVENTION = {
    "ix": "ix_%(table_name)s_%(column_0_N_name)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


def utcnow() -> datetime:
    return datetime.now(timezone.utc)


class UtcDateTime(TypeDecorator):
    """Timezone-aware UTC everywhere: SQLite drops the offset, so put UTC back on the way out."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            value = value.replace(tzinfo=timezone.utc)
        value = value.astimezone(timezone.utc)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            return value.replace(tzinfo=timezone.utc)
        return value.astimezone(timezone.utc)


# Integer primary keys that are 64-bit on PostgreSQL and SQLite's rowid alias on SQLite.
BigId = BigInteger().with_variant(Integer(), "sqlite")


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING_CONVENTION)
    type_annotation_map = {datetime: UtcDateTime(), dict[str, Any]: JSON(), Any: JSON()}


class Dut(Base):
    """One physical board, by serial number: the key of its whole history."""

    __tablename__ = "dut"

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    serial: Mapped[str] = mapped_column(String(64), unique=True)
    sensor: Mapped[str] = mapped_column(String(32), default="")
    first_seen: Mapped[datetime] = mapped_column(default=utcnow)
    last_seen: Mapped[datetime] = mapped_column(default=utcnow)

    runs: Mapped[list["DutRun"]] = relationship(back_populates="dut")


class Batch(Base):
    """One sequencer program run over the plate; enough to resume it at its last completed step."""

    __tablename__ = "batch"

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    profile: Mapped[str] = mapped_column(String(64))
    # the station that ran it (config `name`): many stations may share one database
    station: Mapped[str] = mapped_column(String(64), default="", server_default="", index=True)
    operator: Mapped[str] = mapped_column(String(128), default="")
    state: Mapped[str] = mapped_column(String(32), default="created", index=True)
    reason: Mapped[str] = mapped_column(Text, default="")
    step_index: Mapped[int | None] = mapped_column(Integer)
    last_completed_step: Mapped[int | None] = mapped_column(Integer)
    config_snapshot: Mapped[dict[str, Any]] = mapped_column(default=dict)
    # {"<step index>": {"<slot>": [t_from_s, t_to_s]}} of every completed step (resume, SFEM windows)
    step_windows: Mapped[dict[str, Any]] = mapped_column(default=dict, server_default="{}")
    schema_version: Mapped[str] = mapped_column(String(32), default=SCHEMA_REVISION)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    ended_at: Mapped[datetime | None] = mapped_column()
    # a replay of recorded data (station/replay): its source; None for a batch of real parts.
    # Its runs get no result_seq (never sent to the MES) and are no attempts, yields or SPC points.
    replay_of: Mapped[str | None] = mapped_column(String(256), index=True)
    replay_diff: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    # traceability: what the batch was started for; '' when not given
    work_order: Mapped[str] = mapped_column(String(64), default="", server_default="", index=True)
    part_number: Mapped[str] = mapped_column(String(64), default="", server_default="", index=True)
    part_revision: Mapped[str] = mapped_column(String(32), default="", server_default="")
    lot: Mapped[str] = mapped_column(String(64), default="", server_default="")
    labels: Mapped[dict[str, Any] | None] = mapped_column(JSON)  # {slot: label serial scanned at start}

    runs: Mapped[list["DutRun"]] = relationship(back_populates="batch", order_by="DutRun.id")


class DutRun(Base):
    """One DUT in one slot of one batch. result_seq is the MES cursor of the run's CURRENT verdict
    record: it is taken when the run's final verdict (DutVerdict) is stored and again when a later
    verdict supersedes it (every record is kept in verdict_history)."""

    __tablename__ = "dut_run"

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    batch_id: Mapped[int] = mapped_column(ForeignKey("batch.id", ondelete="CASCADE"), index=True)
    slot: Mapped[str] = mapped_column(String(64))
    station: Mapped[str] = mapped_column(String(64), default="", server_default="", index=True)
    dut_id: Mapped[int] = mapped_column(ForeignKey("dut.id"), index=True)
    state: Mapped[str] = mapped_column(String(32), default="connecting")
    fault_reason: Mapped[str] = mapped_column(Text, default="")
    identity: Mapped[dict[str, Any]] = mapped_column(default=dict)
    n_samples: Mapped[int] = mapped_column(BigInteger, default=0)
    lost_samples: Mapped[int] = mapped_column(BigInteger, default=0)
    samples_pruned_at: Mapped[datetime | None] = mapped_column()
    result_seq: Mapped[int | None] = mapped_column(BigInteger, unique=True)
    started_at: Mapped[datetime] = mapped_column(default=utcnow)
    ended_at: Mapped[datetime | None] = mapped_column(index=True)
    # the serial's attempt number (retests: 2, 3, ...; NO_ATTEMPT = 0: a label mismatch, the part was never
    # tested) and the station's decision (station/decisions/verdicts.py)
    attempt: Mapped[int] = mapped_column(Integer, default=1, server_default="1")
    verdict: Mapped[str | None] = mapped_column(String(16), index=True)  # pass, marginal, fail, error
    grade: Mapped[str | None] = mapped_column(String(16))
    tray: Mapped[str | None] = mapped_column(String(64))
    verdict_reason: Mapped[str] = mapped_column(Text, default="", server_default="")
    verdict_detail: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    limits_name: Mapped[str | None] = mapped_column(String(64))
    limits_version: Mapped[str | None] = mapped_column(String(32))
    judged_at: Mapped[datetime | None] = mapped_column()
    label_serial: Mapped[str | None] = mapped_column(String(64))  # scanned from the part's label, if any
    # what measured the run (migration 0009): the station software's version, the board firmware's
    # (its identity reply; None when it reports none) and what held the part: HOLDERS (None: not
    # stored, a run from before 0009)
    software_version: Mapped[str | None] = mapped_column(String(64))
    firmware_version: Mapped[str | None] = mapped_column(String(64))
    holder: Mapped[str | None] = mapped_column(String(16))
    # the MES's route check before the part was tested (migration 0011, design 5.4): allowed, refused
    # or unanswered (None: no route check configured, or a run from before 0011), with the MES's
    # words or what went wrong; a refused part was never tested (attempt 0), an unanswered one was
    # tested only by the site's policy 'proceed_and_flag'
    route_check: Mapped[str | None] = mapped_column(String(16))
    route_reason: Mapped[str] = mapped_column(Text, default="", server_default="")

    batch: Mapped[Batch] = relationship(back_populates="runs")
    dut: Mapped[Dut] = relationship(back_populates="runs")


class SegmentRow(Base):
    """One averaged stable segment (contracts.types.Segment) plus the step it was logged in."""

    __tablename__ = "segment"

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("dut_run.id", ondelete="CASCADE"), index=True)
    step_index: Mapped[int] = mapped_column(Integer)
    position: Mapped[int | None] = mapped_column(Integer)
    seg_index: Mapped[int] = mapped_column(Integer)
    orientation: Mapped[int] = mapped_column(Integer)
    n_samples: Mapped[int] = mapped_column(Integer)
    acc_mean_x_g: Mapped[float] = mapped_column(Float)
    acc_mean_y_g: Mapped[float] = mapped_column(Float)
    acc_mean_z_g: Mapped[float] = mapped_column(Float)
    acc_std_x_g: Mapped[float] = mapped_column(Float)
    acc_std_y_g: Mapped[float] = mapped_column(Float)
    acc_std_z_g: Mapped[float] = mapped_column(Float)
    temp_mean_c: Mapped[float] = mapped_column(Float)
    temp_std_c: Mapped[float] = mapped_column(Float)
    t_start_s: Mapped[float] = mapped_column(Float)
    t_end_s: Mapped[float] = mapped_column(Float)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class ThermalResultRow(Base):
    """TDB/TDSF per axis of one method (streaming | offline) for one run (martinez2022)."""

    __tablename__ = "thermal_result"

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("dut_run.id", ondelete="CASCADE"), index=True)
    method: Mapped[str] = mapped_column(String(16))
    station: Mapped[str] = mapped_column(String(64), default="", server_default="")
    tdb_x_mg_per_c: Mapped[float | None] = mapped_column(Float)
    tdb_y_mg_per_c: Mapped[float | None] = mapped_column(Float)
    tdb_z_mg_per_c: Mapped[float | None] = mapped_column(Float)
    tdsf_x_ppm_per_c: Mapped[float | None] = mapped_column(Float)
    tdsf_y_ppm_per_c: Mapped[float | None] = mapped_column(Float)
    tdsf_z_ppm_per_c: Mapped[float | None] = mapped_column(Float)
    tdb_sigma_x_mg_per_c: Mapped[float | None] = mapped_column(Float)
    tdb_sigma_y_mg_per_c: Mapped[float | None] = mapped_column(Float)
    tdb_sigma_z_mg_per_c: Mapped[float | None] = mapped_column(Float)
    tdsf_sigma_x_ppm_per_c: Mapped[float | None] = mapped_column(Float)
    tdsf_sigma_y_ppm_per_c: Mapped[float | None] = mapped_column(Float)
    tdsf_sigma_z_ppm_per_c: Mapped[float | None] = mapped_column(Float)
    tdsf_clamped_x: Mapped[bool] = mapped_column(Boolean, default=False)
    tdsf_clamped_y: Mapped[bool] = mapped_column(Boolean, default=False)
    tdsf_clamped_z: Mapped[bool] = mapped_column(Boolean, default=False)
    n_segments: Mapped[int] = mapped_column(Integer, default=0)
    detail: Mapped[dict[str, Any]] = mapped_column(default=dict)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class SfemResultRow(Base):
    """SFEM fit of one temperature step (sensors2023); the cubic polynomials over temperature sit
    on the row of the run's polynomial fit (temperature_step None)."""

    __tablename__ = "sfem_result"

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("dut_run.id", ondelete="CASCADE"), index=True)
    station: Mapped[str] = mapped_column(String(64), default="", server_default="")
    temperature_step: Mapped[int | None] = mapped_column(Integer)
    temp_c: Mapped[float | None] = mapped_column(Float)
    rmse_before_mg: Mapped[float | None] = mapped_column(Float)
    rmse_after_mg: Mapped[float | None] = mapped_column(Float)
    parameters: Mapped[dict[str, Any]] = mapped_column(default=dict)
    polynomial_coefficients: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class ProgramVerifyRow(Base):
    """Program and verify of one run (design 4): what was written and read back (CRC, compensation
    on), and the verified drift error E before (uncompensated, first pass) and after (compensated
    output during the verification heat), per axis in mg (martinez2022 eq. 10, 70 C range)."""

    __tablename__ = "program_verify"

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("dut_run.id", ondelete="CASCADE"), unique=True)
    station: Mapped[str] = mapped_column(String(64), default="", server_default="")
    programmed: Mapped[bool] = mapped_column(Boolean, default=False)
    crc: Mapped[str | None] = mapped_column(String(8))
    readback_crc: Mapped[str | None] = mapped_column(String(8))
    comp_on: Mapped[bool] = mapped_column(Boolean, default=False)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    error_kind: Mapped[str] = mapped_column(String(32), default="")
    error: Mapped[str] = mapped_column(Text, default="")
    verified: Mapped[bool | None] = mapped_column(Boolean)  # None: not verified (yet)
    e_before_x_mg: Mapped[float | None] = mapped_column(Float)
    e_before_y_mg: Mapped[float | None] = mapped_column(Float)
    e_before_z_mg: Mapped[float | None] = mapped_column(Float)
    e_after_x_mg: Mapped[float | None] = mapped_column(Float)
    e_after_y_mg: Mapped[float | None] = mapped_column(Float)
    e_after_z_mg: Mapped[float | None] = mapped_column(Float)
    flags: Mapped[list[Any]] = mapped_column(JSON, default=list)
    program: Mapped[dict[str, Any]] = mapped_column(default=dict)
    verification: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(default=utcnow)


class ResultCounter(Base):
    """The MES cursor's counter (one row, id 1): a result takes `value + 1` with an UPDATE in the
    transaction that stores it. The UPDATE row-locks the counter until that transaction commits, so
    a second writer (another station on the same database) waits and takes the next number only
    after the first commit: result_seq order is commit order, and `results since N` never skips a
    result that commits late. (A PostgreSQL sequence would give unique numbers but hand them out at
    nextval, not at commit: a reader could see 11 before 10 commits and step over 10 for ever.)"""

    __tablename__ = "result_counter"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    value: Mapped[int] = mapped_column(BigInteger)


class VerdictHistoryRow(Base):
    """Every verdict record of a run, in the order the MES got them: the first final verdict
    (supersedes_seq None) and each later one that supersedes it (a resumed batch, a re-judge).
    result_seq is the record's MES cursor (None for a replay, which never reaches the MES);
    dut_run carries the latest record's columns."""

    __tablename__ = "verdict_history"

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("dut_run.id", ondelete="CASCADE"), index=True)
    result_seq: Mapped[int | None] = mapped_column(BigInteger, unique=True)
    station: Mapped[str] = mapped_column(String(64), default="", server_default="")
    verdict: Mapped[str | None] = mapped_column(String(16))
    grade: Mapped[str | None] = mapped_column(String(16))
    tray: Mapped[str | None] = mapped_column(String(64))
    reason: Mapped[str] = mapped_column(Text, default="", server_default="")
    detail: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    limits_name: Mapped[str | None] = mapped_column(String(64))
    limits_version: Mapped[str | None] = mapped_column(String(32))
    judged_at: Mapped[datetime] = mapped_column(default=utcnow, index=True)
    supersedes_seq: Mapped[int | None] = mapped_column(BigInteger)


class AuditRow(Base):
    """Who did what through the REST API (batch start, abort, prompt answers, resume, limit-set
    changes): actor is the token's name, detail what the request carried."""

    __tablename__ = "audit"

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    at: Mapped[datetime] = mapped_column(default=utcnow, index=True)
    station: Mapped[str] = mapped_column(String(64), default="")
    actor: Mapped[str] = mapped_column(String(128), default="")
    action: Mapped[str] = mapped_column(String(64))
    target: Mapped[str] = mapped_column(String(128), default="")
    detail: Mapped[dict[str, Any]] = mapped_column(default=dict)


class WriterCommit(Base):
    """One row per writer transaction (migration 0010): a commit whose answer was lost is found by
    its token before its events are stored again (db/writer_outage.py)."""

    __tablename__ = "writer_commit"

    token: Mapped[str] = mapped_column(String(64), primary_key=True)
    station: Mapped[str] = mapped_column(String(64), default="", server_default="")
    committed_at: Mapped[datetime] = mapped_column(default=utcnow, index=True)


class SampleChunk(Base):
    """A compressed block of a run's sample stream (db/codec.py); seq orders the chunks."""

    __tablename__ = "sample_chunk"
    __table_args__ = (Index("uq_sample_chunk_run_id_seq", "run_id", "seq", unique=True),)

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("dut_run.id", ondelete="CASCADE"))
    seq: Mapped[int] = mapped_column(Integer)
    t_first_s: Mapped[float] = mapped_column(Float)
    t_last_s: Mapped[float] = mapped_column(Float)
    n: Mapped[int] = mapped_column(Integer)
    lost_samples: Mapped[int] = mapped_column(Integer, default=0)
    sealed: Mapped[bool] = mapped_column(Boolean, default=False)
    data: Mapped[bytes] = mapped_column(LargeBinary)


class Outbox(Base):
    """MES webhook outbox: written in the same transaction as the result it announces."""

    __tablename__ = "outbox"
    __table_args__ = (Index("ix_outbox_pending", "delivered_at", "next_attempt_at"),)

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    idempotency_key: Mapped[str] = mapped_column(String(128), unique=True)
    topic: Mapped[str] = mapped_column(String(64), default="result")
    payload: Mapped[dict[str, Any]] = mapped_column(default=dict)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    next_attempt_at: Mapped[datetime] = mapped_column(default=utcnow)
    delivered_at: Mapped[datetime | None] = mapped_column()
    last_error: Mapped[str] = mapped_column(Text, default="")
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


__all__ = [
    "Base",
    "Dut",
    "Batch",
    "DutRun",
    "SegmentRow",
    "ThermalResultRow",
    "SfemResultRow",
    "ProgramVerifyRow",
    "SampleChunk",
    "WriterCommit",
    "Outbox",
    "ResultCounter",
    "AuditRow",
    "VerdictHistoryRow",
    "SCHEMA_REVISION",
    "utcnow",
]
