"""The MES's route check of each run (design 5.4): whether the MES allowed the part to be tested
('allowed'), refused it ('refused': the part was never tested, its run is attempt 0) or gave no
usable answer ('unanswered': tested only by the site's policy proceed_and_flag), with the MES's
words or what went wrong. Runs stored before this revision keep NULL (no route check known).

Revision ID: 0011
Revises: 0010
Create Date: 2026-11-28
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0011"
down_revision = "0010"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("dut_run") as r:
        r.add_column(sa.Column("route_check", sa.String(16), nullable=True))
        r.add_column(sa.Column("route_reason", sa.Text(), nullable=False, server_default=""))


def downgrade() -> None:
    # plain DROP COLUMN (SQLite >= 3.35), not batch mode (see 0008)
    op.drop_column("dut_run", "route_reason")
    op.drop_column("dut_run", "route_check")
