"""Labels may carry a flag: the labeller marked the pair as one nobody can judge (clip broken,
agent not visible, other), with an optional note. Flagged answers are skips.

Revision ID: 0012
Revises: 0011
Create Date: 2026-11-26
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0012"
down_revision: str | None = "0011"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

FLAGS = ("clip_broken", "not_visible", "other")


def upgrade() -> None:
    # Batch mode: SQLite adds a check constraint only by recreating the table.
    with op.batch_alter_table("labels") as batch:
        batch.add_column(sa.Column("flag", sa.String(16), nullable=True))
        batch.add_column(sa.Column("flag_note", sa.Text(), nullable=True))
        batch.create_check_constraint(
            "flag", "flag IN (" + ", ".join(f"'{f}'" for f in FLAGS) + ")")


def downgrade() -> None:
    with op.batch_alter_table("labels") as batch:
        batch.drop_constraint("flag", type_="check")
        batch.drop_column("flag_note")
        batch.drop_column("flag")
