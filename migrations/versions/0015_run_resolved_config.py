"""A run keeps the configuration it trains with, resolved when it is created: `runs.resolved_config`
(`runvocab.config.to_dict`'s JSON). Null for a run stored before this revision, whose worker
resolves its overrides against the presets as before (`labelqueue.run_config`).

Revision ID: 0015
Revises: 0014
Create Date: 2026-11-26
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0015"
down_revision: str | None = "0014"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("runs") as batch:
        batch.add_column(sa.Column("resolved_config", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("runs") as batch:
        batch.drop_column("resolved_config")
