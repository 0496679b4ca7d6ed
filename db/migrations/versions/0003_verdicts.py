"""dut_run: the station's decision per DUT run (verdict, grade, tray, reasons, the limits set it was
judged against) and the attempt number of the serial (a retest is attempt 2, 3, ...).

Existing runs get attempt numbers in the order they were created, per serial, and no verdict.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-23
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("dut_run") as b:
        b.add_column(sa.Column("attempt", sa.Integer(), nullable=False, server_default="1"))
        b.add_column(sa.Column("verdict", sa.String(length=16), nullable=True))
        b.add_column(sa.Column("grade", sa.String(length=16), nullable=True))
        b.add_column(sa.Column("tray", sa.String(length=64), nullable=True))
        b.add_column(sa.Column("verdict_reason", sa.Text(), nullable=False, server_default=""))
        b.add_column(sa.Column("verdict_detail", sa.JSON(), nullable=True))
        b.add_column(sa.Column("limits_name", sa.String(length=64), nullable=True))
        b.add_column(sa.Column("limits_version", sa.String(length=32), nullable=True))
        b.add_column(sa.Column("judged_at", sa.DateTime(timezone=True), nullable=True))
        b.create_index("ix_dut_run_verdict", ["verdict"])
    # attempt numbers of the runs already stored: 1, 2, ... per DUT in creation order
    conn = op.get_bind()
    rows = conn.execute(sa.text("SELECT id, dut_id FROM dut_run ORDER BY id")).all()
    seen: dict[int, int] = {}
    for run_id, dut_id in rows:
        seen[dut_id] = seen.get(dut_id, 0) + 1
        if seen[dut_id] > 1:
            conn.execute(sa.text("UPDATE dut_run SET attempt = :a WHERE id = :i"), {"a": seen[dut_id], "i": run_id})


def downgrade() -> None:
    with op.batch_alter_table("dut_run") as b:
        b.drop_index("ix_dut_run_verdict")
        for col in ("judged_at", "limits_version", "limits_name", "verdict_detail", "verdict_reason", "tray", "grade",
                    "verdict", "attempt"):
            b.drop_column(col)
