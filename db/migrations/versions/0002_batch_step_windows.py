"""batch.step_windows: each completed step's sample-time window per slot, so a resumed batch can
still cut the static windows of the steps it completed before a crash (SFEM profiles).

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-22
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("batch") as b:
        b.add_column(sa.Column("step_windows", sa.JSON(), nullable=False, server_default="{}"))


def downgrade() -> None:
    with op.batch_alter_table("batch") as b:
        b.drop_column("step_windows")
