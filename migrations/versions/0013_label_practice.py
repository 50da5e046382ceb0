"""Labels record whether they were a practice-round answer (`feedback.practice_pairs`): a gold
pair answered before the labeller's first real answer on the run, explained to them once
answered and left out of their gold accuracy.

Revision ID: 0013
Revises: 0012
Create Date: 2026-11-26
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0013"
down_revision: str | None = "0012"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("labels") as batch:
        batch.add_column(sa.Column("practice", sa.Boolean(), nullable=False,
                                   server_default=sa.false()))
    with op.batch_alter_table("labels") as batch:
        batch.alter_column("practice", existing_type=sa.Boolean(), server_default=None)


def downgrade() -> None:
    with op.batch_alter_table("labels") as batch:
        batch.drop_column("practice")
