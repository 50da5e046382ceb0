"""The label database's rows for export: one row per label (`rundata.label_files` writes
them as JSONL, CSV or Parquet).

The columns are declared once, in `COLUMNS`; a query's own columns come from its fields'
declaration (`runvocab.query_fields`). docs/EXPORT.md lists the same table (a test keeps the
two equal). `SCHEMA_VERSION` is written into every row and into the Parquet file's metadata.
Additive changes (a new column) keep the version; renaming or removing a column, or changing
its type or meaning, bumps it.

Rows hold hidden ground truth (segment and trajectory returns, the scripted teacher's answer):
an export is for operators, never for a labeller's browser.

Rows are read in chunks by label id, each chunk in its own short transaction, up to the newest
label at the start of the export: SQLite's write lock is never held for the whole export, and
labels answered meanwhile wait for the next one.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Literal

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from labelqueue.errors import NotFound
from labelqueue.instructions import InstructionHistory, instructions_at
from labelqueue.models import ExternalPair, Label, Labeller, LabelSource, Query, Run
from labelqueue.transaction import reading
from runvocab.answers import Answer, trained_answer
from runvocab.instructions import instruction_sha256, run_instruction
from runvocab.query_fields import QUERY_FIELDS, FieldType

SCHEMA_VERSION = 3
CHUNK_ROWS = 2000

ColumnType = Literal["int64", "float64", "string", "bool", "timestamp", "list<float64>"]


@dataclass(frozen=True)
class Column:
    """One exported column, as docs/EXPORT.md documents it."""

    name: str
    type: ColumnType
    nullable: bool
    description: str


def _c(name: str, type_: ColumnType, description: str, *, nullable: bool = False) -> Column:
    return Column(name, type_, nullable, description)


# The query's own columns, as `runvocab.query_fields` declares them.
_TYPES: dict[FieldType, ColumnType] = {
    "int": "int64",
    "float": "float64",
    "bool": "bool",
    "str": "string",
    "floats": "list<float64>",
    "answer": "string",
    "clip": "string",
}
QUERY_COLUMNS: tuple[Column, ...] = tuple(
    Column(field.name, _TYPES[field.type], field.nullable, field.description)
    for field in QUERY_FIELDS
    if field.exported
)
"""the columns each exported query field gives, in the declaration's order"""

COLUMNS: tuple[Column, ...] = (
    _c("schema_version", "int64", "version of this column schema (see below)"),
    _c("label_id", "int64", "the label's id; rows are ordered by it"),
    _c("query_id", "int64", "the query (pair of segments) the label answers"),
    _c("run_id", "int64", "the run that asked the query"),
    _c("run_name", "string", "the run's name"),
    _c("task", "string", "the run's task, e.g. `dmc:cheetah_run`"),
    _c("algo", "string", "the run's algorithm: sac, pebble, surf, rune, rime or sepoa"),
    _c("preset", "string", "the run's configuration preset"),
    _c("seed", "int64", "the run's seed"),
    *QUERY_COLUMNS,
    _c("labels_per_query", "int64", "distinct labellers' answers the query asked for; null for "
       "a gold pair, which every labeller may answer once", nullable=True),
    _c("query_answers", "int64", "standing answers (not withdrawn) the query got in all"),
    _c("aggregate", "string", "the query's answer the reward model trains on: the scripted "
       "teacher's if it answered, else the majority over its standing answers "
       "(`runvocab.answers.trained_answer`); null for a gold pair", nullable=True),
    _c("labeller_id", "int64", "who answered"),
    _c("labeller_name", "string", "who answered, by name"),
    _c("source", "string", "what answered: human or scripted"),
    _c(
        "choice",
        "string",
        "what was clicked, in screen terms: left, right, equal, cant_tell or skip",
    ),
    _c("left_is_first", "bool", "whether the first segment was shown on the left"),
    _c("left_segment", "string", "which segment was shown on the left: first or second"),
    _c(
        "answer",
        "string",
        "the answer in segment terms: first, second, equal, cant_tell or skip",
    ),
    _c(
        "agrees_with_shadow",
        "bool",
        "`answer` equals `shadow_choice`; null unless both are first, second or equal",
        nullable=True,
    ),
    _c(
        "correct",
        "bool",
        "`answer` names the segment with the larger true segment return "
        "(equal: the returns are exactly equal); null unless `answer` is first, second or equal",
        nullable=True,
    ),
    _c("shown_at", "timestamp", "when the pair was shown (as the page reported it)", nullable=True),
    _c("answered_at", "timestamp", "when the answer was stored"),
    _c(
        "answer_seconds",
        "float64",
        "seconds from `shown_at` to `answered_at`",
        nullable=True,
    ),
    _c(
        "consumed_at",
        "timestamp",
        "when the trainer took the label; null until then",
        nullable=True,
    ),
    _c(
        "withdrawn_at",
        "timestamp",
        "when the labeller took the answer back (undo); null for an answer that stands",
        nullable=True,
    ),
    _c(
        "flag",
        "string",
        "the labeller flagged the pair (with a skip): clip_broken, not_visible or other; null "
        "for an unflagged answer",
        nullable=True,
    ),
    _c("flag_note", "string", "the labeller's note on the flag; null without one", nullable=True),
    _c("practice", "bool", "an answer of the labeller's practice round on the run (a gold pair, "
       "explained once answered, not counted in gold accuracy)"),
    _c(
        "instruction",
        "string",
        "the run's instruction to labellers when the label was answered, as shown",
    ),
    _c(
        "instruction_sha256",
        "string",
        "hex sha256 of `instruction` (UTF-8): equal texts, equal hashes",
    ),
)
COLUMN_NAMES: tuple[str, ...] = tuple(column.name for column in COLUMNS)

# The stored values, by column name; `_row` derives the other columns from them.
_STORED: dict[str, Any] = {
    "label_id": Label.id,
    "query_id": Label.query_id,
    "run_id": Label.run_id,
    "run_name": Run.name,
    "task": Run.task,
    "algo": Run.algo,
    "preset": Run.preset,
    "seed": Run.seed,
    **{column.name: getattr(Query, column.name) for column in QUERY_COLUMNS},
    "needs_labels": Query.needs_labels,
    "gold_answer": ExternalPair.gold_answer,  # an external gold pair known by its answer only
    "labeller_id": Label.labeller_id,
    "labeller_name": Labeller.name,
    "source": Label.source,
    "choice": Label.choice,
    "left_is_first": Label.left_is_first,
    "answer": Label.answer,
    "shown_at": Label.shown_at,
    "answered_at": Label.answered_at,
    "consumed_at": Label.consumed_at,
    "withdrawn_at": Label.withdrawn_at,
    "flag": Label.flag,
    "flag_note": Label.flag_note,
    "practice": Label.practice,
}
_SEGMENT_ANSWERS = ("first", "second", "equal")


def _plain(value: Any) -> Any:
    """Enum members as their values, non-finite floats as None, skills as lists of floats."""
    if isinstance(value, StrEnum):
        return value.value
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, list):
        return [_plain(float(x)) for x in value]
    return value


def correct_answer(first_return: float | None, second_return: float | None) -> str | None:
    """The segment answer the true segment returns call for: first, second or equal."""
    if first_return is None or second_return is None:
        return None
    if first_return == second_return:
        return "equal"
    return "first" if first_return > second_return else "second"


def _row(stored: Mapping[str, Any], instructions: InstructionHistory,
         answers: Mapping[int, list[tuple[Answer, bool]]]) -> dict[str, Any]:
    got = {name: _plain(value) for name, value in stored.items()}
    given = instructions.at(got["run_id"], got["answered_at"])
    # A run from before instructions were recorded showed its task's own until its first edit.
    text = given.text if given is not None else run_instruction(got["task"], None)
    answer, shadow = got["answer"], got["shadow_choice"]
    preferred = answer if answer in _SEGMENT_ANSWERS else None
    given_to_query = answers.get(got["query_id"], [])
    truth = got["gold_answer"] or correct_answer(got["first_segment_return"],
                                                 got["second_segment_return"])
    shown, answered = got["shown_at"], got["answered_at"]
    derived = {
        "schema_version": SCHEMA_VERSION,
        "left_segment": "first" if got["left_is_first"] else "second",
        "labels_per_query": None if got["gold"] else got["needs_labels"],
        "query_answers": len(given_to_query),
        "aggregate": None if got["gold"] else trained_answer(given_to_query).value,
        "agrees_with_shadow": (
            preferred == shadow
            if preferred in _SEGMENT_ANSWERS and shadow in _SEGMENT_ANSWERS
            else None
        ),
        "correct": None if preferred is None or truth is None else preferred == truth,
        "answer_seconds": (
            None if shown is None or answered is None else (answered - shown).total_seconds()
        ),
        "instruction": text,
        "instruction_sha256": instruction_sha256(text),
    }
    merged = got | derived
    return {name: merged[name] for name in COLUMN_NAMES}


def export_rows(
    session: Session, *, run_id: int | None = None, chunk_rows: int | None = None
) -> Iterator[dict[str, Any]]:
    """One dict per label (keys: `COLUMN_NAMES`), ordered by label id; of one run or all.

    Raises NotFound at once for an unknown run. Labels answered after the call are left out.
    Values are Python values: int, float, str, bool, UTC-aware datetime, list[float] or None.
    Each chunk of `chunk_rows` (default `CHUNK_ROWS`) is read in a transaction of its own.
    """
    limit = chunk_rows or CHUNK_ROWS
    condition = [] if run_id is None else [Label.run_id == run_id]
    with reading(session):
        if run_id is not None and session.scalar(select(Run.id).where(Run.id == run_id)) is None:
            raise NotFound(f"run {run_id} does not exist")
        last = session.scalar(select(func.max(Label.id)).where(*condition))

    def rows() -> Iterator[dict[str, Any]]:
        after = 0
        while last is not None and after < last:
            with reading(session):
                chunk = session.execute(
                    select(*(column.label(name) for name, column in _STORED.items()))
                    .join(Query, Query.id == Label.query_id)
                    .outerjoin(ExternalPair, ExternalPair.query_id == Query.id)
                    .join(Run, Run.id == Label.run_id)
                    .join(Labeller, Labeller.id == Label.labeller_id)
                    .where(Label.id > after, Label.id <= last, *condition)
                    .order_by(Label.id)
                    .limit(limit)
                ).all()
            if not chunk:
                return
            after = chunk[-1].label_id
            instructions = instructions_at(session, run_ids={row.run_id for row in chunk})
            answers = standing_answers(session, query_ids={row.query_id for row in chunk},
                                       last=last)
            for stored in chunk:
                yield _row(stored._asdict(), instructions, answers)

    return rows()


def standing_answers(session: Session, *, query_ids: set[int],
                     last: int | None = None) -> dict[int, list[tuple[Answer, bool]]]:
    """Each query's standing answers (not withdrawn), each with whether the scripted teacher
    gave it, by query id; with `last`, only labels up to that id (those an export found)."""
    answers: dict[int, list[tuple[Answer, bool]]] = {}
    bound = [] if last is None else [Label.id <= last]
    with reading(session):
        rows = session.execute(select(Label.query_id, Label.answer, Label.source).where(
            Label.query_id.in_(query_ids), Label.withdrawn_at.is_(None), *bound)
            .order_by(Label.id))
        for query_id, answer, source in rows:
            answers.setdefault(query_id, []).append(
                (Answer(answer), source == LabelSource.SCRIPTED))
    return answers
