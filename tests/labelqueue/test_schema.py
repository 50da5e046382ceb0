"""The schema comes from the migrations and matches the models, whose query columns are the
declared query fields; SQLite is set up for concurrency."""

from __future__ import annotations

import argparse
import os
import re
import sqlite3
import threading
import time
from contextlib import closing
from pathlib import Path
from typing import Any

import pytest
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import (
    JSON,
    Boolean,
    CheckConstraint,
    Engine,
    Enum,
    Float,
    Integer,
    String,
    func,
    inspect,
    select,
    update,
)
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session

from labelqueue import Labeller, create_labeller, make_engine, migrate, reading
from labelqueue.models import QUERIES, Base
from labelqueue.schema import MIGRATIONS_DIR, alembic_config, check_database
from runvocab.answers import Answer
from runvocab.query_fields import QUERY_FIELD_NAMES, QUERY_FIELDS, FieldType

# The queue's own bookkeeping of a query, which the worker never pushes.
QUEUE_COLUMNS = {"id", "run_id", "label_count", "status", "lease_holder", "lease_expires_at",
                 "leased_at", "created_at", "practice"}
SQL_TYPES: dict[FieldType, type] = {"int": Integer, "float": Float, "bool": Boolean,
                                    "str": String, "floats": JSON, "answer": Enum, "clip": String}


def test_migrations_create_exactly_the_models_schema(engine: Engine) -> None:
    with engine.connect() as connection:
        context = MigrationContext.configure(connection, opts={"compare_type": True})
        assert compare_metadata(context, Base.metadata) == []


def test_the_queries_table_holds_each_declared_query_field_as_declared() -> None:
    # Adding a query field: `runvocab.query_fields`, a `labelqueue.models.Query` column and a
    # migration (the test above keeps the migrations and the models equal).
    assert set(QUERIES.c.keys()) - QUEUE_COLUMNS == set(QUERY_FIELD_NAMES)
    for field in QUERY_FIELDS:
        column = QUERIES.c[field.name]
        assert type(column.type) is SQL_TYPES[field.type], field.name
        assert column.nullable == field.nullable, field.name
        if field.default is not None:
            assert column.default is not None, field.name
            assert column.default.arg == field.default, field.name  # type: ignore[attr-defined]
        if field.type == "answer":
            assert column.type.enum_class is Answer, field.name  # type: ignore[attr-defined]


def test_migrations_create_the_models_check_constraints(engine: Engine) -> None:
    # Autogenerate does not compare CHECK constraints; the enum columns rely on them.
    inspector = inspect(engine)
    for table in Base.metadata.sorted_tables:
        stored = {c["name"] for c in inspector.get_check_constraints(table.name)}
        declared = {c.name for c in table.constraints if isinstance(c, CheckConstraint)}
        assert stored == declared, table.name


def test_database_is_at_the_single_head_and_migrate_is_idempotent(url: str, engine: Engine) -> None:
    script = ScriptDirectory.from_config(alembic_config(url))
    assert len(script.get_heads()) == 1
    migrate(url)  # a second server start-up
    with engine.connect() as connection:
        assert MigrationContext.configure(connection).get_current_heads() == tuple(
            script.get_heads()
        )


def test_downgrade_removes_the_schema_and_upgrade_restores_it(url: str, engine: Engine) -> None:
    tables = set(inspect(engine).get_table_names())
    assert {"labellers", "runs", "workers", "queries", "labels", "metrics"} <= tables
    command.downgrade(alembic_config(url), "base")
    assert set(inspect(engine).get_table_names()) <= {"alembic_version"}
    migrate(url)
    assert set(inspect(engine).get_table_names()) == tables


def test_sqlite_uses_wal_busy_timeout_and_foreign_keys(tmp_path: Path) -> None:
    path = tmp_path / "new" / "queue.db"  # the folder does not exist yet
    migrate(f"sqlite:///{path}")
    engine = make_engine(f"sqlite:///{path}")
    with engine.connect() as connection:

        def pragma(name: str) -> object:
            return connection.exec_driver_sql(f"PRAGMA {name}").scalar()

        assert pragma("journal_mode") == "wal"
        assert pragma("busy_timeout") == 30_000
        assert pragma("foreign_keys") == 1
    engine.dispose()
    # WAL is a property of the file: any other client (sqlite3 CLI, a backup) sees it too.
    with closing(sqlite3.connect(path)) as plain:
        assert plain.execute("PRAGMA journal_mode").fetchone() == ("wal",)


def other_writer(path: Path) -> sqlite3.Connection:
    """A second client of the file (as another process would be) that never waits for a lock."""
    return sqlite3.connect(path, timeout=0, isolation_level=None, check_same_thread=False)


def test_sqlite_transactions_take_the_write_lock_when_they_begin(tmp_path: Path) -> None:
    migrate(f"sqlite:///{tmp_path / 'queue.db'}")
    engine = make_engine(f"sqlite:///{tmp_path / 'queue.db'}")
    with closing(other_writer(tmp_path / "queue.db")) as other:
        with engine.begin():  # nothing executed yet: the lock is taken at BEGIN
            with pytest.raises(sqlite3.OperationalError, match="database is locked"):
                other.execute("BEGIN IMMEDIATE")
        other.execute("BEGIN IMMEDIATE")  # and given back at COMMIT
        other.execute("COMMIT")
    engine.dispose()


def test_sqlite_reads_take_no_lock_and_refuse_writes(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'queue.db'}"
    migrate(url)
    engine = make_engine(url)
    with closing(other_writer(tmp_path / "queue.db")) as other, Session(engine) as session:
        with reading(session):
            assert session.scalar(select(func.count()).select_from(Labeller)) == 0
            # A writer elsewhere goes ahead at once; this read keeps its snapshot.
            other.execute("BEGIN IMMEDIATE")
            other.execute(
                "INSERT INTO labellers (name, role, token_hash, active, created_at) "
                "VALUES ('a', 'labeller', '', 1, '2026-01-01 00:00:00')"
            )
            other.execute("COMMIT")
            assert session.scalar(select(func.count()).select_from(Labeller)) == 0
        with reading(session), pytest.raises(OperationalError, match="readonly"):
            session.execute(update(Labeller).values(name="b"))
        with reading(session):
            assert session.scalars(select(Labeller.name)).all() == ["a"]
        create_labeller(session, name="c")  # the same connection writes again afterwards
    engine.dispose()


def test_a_writer_waits_for_another_process_then_goes_ahead(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'queue.db'}"
    migrate(url)
    engine = make_engine(url)
    with closing(other_writer(tmp_path / "queue.db")) as other:
        other.execute("BEGIN IMMEDIATE")
        threading.Timer(0.3, lambda: other.execute("COMMIT")).start()
        start = time.monotonic()
        with Session(engine) as session:
            create_labeller(session, name="after")
        assert time.monotonic() - start >= 0.25
    engine.dispose()


def test_postgresql_variants_are_enabled() -> None:
    """Skipped, as a visible note, when the PostgreSQL variants of these tests do not run."""
    if not os.environ.get("SEPOA_TEST_POSTGRES_URL"):
        pytest.skip("queue tests ran on SQLite only: set SEPOA_TEST_POSTGRES_URL for PostgreSQL")


def test_the_entry_test_migration_goes_down_and_up(url: str, engine: Engine) -> None:
    def columns(table: str) -> set[str]:
        return {c["name"] for c in inspect(engine).get_columns(table)}

    entry = {("invites", "entry_pass"), ("invitees", "entry_passed"),
             ("invitees", "entry_correct")}
    assert all(name in columns(table) for table, name in entry)
    command.downgrade(alembic_config(url), "0017")
    engine.dispose()  # the inspector's cached schema (PostgreSQL) with it
    assert not any(name in columns(table) for table, name in entry)
    assert "wait_limit_s" in columns("invites")  # 0016's columns stay
    migrate(url)
    engine.dispose()
    assert all(name in columns(table) for table, name in entry)


def test_the_queues_tables_are_never_written_into_a_file_that_is_no_queue(
        tmp_path: Path) -> None:
    """Migrating (as a server or a worker starting does) an SQLite database of something else
    wrote the queue's tables into it; a file that is no database was called damaged."""
    other = tmp_path / "notes.db"
    with closing(sqlite3.connect(other)) as connection:
        connection.execute("CREATE TABLE notes (text TEXT)")
        connection.commit()
    text = tmp_path / "notes.txt"
    text.write_text("not a database, and long enough to have a header's worth of bytes\n")
    for path, said in ((other, "is an SQLite database but not a sepoa queue (no queue tables)"),
                       (text, "is not an SQLite database")):
        before = path.read_bytes()
        for check in (migrate, lambda url: check_database(url, writable=True)):
            with pytest.raises(ValueError, match=re.escape(f"{path} {said}")):
                check(f"sqlite:///{path}")
        assert path.read_bytes() == before
    empty = tmp_path / "empty.db"  # no tables yet: a queue is made in it
    empty.touch()
    migrate(f"sqlite:///{empty}")
    check_database(f"sqlite:///{empty}", writable=True)


def test_alembic_on_its_own_finds_the_queue_as_the_server_does(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`alembic current` (and upgrade) used data/queue.db whatever SEPOA_DATA_DIR said; `-x url=`
    still wins."""
    from alembic.config import Config

    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("SEPOA_DATABASE_URL", raising=False)
    monkeypatch.delenv("SEPOA_DATABASE_URL_FILE", raising=False)
    monkeypatch.setenv("SEPOA_DATA_DIR", str(tmp_path / "study"))
    config = Config()  # as alembic.ini makes it, without its logging
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    command.current(config)
    assert (tmp_path / "study" / "queue.db").exists() and not (tmp_path / "data").exists()
    given = tmp_path / "given.db"
    config = Config(cmd_opts=argparse.Namespace(x=[f"url=sqlite:///{given}"]))
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    command.current(config)
    assert given.exists()


def test_a_live_queues_file_is_read_only_through_sqlite(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Checking a queue's file beside the process's open connections (a server's restart, a
    worker's retry) must not open it outside SQLite: closing that descriptor dropped every POSIX
    lock the process held on the file, and the queue's first page was overwritten under load."""
    import builtins

    url = f"sqlite:///{tmp_path / 'queue.db'}"
    migrate(url)
    engine = make_engine(url)
    opened: list[str] = []
    real_open = builtins.open

    def spying_open(file: Any, *args: Any, **kwargs: Any) -> Any:
        opened.append(os.fspath(file))
        return real_open(file, *args, **kwargs)

    with engine.connect() as connection:
        connection.exec_driver_sql("SELECT count(*) FROM labellers").all()
        connection.rollback()  # open, as a server's pooled connections are, in no transaction
        monkeypatch.setattr(builtins, "open", spying_open)
        migrate(url)
        check_database(url, writable=True)
        monkeypatch.setattr(builtins, "open", real_open)
    engine.dispose()
    assert not [path for path in opened if path.startswith(str(tmp_path / "queue.db"))], opened
