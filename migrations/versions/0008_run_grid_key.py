"""Runs: an experiment's grid key (`<spec name>/<run folder>`), unique, so enqueueing a grid
again adds nothing.

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-23
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0008"
down_revision: str | None = "0007"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

INDEX = "ix_runs_grid_key"


def upgrade() -> None:
    op.add_column("runs", sa.Column("grid_key", sa.String(300), nullable=True))
    # A unique index, not a constraint: SQLite adds one without recreating the table. NULLs
    # (runs not from an experiment) never collide.
    op.create_index(INDEX, "runs", ["grid_key"], unique=True)


def downgrade() -> None:
    op.drop_index(INDEX, table_name="runs")
    with op.batch_alter_table("runs") as batch:
        batch.drop_column("grid_key")
