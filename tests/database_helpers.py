"""A queue database with labels, and copies of it damaged as disks and copies damage files; a
PostgreSQL schema of its own for a test, when SEPOA_TEST_POSTGRES_URL names a database."""

from __future__ import annotations

import os
import sqlite3
import sys
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from sqlalchemy import create_engine, make_url

from labelqueue import (
    TeacherKind,
    claim_run,
    create_labeller,
    create_run,
    lease_next_query,
    make_engine,
    migrate,
    push_queries,
    session_factory,
    sqlite_url,
    submit_label,
)

sys.path.insert(0, str(Path(__file__).resolve().parent / "labelqueue"))
from queue_helpers import query_spec  # noqa: E402


def damaged_copies(tmp_path: Path) -> dict[str, Path]:
    """A database with 233 labels in the data folder `tmp_path / "sound"`, and data folders
    holding copies of it damaged two ways: "rows", a page of the labels table claiming fewer
    rows than it holds (reads lose labels without an error), and "header", a file whose header
    is overwritten."""
    sound = tmp_path / "sound"
    migrate(sqlite_url(sound))
    engine = make_engine(sqlite_url(sound))
    with session_factory(engine)() as session:
        run = create_run(session, name="r", task="dmc:cheetah_run", algo="pebble", budget=300,
                         teacher=TeacherKind.HUMAN)
        claim_run(session, worker_id="w")
        push_queries(session, run_id=run.id, queries=[query_spec(i) for i in range(240)])
        ann, _ = create_labeller(session, name="ann")
        for _ in range(233):
            query = lease_next_query(session, labeller_id=ann.id, run_id=run.id)
            assert query is not None
            submit_label(session, query_id=query.id, labeller_id=ann.id, choice="left",
                         left_is_first=True)
    engine.dispose()  # checkpoints the WAL into the file
    with sqlite3.connect(sound / "queue.db") as connection:
        [(page,)] = connection.execute("SELECT pageno FROM dbstat WHERE name = 'labels' AND "
                                       "pagetype = 'leaf' ORDER BY pageno LIMIT 1 OFFSET 1")
        page_size = connection.execute("PRAGMA page_size").fetchone()[0]
    copies = {}
    for kind, offset, data in (("rows", (page - 1) * page_size + 3, b"\x00\x05"),
                               ("header", 0, b"not a database" * 2)):
        folder = tmp_path / kind
        folder.mkdir()
        blob = bytearray((sound / "queue.db").read_bytes())
        blob[offset:offset + len(data)] = data
        (folder / "queue.db").write_bytes(bytes(blob))
        copies[kind] = folder
    return copies


POSTGRES_URL = os.environ.get("SEPOA_TEST_POSTGRES_URL")
"""a PostgreSQL database the tests may use (scripts/with_postgres.sh sets it); unset: none"""
BACKENDS = ["sqlite", "postgresql"] if POSTGRES_URL else ["sqlite"]


@contextmanager
def postgres_schema() -> Iterator[str]:
    """A URL of `POSTGRES_URL`'s database whose search path is a new schema, dropped after."""
    assert POSTGRES_URL is not None
    schema = f"test_{uuid.uuid4().hex[:12]}"
    admin = create_engine(POSTGRES_URL)
    with admin.begin() as connection:
        connection.exec_driver_sql(f'CREATE SCHEMA "{schema}"')
    try:
        scoped = make_url(POSTGRES_URL).update_query_dict({"options": f"-csearch_path={schema}"})
        yield scoped.render_as_string(hide_password=False)
    finally:
        with admin.begin() as connection:
            connection.exec_driver_sql(f'DROP SCHEMA "{schema}" CASCADE')
        admin.dispose()
