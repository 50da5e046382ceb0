"""Each server test gets a fresh migrated SQLite database, built by the app factory."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from server_helpers import OPERATOR_TOKEN
from sqlalchemy.orm import Session

from labelqueue import make_engine, session_factory
from server.app import create_app
from server.settings import Settings


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    data = tmp_path / "data"
    return Settings(
        database_url=f"sqlite:///{data / 'queue.db'}",
        data_dir=data,
        operator_token=OPERATOR_TOKEN,
        secret_key="test-secret-key-0123456789",
        # Scripted labellers lease at full speed; the tests of the rate limits set their own.
        lease_per_s=1000.0, lease_burst=1000,
    )


@pytest.fixture
def client(settings: Settings) -> Iterator[TestClient]:
    with TestClient(create_app(settings)) as client:
        yield client


@pytest.fixture
def session(client: TestClient, settings: Settings) -> Iterator[Session]:
    """A direct session on the same database, for setting up what a worker would do."""
    engine = make_engine(settings.database_url)
    with session_factory(engine)() as session:
        yield session
    engine.dispose()
