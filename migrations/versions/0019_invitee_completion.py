"""A participant's completion, kept once found.

- `invitees.completed_at`, `invitees.completed_why`: when their study was first found complete
  with a code, and why (`target`, `runs_over`, `paused`, `nothing_left`): from then on it stays
  complete for that reason, and their code earned, whatever their runs do later (a run
  requeued, a pause lifted; `crowdstudy.completion`). Participants of older revisions are
  recorded the next time their progress is read.

Revision ID: 0019
Revises: 0018
Create Date: 2026-11-29
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0019"
down_revision: str | None = "0018"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("invitees") as batch:
        batch.add_column(sa.Column("completed_at", sa.DateTime(timezone=True), nullable=True))
        batch.add_column(sa.Column("completed_why", sa.String(length=20), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("invitees") as batch:
        batch.drop_column("completed_why")
        batch.drop_column("completed_at")
