"""Initial schema: labellers, runs, workers, queries, labels, metrics.

Revision ID: 0001
Revises:
Create Date: 2026-11-21
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0001"
down_revision: str | None = None
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def _one_of(column: str, values: Sequence[str], name: str) -> sa.CheckConstraint:
    # The models' enums are VARCHAR + CHECK, spelled out so this revision never changes.
    allowed = ", ".join(f"'{v}'" for v in values)
    return sa.CheckConstraint(f"{column} IN ({allowed})", name=op.f(name))


def _time(name: str, nullable: bool) -> sa.Column:
    return sa.Column(name, sa.DateTime(timezone=True), nullable=nullable)


def upgrade() -> None:
    op.create_table(
        "labellers",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(100), nullable=False),
        sa.Column("role", sa.String(16), nullable=False),
        sa.Column("token_hash", sa.String(64), nullable=False),
        sa.Column("active", sa.Boolean(), nullable=False),
        _time("created_at", nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_labellers")),
        sa.UniqueConstraint("name", name=op.f("uq_labellers_name")),
        _one_of("role", ["labeller", "operator"], "ck_labellers_role"),
    )

    op.create_table(
        "runs",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(200), nullable=False),
        sa.Column("task", sa.String(100), nullable=False),
        sa.Column("algo", sa.String(50), nullable=False),
        sa.Column("preset", sa.String(50), nullable=False),
        sa.Column("seed", sa.Integer(), nullable=False),
        sa.Column("config", sa.JSON(), nullable=False),
        sa.Column("teacher", sa.String(16), nullable=False),
        sa.Column("teacher_params", sa.JSON(), nullable=False),
        sa.Column("budget", sa.Integer(), nullable=False),
        sa.Column("labels_used", sa.Integer(), nullable=False),
        sa.Column("step", sa.Integer(), nullable=False),
        sa.Column("progress", sa.JSON(), nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("worker_id", sa.String(200), nullable=True),
        _time("heartbeat_at", nullable=True),
        _time("created_at", nullable=False),
        _time("started_at", nullable=True),
        _time("finished_at", nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_runs")),
        _one_of("teacher", ["human", "scripted"], "ck_runs_teacher"),
        _one_of(
            "status",
            ["queued", "running", "paused", "stopping", "stopped", "finished", "failed"],
            "ck_runs_status",
        ),
    )
    op.create_index(op.f("ix_runs_status"), "runs", ["status"])

    op.create_table(
        "workers",
        sa.Column("id", sa.String(200), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=True),
        _time("first_seen_at", nullable=False),
        _time("last_seen_at", nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_workers")),
        sa.ForeignKeyConstraint(["run_id"], ["runs.id"], name=op.f("fk_workers_run_id_runs")),
    )

    op.create_table(
        "queries",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("round", sa.Integer(), nullable=False),
        sa.Column("position", sa.Integer(), nullable=False),
        sa.Column("step", sa.Integer(), nullable=True),
        sa.Column("segment_length", sa.Integer(), nullable=False),
        sa.Column("first_trajectory", sa.Integer(), nullable=False),
        sa.Column("first_start", sa.Integer(), nullable=False),
        sa.Column("first_skill", sa.JSON(), nullable=True),
        sa.Column("first_clip", sa.String(500), nullable=True),
        sa.Column("first_segment_return", sa.Float(), nullable=False),
        sa.Column("first_trajectory_return", sa.Float(), nullable=False),
        sa.Column("second_trajectory", sa.Integer(), nullable=False),
        sa.Column("second_start", sa.Integer(), nullable=False),
        sa.Column("second_skill", sa.JSON(), nullable=True),
        sa.Column("second_clip", sa.String(500), nullable=True),
        sa.Column("second_segment_return", sa.Float(), nullable=False),
        sa.Column("second_trajectory_return", sa.Float(), nullable=False),
        sa.Column("model_p", sa.Float(), nullable=True),
        sa.Column("score", sa.Float(), nullable=True),
        sa.Column("rule", sa.String(50), nullable=True),
        sa.Column("needs_labels", sa.Integer(), nullable=False),
        sa.Column("label_count", sa.Integer(), nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("lease_holder", sa.Integer(), nullable=True),
        _time("lease_expires_at", nullable=True),
        _time("created_at", nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_queries")),
        sa.ForeignKeyConstraint(["run_id"], ["runs.id"], name=op.f("fk_queries_run_id_runs")),
        sa.ForeignKeyConstraint(
            ["lease_holder"], ["labellers.id"], name=op.f("fk_queries_lease_holder_labellers")
        ),
        sa.UniqueConstraint(
            "run_id", "round", "position", name=op.f("uq_queries_run_id_round_position")
        ),
        _one_of("status", ["pending", "leased", "labelled", "cancelled"], "ck_queries_status"),
    )
    op.create_index(op.f("ix_queries_run_id_status"), "queries", ["run_id", "status", "id"])
    op.create_index(op.f("ix_queries_lease_holder"), "queries", ["lease_holder"])

    op.create_table(
        "labels",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("query_id", sa.Integer(), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("labeller_id", sa.Integer(), nullable=False),
        sa.Column("choice", sa.String(16), nullable=False),
        sa.Column("left_is_first", sa.Boolean(), nullable=False),
        sa.Column("preferred", sa.String(16), nullable=True),
        sa.Column("source", sa.String(16), nullable=False),
        _time("shown_at", nullable=True),
        _time("answered_at", nullable=False),
        _time("consumed_at", nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_labels")),
        sa.ForeignKeyConstraint(
            ["query_id"], ["queries.id"], name=op.f("fk_labels_query_id_queries")
        ),
        sa.ForeignKeyConstraint(["run_id"], ["runs.id"], name=op.f("fk_labels_run_id_runs")),
        sa.ForeignKeyConstraint(
            ["labeller_id"], ["labellers.id"], name=op.f("fk_labels_labeller_id_labellers")
        ),
        sa.UniqueConstraint("query_id", "labeller_id", name=op.f("uq_labels_query_id_labeller_id")),
        _one_of("choice", ["left", "right", "equal", "cant_tell", "skip"], "ck_labels_choice"),
        _one_of("preferred", ["first", "second", "equal"], "ck_labels_preferred"),
        _one_of("source", ["human", "scripted", "gold"], "ck_labels_source"),
    )
    op.create_index(op.f("ix_labels_run_id_consumed_at"), "labels", ["run_id", "consumed_at"])

    op.create_table(
        "metrics",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("stream", sa.String(16), nullable=False),
        sa.Column("step", sa.Integer(), nullable=False),
        sa.Column("values", sa.JSON(), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_metrics")),
        sa.ForeignKeyConstraint(["run_id"], ["runs.id"], name=op.f("fk_metrics_run_id_runs")),
        sa.UniqueConstraint("run_id", "stream", "step", name=op.f("uq_metrics_run_id_stream_step")),
        _one_of("stream", ["episodes", "eval", "rounds"], "ck_metrics_stream"),
    )


def downgrade() -> None:
    op.drop_table("metrics")
    op.drop_table("labels")
    op.drop_table("queries")
    op.drop_table("workers")
    op.drop_table("runs")
    op.drop_table("labellers")
