"""An invite's entry test: pass n of the run's m practice pairs or be let go, with a message, no
more pairs (403), no code, nothing spent of the budget, and "failed the entry test, not to be
paid" in the participants list and its CSV."""

from __future__ import annotations

import csv
import io
from typing import Any

from fastapi.testclient import TestClient
from server_helpers import OPERATOR, bearer, new_run, query_spec, running_run_with_queries
from sqlalchemy.orm import Session

from labelqueue import Run, claim_run, push_queries, reading, set_clips
from labelqueue.models import utcnow
from server.settings import Settings

PRACTICE = 3


def practice_run(client: TestClient, session: Session, settings: Settings,
                 practice: int = PRACTICE) -> int:
    """A human-taught run with `practice` practice pairs (its first gold pairs) and six ordinary
    pairs, all rendered; the first segment is always the better one."""
    run_id = int(new_run(client, config={"feedback.practice_pairs": practice})["id"])
    assert claim_run(session, worker_id="w") is not None
    specs = [query_spec(i) | ({"gold": True} if i < practice else {}) for i in range(6 + practice)]
    for query_id in push_queries(session, run_id=run_id, queries=specs):
        keys = [f"run{run_id}/q{query_id}-{side}.mp4" for side in ("a", "b")]
        for key in keys:
            (settings.clips_root / key).parent.mkdir(parents=True, exist_ok=True)
            (settings.clips_root / key).write_bytes(b"mp4 " * 50)
        set_clips(session, query_id=query_id, first_clip=keys[0], second_clip=keys[1])
    return run_id


def join(client: TestClient, code: str, participant: str) -> str:
    response = client.post(f"/api/join/{code}", json={"participant": participant})
    assert response.status_code == 201, response.text
    return str(response.json()["token"])


def next_pair(client: TestClient, token: str) -> dict[str, Any]:
    shown = client.get("/api/label/next", headers=bearer(token))
    assert shown.status_code == 200, shown.text
    query: dict[str, Any] = shown.json()
    return query


def give(client: TestClient, token: str, query: dict[str, Any], how: str) -> dict[str, Any]:
    """Answer the pair: `right` (the better clip), `wrong`, or a choice as it is."""
    better = "left" if query["left_is_first"] else "right"
    choice = {"right": better, "wrong": "right" if better == "left" else "left"}.get(how, how)
    stored = client.post(f"/api/label/{query['query_id']}", headers=bearer(token), json={
        "choice": choice, "left_is_first": query["left_is_first"],
        "shown_at": utcnow().isoformat()})
    assert stored.status_code == 201, stored.text
    out: dict[str, Any] = stored.json()
    return out


def practise(client: TestClient, token: str, *answers: str) -> None:
    for how in answers:
        query = next_pair(client, token)
        assert query["practice"] is not None, "a newcomer's first pairs are practice"
        give(client, token, query, how)


def labels_used(session: Session, run_id: int) -> int:
    with reading(session):
        run = session.get(Run, run_id)
        assert run is not None
        used = run.labels_used
        session.expunge_all()
    return used


def test_entry_pass_is_checked_against_the_runs_practice_pairs(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id = practice_run(client, session, settings)
    for bad, why in ((PRACTICE + 1, "practice pairs"), (0, "entry_pass")):
        refused = client.post("/api/invites", headers=OPERATOR,
                              json={"run_id": run_id, "entry_pass": bad})
        assert refused.status_code == 422, refused.text
        assert why in refused.text and "entry_pass" in refused.text
    plain = int(new_run(client)["id"])  # no practice pairs: no entry test
    refused = client.post("/api/invites", headers=OPERATOR,
                          json={"run_id": plain, "entry_pass": 1})
    assert refused.status_code == 422 and "has none" in refused.text
    made = client.post("/api/invites", headers=OPERATOR,
                       json={"run_id": run_id, "entry_pass": PRACTICE})
    assert made.status_code == 201 and made.json()["entry_pass"] == PRACTICE
    listed = client.get("/api/invites", headers=OPERATOR).json()
    assert [i["entry_pass"] for i in listed] == [PRACTICE]


def test_who_passes_goes_on_and_who_fails_is_let_go_without_a_code(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id = practice_run(client, session, settings)
    study = client.post("/api/invites", headers=OPERATOR, json={
        "run_id": run_id, "entry_pass": 2, "target_answers": 1,
        "completion_code": "ENTRY"}).json()
    ann, bob, cat = (join(client, study["code"], name) for name in ("ann", "bob", "cat"))

    # Ann passes (2 of 3) and goes on to real pairs, which spend the budget.
    practise(client, ann, "right", "wrong", "right")
    real = next_pair(client, ann)
    assert real["practice"] is None
    give(client, ann, real, "right")
    assert labels_used(session, run_id) == 1

    # Bob gets one right: a can't-tell and a skip are not right. He is let go.
    practise(client, bob, "right", "cant_tell")
    last = next_pair(client, bob)
    out = give(client, bob, last, "skip")
    assert out["practice_feedback"]["correct"] is None
    assert out["practice_feedback"]["entry_test"] == "failed"  # said on the explanation
    refused = client.get("/api/label/next", headers=bearer(bob))
    assert refused.status_code == 403
    assert refused.json()["detail"].startswith("entry test not passed: 1 of your practice")
    # Decided, it stays decided: the last practice answer cannot be taken back.
    back = client.post(f"/api/label/{last['query_id']}/withdraw", headers=bearer(bob))
    assert back.status_code == 409 and "entry test" in back.text
    progress = client.get("/api/label/progress", headers=bearer(bob)).json()
    assert (progress["complete"], progress["why"]) == (True, "entry_failed")
    assert progress["completion_code"] is None and progress["redirect_url"] is None
    assert (progress["entry_correct"], progress["entry_pass"]) == (1, 2)
    assert labels_used(session, run_id) == 1  # the budget: ann's one real answer

    # Cat cannot take a wrong practice answer back, even before the test is decided: the
    # explanation told her the right one, and the test measures her first try.
    first = next_pair(client, cat)
    give(client, cat, first, "wrong")
    back = client.post(f"/api/label/{first['query_id']}/withdraw", headers=bearer(cat))
    assert back.status_code == 409 and "entry test" in back.json()["detail"]
    practise(client, cat, "right", "right")
    assert next_pair(client, cat)["practice"] is None  # 2 of 3: she goes on

    rows = {row["participant"]: row for row in client.get(
        f"/api/invites/{study['id']}/participants", headers=OPERATOR).json()}
    assert (rows["ann"]["entry_test"], rows["ann"]["code_valid"]) == ("passed", True)
    assert (rows["bob"]["entry_test"], rows["bob"]["why"]) == ("failed", "entry_failed")
    assert (rows["bob"]["code_valid"], rows["bob"]["entry_correct"]) == (False, 1)
    assert (rows["cat"]["entry_test"], rows["cat"]["code_valid"]) == ("passed", False)
    text = client.get(f"/api/invites/{study['id']}/participants?format=csv",
                      headers=OPERATOR).text
    csv_rows = {r["participant"]: r for r in csv.DictReader(io.StringIO(text))}
    assert {k: csv_rows["bob"][k] for k in ("entry_test", "why", "code_valid", "practice")} == {
        "entry_test": "failed", "why": "entry_failed", "code_valid": "False", "practice": "3"}
    assert {k: csv_rows["ann"][k] for k in ("entry_test", "why", "code_valid")} == {
        "entry_test": "passed", "why": "target", "code_valid": "True"}
    checked = client.post("/api/invites/verify-codes", headers=OPERATOR, json={
        "codes": [rows["bob"]["completion_code"]]}).json()
    assert (checked[0]["valid"], checked[0]["why"]) == (False, "entry_failed")


def test_an_all_runs_entry_test_that_no_run_can_give_is_said_to_both_sides(
    client: TestClient, session: Session, settings: Settings
) -> None:
    # Made before its runs, as an all-runs link may be; then the only run has no practice pairs.
    study = client.post("/api/invites", headers=OPERATOR, json={"entry_pass": 2}).json()
    plain, _ = running_run_with_queries(client, session, settings, n=3)
    ann = join(client, study["code"], "ann")
    assert client.get("/api/label/next", headers=bearer(ann)).status_code == 204
    waiting = client.get("/api/label/status", headers=bearer(ann)).json()["waiting"]
    assert waiting["reason"] == "entry_test" and "practice pairs" in waiting["text"]
    [listed] = client.get("/api/invites", headers=OPERATOR).json()
    assert f"none of its open runs ({plain}) has at least 2 practice pairs" in \
        listed["entry_test_missing"]
    # A new link with such a test is refused while no open run could give it.
    refused = client.post("/api/invites", headers=OPERATOR, json={"entry_pass": 2})
    assert refused.status_code == 422, refused.text
    assert refused.json()["detail"][0]["loc"] == ["body", "entry_pass"]
    assert "practice pairs" in refused.text

    practice_run(client, session, settings, practice=2)  # a run that can give it: she starts
    assert next_pair(client, ann)["practice"] is not None
    [listed] = client.get("/api/invites", headers=OPERATOR).json()
    assert listed["entry_test_missing"] is None
