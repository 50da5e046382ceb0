"""Each test gets a fresh, migrated queue database.

SQLite always. PostgreSQL too when SEPOA_TEST_POSTGRES_URL names a database
(`postgresql+psycopg://user:password@localhost/sepoa_test`): every test then also runs there,
in a schema of its own that is dropped afterwards. Without the variable only SQLite runs, and
one test (test_schema.py::test_postgresql_variants_are_enabled) says so by being skipped.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from database_helpers import BACKENDS, postgres_schema
from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from labelqueue import make_engine, migrate, session_factory


@pytest.fixture(params=BACKENDS)
def url(request: pytest.FixtureRequest, tmp_path: Any) -> Iterator[str]:
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'data' / 'queue.db'}"
        return
    with postgres_schema() as url:
        yield url


@pytest.fixture
def engine(url: str) -> Iterator[Engine]:
    migrate(url)
    engine = make_engine(url)
    yield engine
    engine.dispose()


@pytest.fixture
def sessions(engine: Engine) -> sessionmaker[Session]:
    return session_factory(engine)


@pytest.fixture
def session(sessions: sessionmaker[Session]) -> Iterator[Session]:
    with sessions() as session:
        yield session
