"""External runs: runs no worker trains, whose pairs a client pushes over REST.

- `queries.*_return` nullable: an external client's pair may come without true returns (they
  are hidden metadata it may give for the calibration report); the trainer always gives them.
- `run_tokens`: bearer tokens scoped to one run (`externalruns`), which push its pairs
  and read its answers and nothing else; only their sha256 is stored.
- `external_pairs`: a pushed pair's idempotency key (unique per run), the digest of what was
  pushed under it, the client's hidden metadata and, for a gold pair, its known answer.
- `withdrawals`: one row per answer taken back, in order, so the answers feed
  (`GET /api/runs/{id}/answers`) can resume after a withdrawal as after an answer.

Revision ID: 0017
Revises: 0016
Create Date: 2026-11-28
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0017"
down_revision: str | None = "0016"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

RETURNS = ("first_segment_return", "second_segment_return", "first_trajectory_return",
           "second_trajectory_return")
ANSWERS = ("first", "second", "equal", "cant_tell", "skip")


def upgrade() -> None:
    with op.batch_alter_table("queries") as batch:
        for name in RETURNS:
            batch.alter_column(name, existing_type=sa.Float(), nullable=True)
    op.create_table(
        "run_tokens",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("token_hash", sa.String(64), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("revoked_at", sa.DateTime(timezone=True), nullable=True),
        sa.ForeignKeyConstraint(["run_id"], ["runs.id"], name="fk_run_tokens_run_id_runs"),
        sa.PrimaryKeyConstraint("id", name="pk_run_tokens"),
    )
    op.create_table(
        "external_pairs",
        sa.Column("query_id", sa.Integer(), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("key", sa.String(200), nullable=False),
        sa.Column("digest", sa.String(64), nullable=False),
        sa.Column("meta", sa.JSON(), nullable=True),
        sa.Column("gold_answer", sa.String(16), nullable=True),
        sa.ForeignKeyConstraint(["query_id"], ["queries.id"],
                                name="fk_external_pairs_query_id_queries"),
        sa.ForeignKeyConstraint(["run_id"], ["runs.id"], name="fk_external_pairs_run_id_runs"),
        sa.PrimaryKeyConstraint("query_id", name="pk_external_pairs"),
        sa.UniqueConstraint("run_id", "key", name="uq_external_pairs_run_id_key"),
        sa.CheckConstraint("gold_answer IN (" + ", ".join(f"'{a}'" for a in ANSWERS) + ")",
                           name=op.f("ck_external_pairs_gold_answer")),
    )
    op.create_table(
        "withdrawals",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("label_id", sa.Integer(), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("withdrawn_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["label_id"], ["labels.id"],
                                name="fk_withdrawals_label_id_labels"),
        sa.ForeignKeyConstraint(["run_id"], ["runs.id"], name="fk_withdrawals_run_id_runs"),
        sa.PrimaryKeyConstraint("id", name="pk_withdrawals"),
    )
    op.create_index("ix_withdrawals_run_id", "withdrawals", ["run_id", "id"])


def downgrade() -> None:
    op.drop_index("ix_withdrawals_run_id", table_name="withdrawals")
    op.drop_table("withdrawals")
    op.drop_table("external_pairs")
    op.drop_table("run_tokens")
    with op.batch_alter_table("queries") as batch:
        for name in RETURNS:
            batch.alter_column(name, existing_type=sa.Float(), nullable=False)
