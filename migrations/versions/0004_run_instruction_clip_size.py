"""Runs: the operator's instruction to labellers, the clip size, and the instruction's history.

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-24
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("runs") as batch:
        batch.add_column(sa.Column("instruction", sa.Text(), nullable=True))
        batch.add_column(sa.Column("clip_size", sa.String(16), nullable=True))
    op.create_table(
        "run_instructions",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("text", sa.Text(), nullable=False),
        sa.Column("sha256", sa.String(64), nullable=False),
        sa.Column("custom", sa.Boolean(), nullable=False),
        sa.Column("set_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["run_id"], ["runs.id"], name=op.f("fk_run_instructions_run_id_runs")
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_run_instructions")),
    )
    op.create_index(
        op.f("ix_run_instructions_run_id"), "run_instructions", ["run_id"], unique=False
    )


def downgrade() -> None:
    op.drop_index(op.f("ix_run_instructions_run_id"), table_name="run_instructions")
    op.drop_table("run_instructions")
    with op.batch_alter_table("runs") as batch:
        batch.drop_column("clip_size")
        batch.drop_column("instruction")
