"""The line's traceability: every batch carries the work order, the part number and
revision and the lot it was started for, and the label serials scanned per slot; every run the
label serial scanned for its slot (NULL when none was scanned). Existing rows get '' (not known).

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-24
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None

BATCH_TEXT = (("work_order", 64), ("part_number", 64), ("part_revision", 32), ("lot", 64))


def upgrade() -> None:
    with op.batch_alter_table("batch") as b:
        for name, size in BATCH_TEXT:
            b.add_column(sa.Column(name, sa.String(size), nullable=False, server_default=""))
        b.add_column(sa.Column("labels", sa.JSON(), nullable=True))
        b.create_index("ix_batch_work_order", ["work_order"])
        b.create_index("ix_batch_part_number", ["part_number"])
    with op.batch_alter_table("dut_run") as r:
        r.add_column(sa.Column("label_serial", sa.String(64), nullable=True))


def downgrade() -> None:
    # Plain ALTER TABLE ... DROP COLUMN (SQLite >= 3.35 has it), not batch mode: batch mode copies
    # and drops the table, and dropping `batch` with foreign keys on cascades to every run.
    op.drop_column("dut_run", "label_serial")
    op.drop_index("ix_batch_part_number", table_name="batch")
    op.drop_index("ix_batch_work_order", table_name="batch")
    op.drop_column("batch", "labels")
    for name, _ in reversed(BATCH_TEXT):
        op.drop_column("batch", name)
