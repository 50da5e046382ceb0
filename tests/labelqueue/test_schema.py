"""The schema comes from the migrations and matches the models; SQLite is set up for concurrency."""

from __future__ import annotations

import os
import sqlite3
from contextlib import closing
from pathlib import Path

import pytest
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import CheckConstraint, Engine, event, inspect

from labelqueue import make_engine, migrate
from labelqueue.db import alembic_config
from labelqueue.models import Base


def test_migrations_create_exactly_the_models_schema(engine: Engine) -> None:
    with engine.connect() as connection:
        context = MigrationContext.configure(connection, opts={"compare_type": True})
        assert compare_metadata(context, Base.metadata) == []


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


def test_sqlite_transactions_take_the_write_lock_when_they_begin(tmp_path: Path) -> None:
    engine = make_engine(f"sqlite:///{tmp_path / 'queue.db'}")
    statements: list[str] = []

    @event.listens_for(engine, "before_cursor_execute")
    def record(_conn: object, _cursor: object, statement: str, *_args: object) -> None:
        statements.append(statement)

    with engine.begin() as connection:
        connection.exec_driver_sql("SELECT 1")
    assert statements == ["BEGIN IMMEDIATE", "SELECT 1"]
    engine.dispose()


def test_postgresql_variants_are_enabled() -> None:
    """Skipped, as a visible note, when the PostgreSQL variants of these tests do not run."""
    if not os.environ.get("SEPOA_TEST_POSTGRES_URL"):
        pytest.skip("queue tests ran on SQLite only: set SEPOA_TEST_POSTGRES_URL for PostgreSQL")
