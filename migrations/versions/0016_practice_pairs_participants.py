"""Practice pairs of their own, one labeller per participant, and waiting that ends paid.

- `queries.practice`: a run's practice pairs, reserved from its first gold pairs when they are
  pushed (`labelqueue.practice`): answered by every newcomer, never leased to one labeller
  alone, never served as a check pair, never charged to the budget. A run that practised on
  shared gold pairs before this revision reserves its practice pairs from the next round.
- `invitees (invite_id, participant)`: a participant id that joins an invite again gets its
  labeller back (`crowdstudy.invites.join_invite`), found by this index.
- `invitees.asked_at`, `invitees.waiting_since`: when the participant last asked for a pair,
  and since when they have asked without getting one; `invites.wait_limit_s`: after waiting so
  long with nothing to label, a participant may finish with their code.

Revision ID: 0016
Revises: 0015
Create Date: 2026-11-27
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0016"
down_revision: str | None = "0015"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("queries") as batch:
        batch.add_column(sa.Column("practice", sa.Boolean(), nullable=False,
                                   server_default=sa.false()))
    with op.batch_alter_table("queries") as batch:
        batch.alter_column("practice", existing_type=sa.Boolean(), server_default=None)
    with op.batch_alter_table("invitees") as batch:
        batch.add_column(sa.Column("asked_at", sa.DateTime(timezone=True), nullable=True))
        batch.add_column(sa.Column("waiting_since", sa.DateTime(timezone=True), nullable=True))
        batch.add_column(sa.Column("nothing_left_at", sa.DateTime(timezone=True),
                                   nullable=True))
    op.create_index("ix_invitees_invite_id_participant", "invitees",
                    ["invite_id", "participant"])
    with op.batch_alter_table("invites") as batch:
        batch.add_column(sa.Column("wait_limit_s", sa.Integer(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("invites") as batch:
        batch.drop_column("wait_limit_s")
    op.drop_index("ix_invitees_invite_id_participant", table_name="invitees")
    with op.batch_alter_table("invitees") as batch:
        batch.drop_column("nothing_left_at")
        batch.drop_column("waiting_since")
        batch.drop_column("asked_at")
    with op.batch_alter_table("queries") as batch:
        batch.drop_column("practice")
