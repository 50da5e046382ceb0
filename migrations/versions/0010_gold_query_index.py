"""Queries: an index on (run, gold, status, id), so a lease's look for a gold pair reads only them.

Revision ID: 0010
Revises: 0009
Create Date: 2026-11-23
"""

from collections.abc import Sequence

from alembic import op

revision: str = "0010"
down_revision: str | None = "0009"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_index(
        "ix_queries_run_id_gold_status", "queries", ["run_id", "gold", "status", "id"]
    )


def downgrade() -> None:
    op.drop_index("ix_queries_run_id_gold_status", table_name="queries")
