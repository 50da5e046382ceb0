"""The scripted teacher is the labeller named `scripted-teacher`, which workers make and answer
as: no operator may give a person that name, revoke it, rename it or give it a token, through
the API or the command line."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from server_helpers import OPERATOR, new_labeller, snapshot
from sqlalchemy.orm import Session

from labelqueue import create_labeller
from labelqueue.models import SCRIPTED_TEACHER
from sepoa.cli import main
from server.settings import Settings


def test_no_person_takes_the_scripted_teachers_name(client: TestClient, session: Session) -> None:
    made = client.post("/api/labellers", json={"name": SCRIPTED_TEACHER}, headers=OPERATOR)
    assert made.status_code == 409 and "scripted teacher" in made.json()["detail"]
    new_labeller(client, "alice")
    renamed = client.patch("/api/labellers/1", json={"name": SCRIPTED_TEACHER}, headers=OPERATOR)
    assert renamed.status_code == 409 and SCRIPTED_TEACHER in renamed.json()["detail"]
    assert [lab["name"] for lab in client.get("/api/labellers", headers=OPERATOR).json()] == [
        "alice"]


def test_the_scripted_teacher_is_not_revoked_renamed_or_given_a_token(
    client: TestClient, session: Session
) -> None:
    teacher, _ = create_labeller(session, name=SCRIPTED_TEACHER)  # as a worker makes it
    before = snapshot(session)
    for body, why in (({"active": False}, "wait for answers"), ({"name": "bob"}, "renamed")):
        refused = client.patch(f"/api/labellers/{teacher.id}", json=body, headers=OPERATOR)
        assert refused.status_code == 409, refused.text
        assert why in refused.json()["detail"]
    token = client.post(f"/api/labellers/{teacher.id}/token", headers=OPERATOR)
    assert token.status_code == 409 and "no person" in token.json()["detail"]
    assert snapshot(session) == before
    [row] = client.get("/api/labellers", headers=OPERATOR).json()
    assert (row["name"], row["active"], row["scripted"]) == (SCRIPTED_TEACHER, True, True)


def test_the_command_line_refuses_the_same(
    session: Session, settings: Settings, capsys: pytest.CaptureFixture[str]
) -> None:
    data = ["--data-dir", str(settings.data_dir)]
    assert main(["labeller", "create", SCRIPTED_TEACHER, *data]) != 0
    assert "scripted teacher" in capsys.readouterr().err
    create_labeller(session, name=SCRIPTED_TEACHER)
    before = snapshot(session)
    for action in ("revoke", "token"):
        assert main(["labeller", action, SCRIPTED_TEACHER, *data]) != 0
        assert "scripted teacher" in capsys.readouterr().err
    assert snapshot(session) == before
