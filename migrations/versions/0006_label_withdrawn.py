"""Labels: an answer taken back (undo) stays, withdrawn; one standing answer per labeller and
query instead of one answer.

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-23
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

STANDING = "uq_labels_query_id_labeller_id_standing"


def upgrade() -> None:
    # Batch mode: SQLite drops a unique constraint only by recreating the table.
    with op.batch_alter_table("labels") as batch:
        batch.add_column(sa.Column("withdrawn_at", sa.DateTime(timezone=True), nullable=True))
        batch.drop_constraint("uq_labels_query_id_labeller_id", type_="unique")
    standing = sa.text("withdrawn_at IS NULL")
    op.create_index(STANDING, "labels", ["query_id", "labeller_id"], unique=True,
                    sqlite_where=standing, postgresql_where=standing)


def downgrade() -> None:
    op.execute("DELETE FROM labels WHERE withdrawn_at IS NOT NULL")
    op.drop_index(STANDING, table_name="labels")
    with op.batch_alter_table("labels") as batch:
        batch.create_unique_constraint("uq_labels_query_id_labeller_id",
                                       ["query_id", "labeller_id"])
        batch.drop_column("withdrawn_at")
