"""Invite links: operators hand them out, people join as labellers by opening one.

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-24
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005"
down_revision: str | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def _time(name: str, *, nullable: bool) -> sa.Column:
    return sa.Column(name, sa.DateTime(timezone=True), nullable=nullable)


def upgrade() -> None:
    op.create_table(
        "invites",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("code", sa.String(64), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=True),
        sa.Column("note", sa.String(200), nullable=True),
        _time("expires_at", nullable=False),
        sa.Column("max_uses", sa.Integer(), nullable=True),
        sa.Column("uses", sa.Integer(), nullable=False),
        sa.Column("target_answers", sa.Integer(), nullable=True),
        sa.Column("completion_code", sa.String(64), nullable=True),
        _time("created_at", nullable=False),
        _time("revoked_at", nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_invites")),
        sa.ForeignKeyConstraint(["run_id"], ["runs.id"], name=op.f("fk_invites_run_id_runs")),
        sa.UniqueConstraint("code", name=op.f("uq_invites_code")),
    )
    op.create_table(
        "invitees",
        sa.Column("labeller_id", sa.Integer(), nullable=False),
        sa.Column("invite_id", sa.Integer(), nullable=False),
        sa.Column("participant", sa.String(100), nullable=True),
        _time("joined_at", nullable=False),
        sa.PrimaryKeyConstraint("labeller_id", name=op.f("pk_invitees")),
        sa.ForeignKeyConstraint(
            ["labeller_id"], ["labellers.id"], name=op.f("fk_invitees_labeller_id_labellers")
        ),
        sa.ForeignKeyConstraint(
            ["invite_id"], ["invites.id"], name=op.f("fk_invitees_invite_id_invites")
        ),
    )
    op.create_index(op.f("ix_invitees_invite_id"), "invitees", ["invite_id"], unique=False)


def downgrade() -> None:
    op.drop_index(op.f("ix_invitees_invite_id"), table_name="invitees")
    op.drop_table("invitees")
    op.drop_table("invites")
