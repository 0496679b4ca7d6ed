"""program_verify: per run, the coefficients written to the board and read back (CRC, compensation
on) and the verified drift error E before/after per axis (design 4, program and verify).

Revision ID: 0004
Revises: 0002 (the lead re-chains it after 0003, the verdicts migration)
Create Date: 2026-11-23
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "program_verify",
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer(), "sqlite"), primary_key=True),
        sa.Column(
            "run_id",
            sa.BigInteger().with_variant(sa.Integer(), "sqlite"),
            sa.ForeignKey("dut_run.id", name="fk_program_verify_run_id_dut_run", ondelete="CASCADE"),
            nullable=False,
        ),
        sa.Column("programmed", sa.Boolean(), nullable=False),
        sa.Column("crc", sa.String(8), nullable=True),
        sa.Column("readback_crc", sa.String(8), nullable=True),
        sa.Column("comp_on", sa.Boolean(), nullable=False),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("error_kind", sa.String(32), nullable=False),
        sa.Column("error", sa.Text(), nullable=False),
        sa.Column("verified", sa.Boolean(), nullable=True),
        *[sa.Column(f"e_{when}_{ax}_mg", sa.Float(), nullable=True) for when in ("before", "after") for ax in "xyz"],
        sa.Column("flags", sa.JSON(), nullable=False),
        sa.Column("program", sa.JSON(), nullable=False),
        sa.Column("verification", sa.JSON(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("id", name="pk_program_verify"),
        sa.UniqueConstraint("run_id", name="uq_program_verify_run_id"),
    )


def downgrade() -> None:
    op.drop_table("program_verify")
