"""Many stations, one database: a station name on every batch, run and result row; the result_seq
counter (one row, row-locked by the committing transaction, so the MES cursor's order is the commit
order); the audit trail of REST actions.

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-23
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None

STATION_TABLES = ("batch", "dut_run", "thermal_result", "sfem_result", "program_verify")
BigId = sa.BigInteger().with_variant(sa.Integer(), "sqlite")


def upgrade() -> None:
    for table in STATION_TABLES:
        op.add_column(table, sa.Column("station", sa.String(64), nullable=False, server_default=""))
    op.create_index("ix_batch_station", "batch", ["station"])
    op.create_index("ix_dut_run_station", "dut_run", ["station"])
    op.create_table(
        "result_counter",
        sa.Column("id", sa.Integer(), primary_key=True, autoincrement=False),
        sa.Column("value", sa.BigInteger(), nullable=False),
        sa.PrimaryKeyConstraint("id", name="pk_result_counter"),
    )
    # continue after the results already stored (max+1 was the old rule)
    op.execute("INSERT INTO result_counter (id, value) SELECT 1, COALESCE(MAX(result_seq), 0) FROM dut_run")
    op.create_table(
        "audit",
        sa.Column("id", BigId, primary_key=True),
        sa.Column("at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("station", sa.String(64), nullable=False),
        sa.Column("actor", sa.String(128), nullable=False),
        sa.Column("action", sa.String(64), nullable=False),
        sa.Column("target", sa.String(128), nullable=False),
        sa.Column("detail", sa.JSON(), nullable=False),
        sa.PrimaryKeyConstraint("id", name="pk_audit"),
    )
    op.create_index("ix_audit_at", "audit", ["at"])


def downgrade() -> None:
    op.drop_index("ix_audit_at", table_name="audit")
    op.drop_table("audit")
    op.drop_table("result_counter")
    op.drop_index("ix_dut_run_station", table_name="dut_run")
    op.drop_index("ix_batch_station", table_name="batch")
    for table in STATION_TABLES:
        with op.batch_alter_table(table) as b:
            b.drop_column("station")
