"""An entry test on an invite: pass n of the run's practice pairs, or be let go without a code.

- `invites.entry_pass`: the practice answers a participant must get right to go on; none: no
  entry test (`labelqueue.entry_test`).
- `invitees.entry_passed`, `invitees.entry_correct`: the test once decided (every practice pair
  answered), and how many practice answers were right then; it stays decided.

Revision ID: 0018
Revises: 0017
Create Date: 2026-11-28
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0018"
down_revision: str | None = "0017"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("invites") as batch:
        batch.add_column(sa.Column("entry_pass", sa.Integer(), nullable=True))
    with op.batch_alter_table("invitees") as batch:
        batch.add_column(sa.Column("entry_passed", sa.Boolean(), nullable=True))
        batch.add_column(sa.Column("entry_correct", sa.Integer(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("invitees") as batch:
        batch.drop_column("entry_correct")
        batch.drop_column("entry_passed")
    with op.batch_alter_table("invites") as batch:
        batch.drop_column("entry_pass")
