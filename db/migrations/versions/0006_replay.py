"""Replays: a batch that re-ran recorded data through the station names its source
(`replay_of`, e.g. "batch 12 of line-A" or "3 CSV logs") and keeps the comparison with the
recorded outcome (`replay_diff`). Runs of a replay batch never get a result_seq (never reach the
MES) and never count as attempts, yields or SPC points.

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-23
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("batch", sa.Column("replay_of", sa.String(256), nullable=True))
    op.add_column("batch", sa.Column("replay_diff", sa.JSON(), nullable=True))
    op.create_index("ix_batch_replay_of", "batch", ["replay_of"])


def downgrade() -> None:
    op.drop_index("ix_batch_replay_of", table_name="batch")
    op.drop_column("batch", "replay_diff")
    op.drop_column("batch", "replay_of")
