"""The label export: one row per label with exact derived columns, the same rows in JSONL, CSV
and Parquet as pandas reads them, a versioned schema that docs/EXPORT.md lists exactly."""

from __future__ import annotations

import csv
import io
import json
import math
import re
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any, NamedTuple

import pandas as pd
import pyarrow.parquet as pq
import pytest
from queue_helpers import query_spec
from sqlalchemy import update
from sqlalchemy.orm import Session, sessionmaker

from labelqueue import (
    EXPORT_COLUMNS,
    EXPORT_SCHEMA_VERSION,
    NotFound,
    claim_run,
    consume_labels,
    create_labeller,
    create_run,
    export,
    export_rows,
    lease_next_query,
    push_queries,
    submit_label,
)
from labelqueue.models import Query, utcnow
from rundata import label_files
from rundata.label_files import FORMATS as EXPORT_FORMATS
from rundata.label_files import PARQUET_VERSION_KEY, parquet_schema, write_export
from runvocab.query_fields import QUERY_FIELDS

# How a declared query field's type is exported (docs/EXPORT.md's types).
EXPORT_TYPES = {"int": "int64", "float": "float64", "bool": "bool", "str": "string",
                "floats": "list<float64>", "answer": "string", "clip": "string"}

DOCS = Path(__file__).resolve().parents[2] / "docs" / "EXPORT.md"
NAMES = [column.name for column in EXPORT_COLUMNS]
TIMES = [column.name for column in EXPORT_COLUMNS if column.type == "timestamp"]
SHOWN_BEFORE = timedelta(seconds=2.5)


class Answer(NamedTuple):
    """One seeded label and the derived columns its row must have."""

    query: int  # index into the seeded queries
    labeller: str
    choice: str
    left_is_first: bool
    source: str
    left_segment: str
    answer: str
    agrees_with_shadow: bool | None
    correct: bool | None


# Run "alpha" (people): q0 true answer second, shadow second; q1 equal returns, no shadow;
# q2 true answer first, shadow cant_tell. Run "beta" (scripted): q3 true first, shadow first;
# q4 true second, shadow equal.
ANSWERS = [
    Answer(0, "alice", "left", False, "human", "second", "second", True, True),
    Answer(0, "bob", "left", True, "human", "first", "first", False, False),
    Answer(1, "alice", "equal", False, "human", "second", "equal", None, True),
    Answer(1, "bob", "right", False, "human", "second", "first", None, False),
    Answer(2, "alice", "cant_tell", True, "human", "first", "cant_tell", None, None),
    Answer(2, "bob", "right", False, "human", "second", "first", None, True),
    Answer(3, "teacher", "right", False, "scripted", "second", "first", True, True),
    Answer(4, "teacher", "equal", True, "scripted", "first", "equal", True, False),
]


class Seeded(NamedTuple):
    alpha: int
    beta: int
    query_ids: list[int]
    labellers: dict[str, int]


def seed(session: Session) -> Seeded:
    alpha = create_run(
        session, name="alpha", task="dmc:cheetah_run", algo="sepoa", budget=100, seed=3
    )
    assert (claimed := claim_run(session, worker_id="worker-a")) and claimed.id == alpha.id
    beta = create_run(
        session,
        name="beta",
        task="metaworld:drawer-open",
        algo="pebble",
        budget=100,
        preset="tiny",
        teacher="scripted",
    )
    assert (claimed := claim_run(session, worker_id="worker-b")) and claimed.id == beta.id
    alpha_ids = push_queries(
        session,
        run_id=alpha.id,
        queries=[
            query_spec(0, needs_labels=2, shadow_choice="second", distinguishable=True),
            query_spec(
                1, needs_labels=2, first_segment_return=3.0, second_segment_return=3.0, step=None
            ),
            query_spec(
                2,
                needs_labels=2,
                first_segment_return=5.0,
                second_segment_return=-1.25,
                shadow_choice="cant_tell",
                distinguishable=False,
            ),
        ],
    )
    beta_ids = push_queries(
        session,
        run_id=beta.id,
        queries=[
            query_spec(
                0,
                round=1,
                first_segment_return=2.0,
                second_segment_return=0.5,
                first_skill=[0.25, -1.0],
                second_skill=[1.5, 2.0],
                shadow_choice="first",
                model_p=None,
                score=None,
                rule=None,
            ),
            query_spec(1, round=1, shadow_choice="equal", first_clip=None, second_clip=None),
        ],
    )
    labellers = {
        name: create_labeller(session, name=name)[0].id for name in ("alice", "bob", "teacher")
    }
    query_ids = alpha_ids + beta_ids
    for answer in ANSWERS:
        query_id = query_ids[answer.query]
        run_id = alpha.id if answer.query < 3 else beta.id
        labeller_id = labellers[answer.labeller]
        leased = lease_next_query(session, labeller_id=labeller_id, run_id=run_id)
        assert leased is not None and leased.id == query_id
        # The pair has been on screen since the lease began, longer than SHOWN_BEFORE.
        session.execute(
            update(Query).where(Query.id == query_id).values(leased_at=utcnow() - 2 * SHOWN_BEFORE)
        )
        session.commit()
        submit_label(
            session,
            query_id=query_id,
            labeller_id=labeller_id,
            choice=answer.choice,
            left_is_first=answer.left_is_first,
            shown_at=None if answer.labeller == "teacher" else utcnow() - SHOWN_BEFORE,
            source=answer.source,
        )
    assert len(consume_labels(session, run_id=beta.id)) == 2
    return Seeded(alpha.id, beta.id, query_ids, labellers)


def written(session: Session, fmt: str, run_id: int | None = None) -> tuple[bytes, int]:
    out = io.BytesIO()
    count = write_export(session, fmt=fmt, out=out, run_id=run_id)
    return out.getvalue(), count


def read(fmt: str, data: bytes) -> pd.DataFrame:
    """The export as the documented pandas calls read it (docs/EXPORT.md)."""
    if fmt == "jsonl":
        return pd.read_json(io.BytesIO(data), lines=True, precise_float=True)
    if fmt == "csv":
        frame = pd.read_csv(io.BytesIO(data), parse_dates=TIMES)
        for side in ("first_skill", "second_skill"):
            frame[side] = frame[side].map(json.loads, na_action="ignore")
        return frame
    return pd.read_parquet(io.BytesIO(data))


def plain(type_: str, value: Any) -> Any:
    """A pandas cell as the Python value `export_rows` gives for a column of this type."""
    if type_ == "list<float64>":
        return (
            None
            if value is None or value is pd.NA or isinstance(value, float)
            else [float(x) for x in value]
        )
    if value is None or value is pd.NaT or value is pd.NA:
        return None
    if isinstance(value, float) and math.isnan(value):
        return None
    converters: dict[str, Any] = {
        "int64": int,
        "float64": float,
        "string": str,
        "bool": bool,
        "timestamp": lambda stamp: stamp.to_pydatetime(),
    }
    return converters[type_](value)


def records(frame: pd.DataFrame) -> list[dict[str, Any]]:
    assert list(frame.columns) == NAMES
    return [
        {column.name: plain(column.type, row[column.name]) for column in EXPORT_COLUMNS}
        for row in frame.to_dict("records")
    ]


def test_each_label_is_one_row_with_exact_derived_columns(session: Session) -> None:
    seeded = seed(session)
    rows = list(export_rows(session))
    assert not session.in_transaction()
    assert [row["label_id"] for row in rows] == sorted(row["label_id"] for row in rows)
    assert len(rows) == len(ANSWERS)
    for row, answer in zip(rows, ANSWERS, strict=True):
        assert list(row) == NAMES
        assert row["query_id"] == seeded.query_ids[answer.query]
        assert row["labeller_id"] == seeded.labellers[answer.labeller]
        assert row["labeller_name"] == answer.labeller
        assert (
            row["choice"],
            row["left_is_first"],
            row["source"],
            row["left_segment"],
            row["answer"],
            row["agrees_with_shadow"],
            row["correct"],
        ) == answer[2:], (row["label_id"], answer)
        assert row["schema_version"] == EXPORT_SCHEMA_VERSION == 3

    alpha_row, beta_row = rows[0], rows[6]
    assert (alpha_row["run_id"], alpha_row["run_name"], alpha_row["task"]) == (
        seeded.alpha,
        "alpha",
        "dmc:cheetah_run",
    )
    assert (alpha_row["algo"], alpha_row["preset"], alpha_row["seed"]) == ("sepoa", "small", 3)
    assert (alpha_row["round"], alpha_row["position"], alpha_row["step"]) == (0, 0, 1000)
    assert (alpha_row["first_segment_return"], alpha_row["second_segment_return"]) == (1.5, 2.5)
    assert alpha_row["first_trajectory_return"] == 100.0
    assert alpha_row["second_trajectory_return"] == 120.0
    assert (alpha_row["model_p"], alpha_row["score"], alpha_row["rule"]) == (
        0.6,
        0.1,
        "disagreement",
    )
    assert (alpha_row["shadow_choice"], alpha_row["distinguishable"]) == ("second", True)
    assert alpha_row["first_skill"] is None and alpha_row["consumed_at"] is None
    assert rows[2]["shadow_choice"] is None and rows[2]["step"] is None
    assert rows[4]["shadow_choice"] == "cant_tell" and rows[4]["distinguishable"] is False
    assert alpha_row["answer_seconds"] == pytest.approx(SHOWN_BEFORE.total_seconds(), abs=1.0)
    assert alpha_row["answer_seconds"] == (
        (alpha_row["answered_at"] - alpha_row["shown_at"]).total_seconds()
    )

    assert (beta_row["run_name"], beta_row["algo"], beta_row["round"]) == ("beta", "pebble", 1)
    assert (beta_row["first_skill"], beta_row["second_skill"]) == ([0.25, -1.0], [1.5, 2.0])
    assert (beta_row["model_p"], beta_row["score"], beta_row["rule"]) == (None, None, None)
    assert beta_row["shown_at"] is None and beta_row["answer_seconds"] is None
    assert isinstance(beta_row["consumed_at"], datetime)
    assert beta_row["consumed_at"].utcoffset() == timedelta(0)


def test_the_query_columns_are_the_declared_query_fields_with_their_stored_values(
    session: Session,
) -> None:
    exported = [field for field in QUERY_FIELDS if field.exported]
    declared = [
        (field.name, EXPORT_TYPES[field.type], field.nullable, field.description)
        for field in exported
    ]
    start = NAMES.index(exported[0].name)
    columns = EXPORT_COLUMNS[start : start + len(exported)]
    assert [(c.name, c.type, c.nullable, c.description) for c in columns] == declared
    assert not {field.name for field in QUERY_FIELDS if not field.exported} & set(NAMES)

    seed(session)
    for row in export_rows(session):
        query = session.get(Query, row["query_id"])
        assert query is not None
        for field in exported:
            assert row[field.name] == getattr(query, field.name), field.name


def test_a_run_filter_keeps_only_that_runs_labels(session: Session) -> None:
    seeded = seed(session)
    beta = list(export_rows(session, run_id=seeded.beta))
    assert [row["source"] for row in beta] == ["scripted", "scripted"]
    assert {row["run_id"] for row in beta} == {seeded.beta}
    alpha = list(export_rows(session, run_id=seeded.alpha))
    assert [row["labeller_name"] for row in alpha] == ["alice", "bob"] * 3
    assert written(session, "jsonl", seeded.beta)[1] == 2
    with pytest.raises(NotFound, match="run 999"):
        export_rows(session, run_id=999)
    for fmt in EXPORT_FORMATS:
        out = io.BytesIO()
        with pytest.raises(NotFound):
            write_export(session, fmt=fmt, out=out, run_id=999)
        assert out.getvalue() == b""


def test_an_unknown_format_is_refused_naming_the_valid_ones(session: Session) -> None:
    out = io.BytesIO()
    with pytest.raises(ValueError, match="xlsx.*jsonl, csv, parquet"):
        write_export(session, fmt="xlsx", out=out)
    assert out.getvalue() == b""


def test_an_empty_export_still_has_its_columns(session: Session) -> None:
    run = create_run(session, name="empty", task="dmc:cheetah_run", algo="sac", budget=1)
    for run_id in (None, run.id):
        assert written(session, "jsonl", run_id) == (b"", 0)
        data, count = written(session, "csv", run_id)
        assert count == 0 and data == (",".join(NAMES) + "\n").encode()
        assert list(pd.read_csv(io.BytesIO(data)).columns) == NAMES
        data, count = written(session, "parquet", run_id)
        assert count == 0
        table = pq.read_table(io.BytesIO(data))
        assert table.num_rows == 0 and table.schema.equals(parquet_schema())
        frame = pd.read_parquet(io.BytesIO(data))
        assert list(frame.columns) == NAMES
        assert str(frame["answered_at"].dtype) == "datetime64[us, UTC]"
        assert str(frame["label_id"].dtype) == "int64"


def test_pandas_reads_the_same_rows_and_values_from_every_format(session: Session) -> None:
    seed(session)
    expected = list(export_rows(session))
    frames = {}
    for fmt in EXPORT_FORMATS:
        data, count = written(session, fmt)
        assert count == len(expected)
        frames[fmt] = read(fmt, data)
        assert records(frames[fmt]) == expected, fmt
        assert str(frames[fmt]["answered_at"].dtype).endswith(", UTC]"), fmt
        assert frames[fmt]["label_id"].dtype == "int64", fmt

    lines = [json.loads(line) for line in written(session, "jsonl")[0].splitlines()]
    assert lines[0]["answered_at"].endswith("+00:00") and "T" in lines[0]["answered_at"]
    assert lines[6]["first_skill"] == [0.25, -1.0] and lines[6]["model_p"] is None
    csv_text = written(session, "csv")[0].decode()
    assert csv_text.splitlines()[0] == ",".join(NAMES)
    cells = next(csv.DictReader(io.StringIO(csv_text)))  # instructions hold commas: quoted
    assert (cells["left_is_first"], cells["left_segment"], cells["answer"]) == (
        "false",
        "second",
        "second",
    )
    assert (cells["agrees_with_shadow"], cells["correct"]) == ("true", "true")
    assert (cells["first_skill"], cells["consumed_at"]) == ("", "")
    beta_cells = next(line for line in csv_text.splitlines() if ",beta," in line)
    assert '"[0.25, -1.0]"' in beta_cells
    data = written(session, "parquet")[0]
    assert pq.read_schema(io.BytesIO(data)).metadata[PARQUET_VERSION_KEY.encode()] == b"3"


def test_small_chunks_write_the_same_files(
    session: Session, monkeypatch: pytest.MonkeyPatch
) -> None:
    seed(session)
    whole = {fmt: written(session, fmt) for fmt in EXPORT_FORMATS}
    monkeypatch.setattr(export, "CHUNK_ROWS", 3)  # the rows read per transaction
    monkeypatch.setattr(label_files, "CHUNK_ROWS", 3)  # the rows written per Parquet row group
    for fmt in ("jsonl", "csv"):
        assert written(session, fmt) == whole[fmt]
    data, count = written(session, "parquet")
    assert count == len(ANSWERS) and pq.ParquetFile(io.BytesIO(data)).num_row_groups == 3
    assert pq.read_table(io.BytesIO(data)).equals(pq.read_table(io.BytesIO(whole["parquet"][0])))


def test_labels_answered_during_an_export_wait_for_the_next(
    session: Session, sessions: sessionmaker[Session]
) -> None:
    seeded = seed(session)
    rows = export_rows(session, chunk_rows=2)
    first = next(rows)
    # Between chunks no transaction is open: a writer is not kept waiting by the export.
    assert not session.in_transaction()
    with sessions() as other:
        [query_id] = push_queries(other, run_id=seeded.alpha, queries=[query_spec(3)])
        carol = create_labeller(other, name="carol")[0].id
        assert lease_next_query(other, labeller_id=carol, run_id=seeded.alpha) is not None
        submit_label(other, query_id=query_id, labeller_id=carol, choice="left", left_is_first=True)
    rest = list(rows)
    assert [first, *rest] == list(export_rows(session))[: len(ANSWERS)]
    assert len(rest) == len(ANSWERS) - 1
    assert [row["labeller_name"] for row in export_rows(session)][-1] == "carol"


def test_a_querys_answers_count_only_labels_stored_when_the_export_started(
    session: Session,
) -> None:
    run = create_run(session, name="r", task="dmc:cheetah_run", algo="pebble", budget=100)
    claim_run(session, worker_id="w")
    [query_id] = push_queries(session, run_id=run.id, queries=[query_spec(0, needs_labels=2)])

    def answer(name: str, choice: str) -> None:
        labeller = create_labeller(session, name=name)[0].id
        assert lease_next_query(session, labeller_id=labeller, run_id=run.id) is not None
        submit_label(session, query_id=query_id, labeller_id=labeller, choice=choice,
                     left_is_first=True)

    answer("alice", "left")
    rows = export_rows(session, run_id=run.id)  # the export starts: alice's label only
    answer("bob", "right")  # answered while it runs
    assert [(row["labeller_name"], row["query_answers"], row["aggregate"]) for row in rows] \
        == [("alice", 1, "first")]


def test_docs_list_exactly_the_declared_columns() -> None:
    text = DOCS.read_text()
    assert f"## Columns (schema version {EXPORT_SCHEMA_VERSION})" in text
    table = text.split("| column | type | meaning |", 1)[1].split("\n\n", 1)[0]
    documented = [
        tuple(cell.strip() for cell in line.strip("|").split(" | "))
        for line in table.splitlines()
        if line.startswith("| `")
    ]
    declared = [
        (f"`{c.name}`", c.type + (" or null" if c.nullable else ""), c.description)
        for c in EXPORT_COLUMNS
    ]
    rows = "\n".join(f"| {' | '.join(row)} |" for row in declared if row not in documented)
    assert documented == declared, f"docs/EXPORT.md's table, in COLUMNS' order, needs:\n{rows}"
    assert re.search(rf"`SCHEMA_VERSION` .*now {EXPORT_SCHEMA_VERSION}\)", text)
