"""Labels keep their answer in segment terms, with the full answer vocabulary (`answer`, from
`runvocab.answers`), instead of `preferred`; the unused `gold` label source goes. Queries may be
gold pairs. Labellers may be paused on a run whose gold pairs they answer badly.

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-23
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007"
down_revision: str | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

ANSWERS = ("first", "second", "equal", "cant_tell", "skip")


def _one_of(values: Sequence[str]) -> str:
    return ", ".join(f"'{v}'" for v in values)


# The answer a click gave, from the click and the sides it was given with.
ANSWER_OF_CLICK = """
UPDATE labels SET answer = CASE
    WHEN choice = 'left' AND left_is_first THEN 'first'
    WHEN choice = 'left' THEN 'second'
    WHEN choice = 'right' AND left_is_first THEN 'second'
    WHEN choice = 'right' THEN 'first'
    ELSE choice END
"""


def upgrade() -> None:
    op.execute("UPDATE labels SET source = 'human' WHERE source = 'gold'")
    with op.batch_alter_table("labels") as batch:
        batch.add_column(sa.Column("answer", sa.String(16), nullable=True))
    op.execute(ANSWER_OF_CLICK)
    # Batch mode: SQLite changes a column's constraints only by recreating the table.
    with op.batch_alter_table("labels") as batch:
        batch.alter_column("answer", existing_type=sa.String(16), nullable=False)
        batch.create_check_constraint("answer", f"answer IN ({_one_of(ANSWERS)})")
        batch.drop_constraint("preferred", type_="check")
        batch.drop_column("preferred")
        batch.drop_constraint("source", type_="check")
        batch.create_check_constraint("source", "source IN ('human', 'scripted')")
    with op.batch_alter_table("queries") as batch:
        batch.add_column(sa.Column("gold", sa.Boolean(), nullable=False,
                                   server_default=sa.false()))
    with op.batch_alter_table("queries") as batch:
        batch.alter_column("gold", existing_type=sa.Boolean(), server_default=None)
    op.create_table(
        "labeller_pauses",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("run_id", sa.Integer(), sa.ForeignKey("runs.id"), nullable=False),
        sa.Column("labeller_id", sa.Integer(), sa.ForeignKey("labellers.id"), nullable=False),
        sa.Column("gold_answers", sa.Integer(), nullable=False),
        sa.Column("gold_correct", sa.Integer(), nullable=False),
        sa.Column("paused_at", sa.DateTime(timezone=True), nullable=False),
        sa.UniqueConstraint("run_id", "labeller_id"),
    )


def downgrade() -> None:
    op.drop_table("labeller_pauses")
    with op.batch_alter_table("queries") as batch:
        batch.drop_column("gold")
    with op.batch_alter_table("labels") as batch:
        batch.add_column(sa.Column("preferred", sa.String(16), nullable=True))
    op.execute("UPDATE labels SET preferred = CASE WHEN answer IN ('first', 'second', 'equal') "
                "THEN answer END")
    with op.batch_alter_table("labels") as batch:
        batch.create_check_constraint("preferred", "preferred IN ('first', 'second', 'equal')")
        batch.drop_constraint("answer", type_="check")
        batch.drop_column("answer")
        batch.drop_constraint("source", type_="check")
        batch.create_check_constraint("source", "source IN ('human', 'scripted', 'gold')")
