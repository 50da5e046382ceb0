"""An export over REST checks the database first: a damaged SQLite file, which reads back
fewer labels than it holds without an error, is refused with a 503 that says so."""

from __future__ import annotations

from pathlib import Path

from database_helpers import damaged_copies
from fastapi.testclient import TestClient
from server_helpers import OPERATOR, OPERATOR_TOKEN

from labelqueue import sqlite_url
from server.app import create_app
from server.settings import Settings


def _app(folder: Path) -> TestClient:
    return TestClient(create_app(Settings(database_url=sqlite_url(folder), data_dir=folder,
                                          operator_token=OPERATOR_TOKEN,
                                          secret_key="damaged-export-secret-0123")))


def test_a_damaged_database_is_not_exported(tmp_path: Path) -> None:
    copies = damaged_copies(tmp_path)
    with _app(copies["rows"]) as client:
        refused = client.get("/api/export", headers=OPERATOR)
        assert refused.status_code == 503, refused.text[:200]
        assert "is damaged (PRAGMA quick_check:" in refused.json()["detail"]
    with _app(tmp_path / "sound") as client:
        sound = client.get("/api/export", headers=OPERATOR)
        assert sound.status_code == 200 and len(sound.text.splitlines()) == 233
