"""Paying a study: the participants list (JSON, CSV) and many codes checked at once; one
person, one labeller; joining and leasing too fast is a 429 with Retry-After; a labeller holds
two leases at most; nobody waits unpaid ("nothing left to label" after the invite's wait);
a redirect URL never fills in its host."""

from __future__ import annotations

import csv
import io
from datetime import timedelta
from typing import Any

from fastapi.testclient import TestClient
from server_helpers import OPERATOR, bearer, running_run_with_queries
from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from labelqueue import Invitee, LabellerPause, Query, claim_run
from labelqueue.models import utcnow
from server.app import create_app
from server.settings import Settings


def invite(client: TestClient, **body: Any) -> dict[str, Any]:
    response = client.post("/api/invites", json=body, headers=OPERATOR)
    assert response.status_code == 201, response.text
    made: dict[str, Any] = response.json()
    return made


def joined(client: TestClient, code: str, participant: str | None = None) -> dict[str, Any]:
    response = client.post(f"/api/join/{code}",
                           json={"participant": participant} if participant else {})
    assert response.status_code == 201, response.text
    body: dict[str, Any] = response.json()
    return body


def answer(client: TestClient, token: str, choice: str = "left") -> int | None:
    shown = client.get("/api/label/next", headers=bearer(token))
    if shown.status_code == 204:
        return None
    query = shown.json()
    stored = client.post(f"/api/label/{query['query_id']}", headers=bearer(token), json={
        "choice": choice, "left_is_first": query["left_is_first"],
        "shown_at": utcnow().isoformat()})
    assert stored.status_code == 201, stored.text
    return int(query["query_id"])


def test_the_participants_list_pays_exactly_who_earned_a_code(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, _ = running_run_with_queries(client, session, settings, n=6)
    study = invite(client, run_id=run_id, target_answers=2, completion_code="STUDY")
    ann = joined(client, study["code"], "ann")
    bob = joined(client, study["code"], "bob")
    answer(client, ann["token"])
    answer(client, ann["token"], "equal")  # ann reaches the target
    answer(client, bob["token"], "skip")   # bob does not: a skip counts for nothing

    listed = client.get(f"/api/invites/{study['id']}/participants", headers=OPERATOR)
    assert listed.status_code == 200, listed.text
    rows = {row["participant"]: row for row in listed.json()}
    assert (rows["ann"]["decisive"], rows["ann"]["equal"], rows["ann"]["counted"]) == (1, 1, 2)
    assert rows["ann"]["code_valid"] and rows["ann"]["why"] == "target"
    assert (rows["bob"]["skips"], rows["bob"]["code_valid"]) == (1, False)
    assert rows["ann"]["completion_code"].startswith("STUDY-")

    text = client.get(f"/api/invites/{study['id']}/participants?format=csv",
                      headers=OPERATOR)
    assert text.headers["content-type"].startswith("text/csv")
    paid = [r["participant"] for r in csv.DictReader(io.StringIO(text.text))
            if r["code_valid"] == "True"]
    assert paid == ["ann"]

    codes = [rows["ann"]["completion_code"], " " + rows["bob"]["completion_code"].lower(),
             "", "STUDY-AAAA-BBBB-CCCC"]
    checked = client.post("/api/invites/verify-codes", headers=OPERATOR, json={"codes": codes})
    assert checked.status_code == 200, checked.text
    assert [(c["valid"], c["participant"], c["why"]) for c in checked.json()] == [
        (True, "ann", "target"), (False, "bob", "not_complete"), (False, None, "unknown")]
    # Operators only; an unknown invite or a bad format is a 4xx naming it.
    assert client.get(f"/api/invites/{study['id']}/participants",
                      headers=bearer(ann["token"])).status_code == 403
    assert client.get("/api/invites/999/participants", headers=OPERATOR).status_code == 404
    bad = client.get(f"/api/invites/{study['id']}/participants?format=xls", headers=OPERATOR)
    assert bad.status_code == 422 and "format" in bad.text
    assert client.post("/api/invites/verify-codes", headers=OPERATOR,
                       json={"codes": []}).status_code == 422
    page = client.get(f"/invites/{study['id']}/participants")
    assert page.status_code == 200 and "participants.js" in page.text


def test_a_participant_rejoining_keeps_one_labeller_and_one_code(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, _ = running_run_with_queries(client, session, settings, n=4)
    study = invite(client, run_id=run_id, max_uses=2, target_answers=1)
    first = joined(client, study["code"], "P1")
    answer(client, first["token"])
    for _ in range(5):  # re-joining hammers no slot away
        again = joined(client, study["code"], "P1")
        assert again["labeller_id"] == first["labeller_id"] and again["rejoined"]
    progress = client.get("/api/label/progress", headers=bearer(again["token"])).json()
    assert (progress["counted"], progress["complete"]) == (1, True)
    listed = client.get("/api/invites", headers=OPERATOR).json()
    assert [i["uses"] for i in listed] == [1]
    assert len(client.get(f"/api/invites/{study['id']}/participants",
                          headers=OPERATOR).json()) == 1


def test_joining_and_leasing_too_fast_is_a_429_with_retry_after(
    settings: Settings, tmp_path: Any
) -> None:
    tight = settings.model_copy(update={"join_burst": 3, "join_per_s": 0.01,
                                        "lease_burst": 4, "lease_per_s": 0.01})
    with TestClient(create_app(tight)) as client:
        code = invite(client)["code"]
        statuses = [client.post(f"/api/join/{code}", json={}).status_code for _ in range(5)]
        assert statuses == [201, 201, 201, 429, 429]
        refused = client.post(f"/api/join/{code}", json={})
        assert int(refused.headers["retry-after"]) >= 1 and "too many" in refused.json()["detail"]
        other = invite(client)["code"]  # another link has its own bucket
        joined_token = client.post(f"/api/join/{other}", json={}).json()["token"]
        token = bearer(joined_token)
        leases = [client.get("/api/label/next", headers=token).status_code for _ in range(6)]
        assert leases == [204] * 4 + [429] * 2
        assert int(client.get("/api/label/next", headers=token).headers["retry-after"]) >= 1


def test_a_labeller_holds_two_leases_at_most(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, ids = running_run_with_queries(client, session, settings, n=8)
    token = bearer(joined(client, invite(client, run_id=run_id)["code"])["token"])
    for ahead in [None, *ids, *ids]:  # a script asking ahead of every pair it knows
        client.get("/api/label/next", headers=token,
                   params={} if ahead is None else {"ahead_of": ahead})
        held = session.scalar(select(func.count()).select_from(Query).where(
            Query.lease_holder.is_not(None), Query.lease_expires_at > utcnow()))
        session.commit()
        assert held is not None and held <= 2


def test_nobody_waits_unpaid(client: TestClient, session: Session, settings: Settings) -> None:
    run_id, _ = running_run_with_queries(client, session, settings, n=1)
    study = invite(client, run_id=run_id, target_answers=5, wait_limit_s=120)
    ann, bob = joined(client, study["code"], "ann"), joined(client, study["code"], "bob")
    assert answer(client, ann["token"]) is not None
    assert answer(client, ann["token"]) is None  # nothing left for her
    status = client.get("/api/label/status", headers=bearer(ann["token"])).json()
    assert not status["progress"]["complete"] and status["waiting"] is not None

    def waited(who: dict[str, Any], seconds: float, asked_ago: float) -> None:
        with session.begin():
            session.execute(update(Invitee).where(Invitee.labeller_id == who["labeller_id"])
                            .values(waiting_since=utcnow() - timedelta(seconds=seconds),
                                    asked_at=utcnow() - timedelta(seconds=asked_ago)))

    # Asked the whole time, for longer than the invite's limit: done, with her code.
    waited(ann, 130, 0)
    status = client.get("/api/label/status", headers=bearer(ann["token"])).json()
    progress = status["progress"]
    assert (progress["complete"], progress["why"]) == (True, "nothing_left")
    assert progress["completion_code"] and status["waiting"] is None
    # Bob left ten minutes ago and came back: his wait starts over, no code for the absence.
    assert answer(client, bob["token"]) is None
    waited(bob, 700, 600)
    assert answer(client, bob["token"]) is None  # asking again after the gap: a new wait
    status = client.get("/api/label/status", headers=bearer(bob["token"])).json()
    assert not status["progress"]["complete"]
    # Her code stays valid for the operator.
    rows = client.get(f"/api/invites/{study['id']}/participants", headers=OPERATOR).json()
    assert [(r["participant"], r["code_valid"], r["why"]) for r in rows] == [
        ("ann", True, "nothing_left"), ("bob", False, None)]


def test_a_redirect_url_fills_in_no_host(client: TestClient) -> None:
    for url in ("https://{participant}.example.org/done", "https://example.org:{code}/x"):
        refused = client.post("/api/invites", headers=OPERATOR, json={"redirect_url": url})
        assert refused.status_code == 422, url
        assert refused.json()["detail"][0]["loc"] == ["body", "redirect_url"], url
    assert client.post("/api/invites", headers=OPERATOR, json={
        "redirect_url": "https://example.org/done?pid={participant}&cc={code}"}).status_code == 201


def test_participants_see_no_operator_link_and_may_decline_consent(client: TestClient) -> None:
    made = invite(client, consent_text="We record your answers.")
    for path in ("/label", f"/join/{made['code']}"):
        page = client.get(path).text
        assert 'href="/runs"' not in page and 'href="/labels"' not in page
    assert 'href="/runs"' in client.get("/runs").text
    join_page = client.get(f"/join/{made['code']}").text
    assert 'id="consent-decline"' in join_page and "nothing was recorded" in join_page


def test_a_completion_found_with_a_code_stays_earned_whatever_the_run_does_later(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, _ = running_run_with_queries(client, session, settings, n=6)
    study = invite(client, run_id=run_id, target_answers=5)
    ann, bob, cat = (joined(client, study["code"], who) for who in ("ann", "bob", "cat"))
    answer(client, ann["token"])

    def progress(who: dict[str, Any]) -> dict[str, Any]:
        body: dict[str, Any] = client.get("/api/label/progress",
                                          headers=bearer(who["token"])).json()
        return body

    def checked(*codes: str) -> list[tuple[bool, str]]:
        response = client.post("/api/invites/verify-codes", headers=OPERATOR,
                               json={"codes": list(codes)})
        return [(c["valid"], c["why"]) for c in response.json()]

    # The operator stops the run: ann's page shows her code (bob looks at nothing meanwhile).
    for stop in ("", "?force=true"):
        assert client.post(f"/api/runs/{run_id}/stop{stop}", headers=OPERATOR).is_success
    shown = progress(ann)
    assert (shown["complete"], shown["why"], shown["counted"]) == (True, "runs_over", 1)
    code = shown["completion_code"]
    # The run is requeued and trains again: her code stays earned, and she may label more.
    assert client.post(f"/api/runs/{run_id}/requeue", headers=OPERATOR).is_success
    assert claim_run(session, worker_id="worker-1") is not None
    assert answer(client, ann["token"]) is not None
    again = progress(ann)
    assert (again["complete"], again["why"], again["counted"]) == (True, "runs_over", 2)
    assert again["completion_code"] == code
    assert checked(code) == [(True, "runs_over")]
    assert not progress(bob)["complete"]  # never found complete: nothing kept for him

    # Check pairs pause cat: her code is shown; the operator lifts the pause; it stays earned.
    with session.begin():
        session.add(LabellerPause(run_id=run_id, labeller_id=cat["labeller_id"],
                                  gold_answers=4, gold_correct=1))
    paused = progress(cat)
    assert (paused["complete"], paused["why"]) == (True, "paused")
    assert client.delete(f"/api/quality/runs/{run_id}/pauses/{cat['labeller_id']}",
                         headers=OPERATOR).status_code == 204
    assert checked(paused["completion_code"], code) == [(True, "paused"), (True, "runs_over")]
    rows = client.get(f"/api/invites/{study['id']}/participants", headers=OPERATOR).json()
    assert [(r["participant"], r["complete"], r["why"], r["code_valid"], r["counted"])
            for r in rows] == [("ann", True, "runs_over", True, 2),
                               ("bob", False, None, False, 0),
                               ("cat", True, "paused", True, 0)]


def test_codes_checked_for_one_study_tell_another_studys_apart(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, _ = running_run_with_queries(client, session, settings, n=4)
    mine, other = (invite(client, run_id=run_id, target_answers=1) for _ in range(2))
    ann, zed = joined(client, mine["code"], "ann"), joined(client, other["code"], "zed")
    codes = []
    for who in (ann, zed):
        answer(client, who["token"])
        codes.append(client.get("/api/label/progress",
                                headers=bearer(who["token"])).json()["completion_code"])

    def checked(**scope: Any) -> list[tuple[bool, str, int | None]]:
        response = client.post("/api/invites/verify-codes", headers=OPERATOR,
                               json={"codes": [*codes, "AAAA-BBBB-CCCC"], **scope})
        assert response.status_code == 200, response.text
        return [(c["valid"], c["why"], c["invite_id"]) for c in response.json()]

    # Checked for ann's study, zed's earned code is another study's: not to be paid there.
    assert checked(invite_id=mine["id"]) == [
        (True, "target", mine["id"]), (False, "other_study", other["id"]),
        (False, "unknown", None)]
    assert checked() == [(True, "target", mine["id"]), (True, "target", other["id"]),
                         (False, "unknown", None)]
    missing = client.post("/api/invites/verify-codes", headers=OPERATOR,
                          json={"codes": codes, "invite_id": 999})
    assert missing.status_code == 404 and "invite 999" in missing.json()["detail"]


def test_checking_one_code_says_whether_to_pay_as_the_list_does(
    client: TestClient, session: Session, settings: Settings
) -> None:
    """A code whose owner reached the target but was deactivated (their work rejected) is not to
    be paid: checked alone, it says so, as the participants list and a batch check do."""
    run_id, _ = running_run_with_queries(client, session, settings, n=4)
    study = invite(client, run_id=run_id, target_answers=1)
    ann, bob = joined(client, study["code"], "ann"), joined(client, study["code"], "bob")
    for who in (ann, bob):
        answer(client, who["token"])
    codes = {who["name"]: client.get("/api/label/progress", headers=bearer(who["token"]))
             .json()["completion_code"] for who in (ann, bob)}
    assert client.patch(f"/api/labellers/{bob['labeller_id']}", headers=OPERATOR,
                        json={"active": False}).status_code == 200
    listed = {row["participant"]: row["code_valid"] for row in client.get(
        f"/api/invites/{study['id']}/participants", headers=OPERATOR).json()}
    assert listed == {"ann": True, "bob": False}
    for name, pay in listed.items():
        checked = client.post("/api/invites/verify", json={"code": codes[name]},
                              headers=OPERATOR).json()
        assert (checked["complete"], checked["why"], checked["earned"]) == (True, "target", pay)


def test_a_code_handed_in_twice_is_paid_once(
    client: TestClient, session: Session, settings: Settings
) -> None:
    """Two submissions of one participant's code (shared, or written differently) pay them
    once: the repeat says so and is not valid; the first stays valid."""
    run_id, _ = running_run_with_queries(client, session, settings, n=4)
    study = invite(client, run_id=run_id, target_answers=1)
    ann = joined(client, study["code"], "ann")
    answer(client, ann["token"])
    code = client.get("/api/label/progress", headers=bearer(ann["token"])).json()[
        "completion_code"]
    retyped = " ".join(code.lower().split("-"))
    response = client.post("/api/invites/verify-codes", headers=OPERATOR,
                           json={"codes": [code, retyped, "AAAA-BBBB-CCCC", code]})
    assert response.status_code == 200, response.text
    assert [(c["valid"], c["repeat"], c["why"]) for c in response.json()] == [
        (True, False, "target"), (False, True, "target"), (False, False, "unknown"),
        (False, True, "target")]
