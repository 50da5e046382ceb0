"""Queries: the scripted teacher's shadow answer and whether the pair is distinguishable.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-21
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

CHOICES = ("first", "second", "equal", "cant_tell", "skip")


def upgrade() -> None:
    # Batch mode: SQLite adds a CHECK constraint only by recreating the table.
    with op.batch_alter_table("queries") as batch:
        batch.add_column(sa.Column("shadow_choice", sa.String(16), nullable=True))
        batch.add_column(sa.Column("distinguishable", sa.Boolean(), nullable=True))
        allowed = ", ".join(f"'{v}'" for v in CHOICES)
        batch.create_check_constraint(
            "shadow_choice", f"shadow_choice IN ({allowed})"
        )


def downgrade() -> None:
    with op.batch_alter_table("queries") as batch:
        batch.drop_constraint("shadow_choice", type_="check")
        batch.drop_column("distinguishable")
        batch.drop_column("shadow_choice")
