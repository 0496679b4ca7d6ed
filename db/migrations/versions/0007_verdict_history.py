"""The MES record is the final verdict (design 8): every verdict record of a run is kept in
`verdict_history`, the first one (supersedes_seq NULL) and each later one that supersedes it (a
batch interrupted -> error, then resumed -> pass; a limits change). The results feed pages over this
table, so each record reaches the MES once, with its revision and the record it supersedes.

Existing records (every run that has a result_seq) become revision 1 of their run, so an upgraded
database's feed serves exactly what it served before.

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-24
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None

BigId = sa.BigInteger().with_variant(sa.Integer(), "sqlite")


def upgrade() -> None:
    op.create_table(
        "verdict_history",
        sa.Column("id", BigId, primary_key=True),
        sa.Column("run_id", BigId, sa.ForeignKey("dut_run.id", name="fk_verdict_history_run_id_dut_run",
                                                 ondelete="CASCADE"), nullable=False),
        sa.Column("result_seq", sa.BigInteger(), nullable=True),
        sa.Column("station", sa.String(64), nullable=False, server_default=""),
        sa.Column("verdict", sa.String(16), nullable=True),
        sa.Column("grade", sa.String(16), nullable=True),
        sa.Column("tray", sa.String(64), nullable=True),
        sa.Column("reason", sa.Text(), nullable=False, server_default=""),
        sa.Column("detail", sa.JSON(), nullable=True),
        sa.Column("limits_name", sa.String(64), nullable=True),
        sa.Column("limits_version", sa.String(32), nullable=True),
        sa.Column("judged_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("supersedes_seq", sa.BigInteger(), nullable=True),
        sa.PrimaryKeyConstraint("id", name="pk_verdict_history"),
        sa.UniqueConstraint("result_seq", name="uq_verdict_history_result_seq"),
    )
    op.create_index("ix_verdict_history_run_id", "verdict_history", ["run_id"])
    op.create_index("ix_verdict_history_judged_at", "verdict_history", ["judged_at"])
    op.execute(
        "INSERT INTO verdict_history (run_id, result_seq, station, verdict, grade, tray, reason, detail, "
        "limits_name, limits_version, judged_at, supersedes_seq) "
        "SELECT id, result_seq, station, verdict, grade, tray, COALESCE(verdict_reason, ''), verdict_detail, "
        "limits_name, limits_version, COALESCE(judged_at, ended_at, started_at), NULL "
        "FROM dut_run WHERE result_seq IS NOT NULL"
    )


def downgrade() -> None:
    op.drop_index("ix_verdict_history_judged_at", table_name="verdict_history")
    op.drop_index("ix_verdict_history_run_id", table_name="verdict_history")
    op.drop_table("verdict_history")
