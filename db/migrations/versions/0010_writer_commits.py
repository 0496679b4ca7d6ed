"""Every writer transaction leaves its token: a commit whose answer was lost (the
connection cut while COMMIT was on its way: a PostgreSQL restart, a network blink) may or may not
have happened. The writer asks for its token before it stores the same events again, so a record
is stored once, not twice (a second chunk of the same samples, a second MES record of one verdict).
Tokens older than a day are removed by the writer.

Revision ID: 0010
Revises: 0009
Create Date: 2026-11-27
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0010"
down_revision = "0009"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "writer_commit",
        sa.Column("token", sa.String(64), primary_key=True),
        sa.Column("station", sa.String(64), nullable=False, server_default=""),
        sa.Column("committed_at", sa.DateTime(timezone=True), nullable=False),
    )
    op.create_index("ix_writer_commit_committed_at", "writer_commit", ["committed_at"])


def downgrade() -> None:
    op.drop_index("ix_writer_commit_committed_at", table_name="writer_commit")
    op.drop_table("writer_commit")
