"""Invite links: an operator makes one for a run or all runs; opening it makes a labeller named
after `participant`; a target of decisive answers on the run shows each participant their own
completion code once reached, which the operator can check; revoked, expired, used-up and
closed links (their run is over) are refused with a page or a 410 that says why; bad input is a
4xx naming the problem."""

from __future__ import annotations

import json
from datetime import timedelta
from typing import Any

from fastapi.testclient import TestClient
from server_helpers import OPERATOR, bearer, new_labeller, new_run, running_run_with_queries
from sqlalchemy import update
from sqlalchemy.orm import Session

from labelqueue import Invite, Invitee, find_labeller
from labelqueue.models import utcnow
from server.settings import Settings


def new_invite(client: TestClient, **body: Any) -> dict[str, Any]:
    response = client.post("/api/invites", json=body, headers=OPERATOR)
    assert response.status_code == 201, response.text
    invite: dict[str, Any] = response.json()
    return invite


def join(client: TestClient, code: str, **body: Any) -> Any:
    return client.post(f"/api/join/{code}", json=body)


def test_an_invite_link_makes_a_labeller_named_after_the_participant(
    client: TestClient, session: Session
) -> None:
    run = new_run(client)
    invite = new_invite(client, run_id=run["id"], max_uses=3, note="pilot")
    assert invite["url"].endswith(f"/join/{invite['code']}")
    assert invite["state"] == "open" and invite["uses"] == 0 and invite["run_id"] == run["id"]
    assert len(invite["code"]) >= 24

    page = client.get(f"/join/{invite['code']}?participant=P123")
    assert page.status_code == 200
    assert "forward" in page.text  # the run's instruction, on the page
    assert "Can’t tell" in page.text or "Can't tell" in page.text

    joined = join(client, invite["code"], participant="P123")
    assert joined.status_code == 201, joined.text
    body = joined.json()
    assert body["name"] == "P123" and body["run_id"] == run["id"]
    # The token works at once, for a labeller's calls.
    me = client.get("/api/label/progress", headers=bearer(body["token"])).json()
    assert {key: me[key] for key in ("labels", "target_answers", "completion_code", "run_id",
                                     "invited", "complete", "participant")} == {
        "labels": 0, "target_answers": None, "completion_code": None, "run_id": run["id"],
        "invited": True, "complete": False, "participant": "P123"}
    # The same participant again (another browser): the same labeller, no use of the link;
    # the first browser's token stops (one person, one labeller, one code).
    again = join(client, invite["code"], participant="P123")
    assert again.status_code == 201 and again.json()["rejoined"] is True
    assert (again.json()["name"], again.json()["labeller_id"]) == ("P123", body["labeller_id"])
    assert client.get("/api/label/next", headers=bearer(body["token"])).status_code == 401
    assert client.get("/api/label/progress",
                      headers=bearer(again.json()["token"])).status_code == 200
    nameless = join(client, invite["code"]).json()
    assert nameless["name"].startswith("guest-")
    other = join(client, invite["code"], participant="Q9").json()
    assert other["name"] == "Q9"
    with session.begin():
        invitees = session.query(Invitee).order_by(Invitee.labeller_id).all()
    assert [i.participant for i in invitees] == ["P123", None, "Q9"]
    # A used-up link still lets a participant who joined back in, and no one new.
    assert join(client, invite["code"], participant="P123").status_code == 201

    # Three uses, then it is used up: a clear page and a 410.
    used = join(client, invite["code"], participant="late")
    assert used.status_code == 410 and "used" in used.json()["detail"]
    assert find_labeller(session, name="late") is None
    page = client.get(f"/join/{invite['code']}")
    assert page.status_code == 410 and "used as many times" in page.text
    listed = client.get("/api/invites", headers=OPERATOR).json()
    assert [(i["uses"], i["state"]) for i in listed] == [(3, "used_up")]


def test_revoked_and_expired_links_are_refused_with_a_page_that_says_why(
    client: TestClient, session: Session
) -> None:
    revoked = new_invite(client)
    response = client.post(f"/api/invites/{revoked['id']}/revoke", headers=OPERATOR)
    assert response.status_code == 200 and response.json()["state"] == "revoked"
    refused = join(client, revoked["code"])
    assert refused.status_code == 410 and "withdrawn" in refused.json()["detail"]
    page = client.get(f"/join/{revoked['code']}")
    assert page.status_code == 410 and "withdrawn" in page.text
    assert "Traceback" not in page.text

    expired = new_invite(client)
    with session.begin():
        session.execute(update(Invite).where(Invite.id == expired["id"])
                        .values(expires_at=utcnow() - timedelta(seconds=1)))
    assert join(client, expired["code"]).status_code == 410
    page = client.get(f"/join/{expired['code']}")
    assert page.status_code == 410 and "expired" in page.text

    unknown = client.get("/join/not-a-code")
    assert unknown.status_code == 404 and "not known" in unknown.text
    assert join(client, "not-a-code").status_code == 404
    assert client.get("/join/" + "x" * 500).status_code == 404


def answer(client: TestClient, token: str, run_id: int, choice: str) -> None:
    nxt = client.get(f"/api/label/next?run_id={run_id}", headers=bearer(token)).json()
    body = {"choice": choice, "left_is_first": nxt["left_is_first"],
            "shown_at": "2026-01-01T00:00:00Z"}
    assert client.post(f"/api/label/{nxt['query_id']}", json=body,
                       headers=bearer(token)).status_code == 201


def test_a_target_of_decisive_answers_gives_each_participant_their_own_code(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, _ = running_run_with_queries(client, session, settings, n=8)
    invite = new_invite(client, run_id=run_id, target_answers=2, completion_code="C0DE-42",
                        redirect_url="https://study.test/end?pid={participant}&code={code}")
    tokens = [join(client, invite["code"], participant=who).json()["token"]
              for who in ("worker7", "worker8")]
    # Skips and can't-tells do not count: before, two skips gave everyone the one code.
    for choice in ("skip", "cant_tell"):
        answer(client, tokens[0], run_id, choice)
    progress = client.get("/api/label/progress", headers=bearer(tokens[0])).json()
    assert (progress["labels"], progress["counted"], progress["completion_code"]) == (2, 0, None)
    codes = []
    for token in tokens:
        for choice in ("left", "equal"):
            answer(client, token, run_id, choice)
        progress = client.get("/api/label/progress", headers=bearer(token)).json()
        assert (progress["counted"], progress["complete"], progress["why"]) == (2, True, "target")
        codes.append(progress["completion_code"])
        assert progress["redirect_url"] == (f"https://study.test/end?pid={progress['participant']}"
                                            f"&code={progress['completion_code']}")
    assert codes[0] != codes[1] and all(code.startswith("C0DE-42-") for code in codes)

    # The operator checks a code: whose it is, and how far they got.
    checked = client.post("/api/invites/verify", json={"code": codes[1]}, headers=OPERATOR)
    assert checked.status_code == 200, checked.text
    assert {key: checked.json()[key] for key in ("invite_id", "participant", "counted",
                                                 "target_answers", "complete", "why")} == {
        "invite_id": invite["id"], "participant": "worker8", "counted": 2,
        "target_answers": 2, "complete": True, "why": "target"}
    made_up = client.post("/api/invites/verify", json={"code": "C0DE-42-AAAA-BBBB-CCCC"},
                          headers=OPERATOR)
    assert made_up.status_code == 404 and "no participant" in made_up.json()["detail"]
    for odd in ("ÉÉÉÉ-ÉÉÉÉ-ÉÉÉÉ", codes[1].replace("-", "")[:-1] + "É"):
        unknown = client.post("/api/invites/verify", json={"code": odd}, headers=OPERATOR)
        assert unknown.status_code == 404, unknown.text
    assert client.post("/api/invites/verify", json={"code": codes[0]},
                       headers=bearer(tokens[0])).status_code == 403


def test_an_invite_closes_when_its_run_is_over_and_its_participants_get_their_code(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, _ = running_run_with_queries(client, session, settings, n=2)
    invite = new_invite(client, run_id=run_id, target_answers=10)
    token = join(client, invite["code"], participant="early").json()["token"]
    answer(client, token, run_id, "left")
    assert client.post(f"/api/runs/{run_id}/stop", headers=OPERATOR).status_code == 200
    [listed] = client.get("/api/invites", headers=OPERATOR).json()
    assert listed["state"] == "closed"
    late = join(client, invite["code"], participant="late")
    assert late.status_code == 410 and "ended" in late.json()["detail"]
    page = client.get(f"/join/{invite['code']}")
    assert page.status_code == 410 and "This study has ended" in page.text

    status = client.get("/api/label/status", headers=bearer(token)).json()
    assert status["waiting"] is None
    assert (status["progress"]["complete"], status["progress"]["why"]) == (True, "runs_over")
    assert status["progress"]["completion_code"]


def test_consent_is_asked_before_joining(client: TestClient) -> None:
    run = new_run(client)
    invite = new_invite(client, run_id=run["id"], consent_text="We keep your answers.")
    page = client.get(f"/join/{invite['code']}")
    assert page.status_code == 200 and "We keep your answers." in page.text
    refused = join(client, invite["code"])
    assert refused.status_code == 422 and "consent" in refused.json()["detail"]
    assert join(client, invite["code"], consent=True).status_code == 201


def test_bad_invite_requests_are_a_4xx_naming_the_problem(client: TestClient) -> None:
    token = new_labeller(client, "alice")
    run = new_run(client)
    cases = [
        ({"run_id": 0}, "run_id"),
        ({"run_id": 2**31}, "run_id"),
        ({"expires_in_days": 0}, "expires_in_days"),
        ({"expires_in_days": 1000}, "expires_in_days"),
        ({"max_uses": 0}, "max_uses"),
        ({"target_answers": -1}, "target_answers"),
        ({"completion_code": "has space", "target_answers": 3}, "completion_code"),
        ({"note": ""}, "note"),
        ({"redirect_url": "javascript:alert(1)"}, "redirect_url"),
        ({"redirect_url": "https://x.test/" + "a" * 2000}, "redirect_url"),
        ({"consent_text": ""}, "consent_text"),
        ({"colour": "red"}, "colour"),
    ]
    for body, field in cases:
        response = client.post("/api/invites", json=body, headers=OPERATOR)
        assert response.status_code == 422, (body, response.text)
        assert any(field in error["loc"] for error in response.json()["detail"]), body
    response = client.post("/api/invites", json={"run_id": 999}, headers=OPERATOR)
    assert response.status_code == 404 and "999" in response.json()["detail"]
    # Operators only; a labeller or no token is refused.
    assert client.post("/api/invites", json={}, headers=bearer(token)).status_code == 403
    assert client.post("/api/invites", json={}).status_code == 401
    assert client.get("/api/invites", headers=bearer(token)).status_code == 403
    assert client.post("/api/invites/5/revoke", headers=OPERATOR).status_code == 404
    assert client.post("/api/invites/0/revoke", headers=OPERATOR).status_code == 422

    invite = new_invite(client, run_id=run["id"])
    for participant in ("", "x" * 65, "a b", "<script>", "名前"):
        response = join(client, invite["code"], participant=participant)
        assert response.status_code == 422, (participant, response.text)
        assert any("participant" in error["loc"] for error in response.json()["detail"])
    response = client.post(f"/api/join/{invite['code']}", content=b"{not json",
                           headers={"Content-Type": "application/json"})
    assert response.status_code in (400, 422)
    assert client.post(f"/api/join/{invite['code']}", json={"extra": 1}).status_code == 422
    assert client.get("/api/label/progress").status_code == 401
    assert client.get("/api/label/progress", headers=OPERATOR).status_code == 403
    # The page's participant is checked by the API when the page joins; a bad one is a 200
    # page (whose join then says what is wrong), never a 500.
    assert client.get(f"/join/{invite['code']}?participant=%3Cscript%3E").status_code == 200


def test_a_spent_budget_ends_the_study_and_a_participant_labels_their_own_run_only(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, _ = running_run_with_queries(client, session, settings, n=4, budget=2)
    other = new_run(client)["id"]
    invite = new_invite(client, run_id=run_id, target_answers=5)
    ann = bearer(join(client, invite["code"], participant="ann").json()["token"])

    refused = client.get(f"/api/label/next?run_id={other}", headers=ann)
    assert refused.status_code == 403
    assert f"joined this study for run {run_id}" in refused.json()["detail"]
    for _ in range(2):  # the whole budget
        pair = client.get("/api/label/next", headers=ann).json()
        assert pair["run_id"] == run_id
        answered = client.post(f"/api/label/{pair['query_id']}", headers=ann, json={
            "choice": "left", "shown_at": utcnow().isoformat()})
        assert answered.status_code == 201, answered.text

    [listed] = client.get("/api/invites", headers=OPERATOR).json()
    assert listed["state"] == "closed"
    page = client.get(f"/join/{invite['code']}")
    assert page.status_code == 410 and "study has ended" in page.text
    late = join(client, invite["code"], participant="zed")
    assert late.status_code == 410 and "ended" in late.json()["detail"]
    assert find_labeller(session, name="zed") is None


def test_a_nul_character_in_stored_text_is_a_422_naming_the_field(
    client: TestClient, session: Session, settings: Settings
) -> None:
    """PostgreSQL's text holds no NUL: each free-text field refuses one at the door, rather
    than the database refusing it in words about numbers."""
    run_id, [query_id, _] = running_run_with_queries(client, session, settings)
    fields = ("note", "consent_text", "pause_message")
    for field in fields:
        refused = client.post("/api/invites", headers=OPERATOR,
                              json={"run_id": run_id, field: "a\u0000b"})
        assert refused.status_code == 422, (field, refused.text)
        [error] = refused.json()["detail"]
        assert error["loc"][-1] == field and "NUL" in error["msg"]
    for path, body, field in (
        ("/api/runs", {"task": "dmc:cheetah_run", "algo": "sac", "budget": 1,
                       "name": "a\u0000b"}, "name"),
        ("/api/labellers", {"name": "a\u0000b"}, "name"),
        ("/api/invites", {"redirect_url": "https://x.test/a\u0000b"}, "redirect_url"),
    ):
        refused = client.post(path, headers=OPERATOR, json=body)
        assert refused.status_code == 422 and refused.json()["detail"][0]["loc"][-1] == field
    ann = bearer(new_labeller(client, "ann"))
    pair = client.get("/api/label/next", headers=ann).json()
    flagged = client.post(f"/api/label/{pair['query_id']}", headers=ann, json={
        "choice": "skip", "flag": "other", "flag_note": "a\u0000b",
        "shown_at": utcnow().isoformat()})
    assert flagged.status_code == 422 and flagged.json()["detail"][0]["loc"][-1] == "flag_note"
    assert client.get("/api/invites", headers=OPERATOR).json() == []

    # A code no link can have is no link's: the page says so, and so does the API.
    page = client.get("/join/a%00b")
    assert page.status_code == 404 and "not known" in page.text
    assert client.post("/api/join/a%00b", json={}).status_code == 404
    document = client.get("/openapi.json").json()["components"]["schemas"]["InviteCreate"]
    assert all("x00" in json.dumps(document["properties"][field]) for field in fields)
