"""What measured each run: the station software's version, the board firmware's version
(as the board reported it in its identity; NULL when it reports none, e.g. the CAN identity frames)
and what held the part while it was turned: 'fixture' (a motorized fixture moved the plate) or
'operator' (a person turned it). A certificate states them; runs stored before this revision keep
NULL (not known), never a guessed value.

Revision ID: 0009
Revises: 0008
Create Date: 2026-11-25
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0009"
down_revision = "0008"
branch_labels = None
depends_on = None

RUN_TEXT = (("software_version", 64), ("firmware_version", 64), ("holder", 16))


def upgrade() -> None:
    with op.batch_alter_table("dut_run") as r:
        for name, size in RUN_TEXT:
            r.add_column(sa.Column(name, sa.String(size), nullable=True))


def downgrade() -> None:
    # Plain ALTER TABLE ... DROP COLUMN (SQLite >= 3.35), not batch mode: batch mode copies and
    # drops the table (see 0008)
    for name, _ in reversed(RUN_TEXT):
        op.drop_column("dut_run", name)
