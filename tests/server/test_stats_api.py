"""Label throughput for the run page, and a labeller's own label count, on hand-made labels."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

from fastapi.testclient import TestClient
from server_helpers import (
    OPERATOR,
    bearer,
    new_labeller,
    new_run,
    query_spec,
    running_run_with_queries,
)
from sqlalchemy import update
from sqlalchemy.orm import Session

from labelqueue import (
    Label,
    claim_run,
    create_labeller,
    lease_next_query,
    push_queries,
    submit_label,
)
from labelqueue.models import utcnow
from server.settings import Settings

T0 = datetime(2025, 3, 1, 12, 0, 0, tzinfo=UTC)


def answer(
    session: Session,
    *,
    run_id: int,
    labeller_id: int,
    source: str,
    answered: datetime,
    shown: datetime | None,
) -> None:
    """A label through the queue's own path, then given the hand-picked times."""
    query = lease_next_query(session, labeller_id=labeller_id, run_id=run_id)
    assert query is not None
    label, _ = submit_label(
        session,
        query_id=query.id,
        labeller_id=labeller_id,
        choice="left",
        left_is_first=True,
        source=source,
    )
    session.execute(
        update(Label).where(Label.id == label.id).values(answered_at=answered, shown_at=shown)
    )
    session.commit()


def at(seconds: float) -> datetime:
    return T0 + timedelta(seconds=seconds)


def test_throughput_counts_labels_per_bucket_and_source_and_the_median_answer_time(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, _ = running_run_with_queries(client, session, settings, n=7)
    alice, _ = create_labeller(session, name="alice")
    bob, _ = create_labeller(session, name="bob")
    teacher, _ = create_labeller(session, name="scripted-teacher")
    # Human answers taking 4, 10 and 7 s; one human label without shown_at; scripted and gold
    # labels are fast but are not people's answer times.
    for labeller, source, answered, shown in [
        (alice, "human", at(4), at(0)),
        (alice, "human", at(40), at(30)),
        (bob, "human", at(127), at(120)),
        (bob, "human", at(150), None),
        (teacher, "scripted", at(50), at(49.5)),
        (teacher, "scripted", at(3605), None),
        (teacher, "scripted", at(130), at(129)),
    ]:
        answer(
            session,
            run_id=run_id,
            labeller_id=labeller.id,
            source=source,
            answered=answered,
            shown=shown,
        )
    # Another run's labels are not this run's throughput.
    other_id = new_run(client, teacher="scripted")["id"]
    claim_run(session, worker_id="worker-2")
    push_queries(session, run_id=other_id, queries=[query_spec(0)])
    answer(
        session,
        run_id=other_id,
        labeller_id=teacher.id,
        source="scripted",
        answered=at(5),
        shown=None,
    )

    response = client.get(f"/api/runs/{run_id}/throughput", headers=OPERATOR)
    assert response.status_code == 200, response.text
    stats = response.json()
    assert stats["run_id"] == run_id and stats["bucket_s"] == 60
    assert stats["total"] == 7
    assert stats["by_source"] == {"human": 4, "scripted": 3}
    assert stats["median_answer_s"] == 7.0
    buckets = [(datetime.fromisoformat(b["t"]), b["labels"]) for b in stats["buckets"]]
    assert buckets == [(at(0), 3), (at(120), 3), (at(3600), 1)]  # empty minutes left out

    hourly = client.get(f"/api/runs/{run_id}/throughput?bucket_s=3600", headers=OPERATOR).json()
    assert [(datetime.fromisoformat(b["t"]), b["labels"]) for b in hourly["buckets"]] == [
        (at(0), 6),
        (at(3600), 1),
    ]


def test_a_run_without_labels_has_empty_throughput(client: TestClient) -> None:
    run_id = new_run(client)["id"]
    stats = client.get(f"/api/runs/{run_id}/throughput", headers=OPERATOR).json()
    assert stats == {
        "run_id": run_id,
        "bucket_s": 60,
        "total": 0,
        "by_source": {"human": 0, "scripted": 0},
        "median_answer_s": None,
        "buckets": [],
    }


def test_throughput_is_for_operators_of_existing_runs(client: TestClient) -> None:
    run_id = new_run(client)["id"]
    path = f"/api/runs/{run_id}/throughput"
    assert client.get(path).status_code == 401
    assert client.get(path, headers=bearer("not-a-token")).status_code == 401
    labeller = bearer(new_labeller(client, "alice"))
    refused = client.get(path, headers=labeller)
    assert refused.status_code == 403 and "not an operator" in refused.json()["detail"]
    missing = client.get("/api/runs/999/throughput", headers=OPERATOR)
    assert missing.status_code == 404 and missing.json() == {"detail": "run 999 does not exist"}
    for bad in ("0", "-5", "86401", "minute"):
        assert client.get(f"{path}?bucket_s={bad}", headers=OPERATOR).status_code == 422


def test_a_labeller_sees_how_many_labels_they_have_given(
    client: TestClient, session: Session, settings: Settings
) -> None:
    token = new_labeller(client, "alice")
    alice = bearer(token)
    assert client.get("/api/label/count", headers=alice).json() == {"labels": 0}
    running_run_with_queries(client, session, settings, n=2)
    for _ in range(2):
        shown = client.get("/api/label/next", headers=alice).json()
        body = {
            "choice": "skip",
            "left_is_first": shown["left_is_first"],
            "shown_at": T0.isoformat(),
        }
        assert client.post(f"/api/label/{shown['query_id']}", json=body, headers=alice).is_success
    assert client.get("/api/label/count", headers=alice).json() == {"labels": 2}
    bob = bearer(new_labeller(client, "bob"))
    assert client.get("/api/label/count", headers=bob).json() == {"labels": 0}

    assert client.get("/api/label/count").status_code == 401
    # The operator token is not a labeller: it has given no labels and cannot.
    assert client.get("/api/label/count", headers=OPERATOR).status_code == 403


def test_an_answer_taken_back_counts_nowhere_and_the_median_of_an_even_count_is_the_mean(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, _ = running_run_with_queries(client, session, settings, n=4)
    token = new_labeller(client, "alice")
    alice = bearer(token)
    path = f"/api/runs/{run_id}/throughput"
    shown = []
    for _ in range(3):
        pair = client.get("/api/label/next", headers=alice).json()
        body = {"choice": "left", "left_is_first": pair["left_is_first"],
                "shown_at": T0.isoformat()}
        assert client.post(f"/api/label/{pair['query_id']}", json=body,
                           headers=alice).status_code == 201
        shown.append(pair["query_id"])
    # Answer times of 4, 10 and 6 s (then 4 and 10 once the last is taken back).
    for query_id, seconds in zip(shown, (4, 10, 6), strict=True):
        session.execute(update(Label).where(Label.query_id == query_id)
                        .values(shown_at=at(0), answered_at=at(seconds)))
    session.commit()
    before = client.get(path, headers=OPERATOR).json()
    assert before["total"] == 3 and before["median_answer_s"] == 6.0
    assert before["buckets"] == [{"t": at(0).isoformat().replace("+00:00", "Z"), "labels": 3}]
    assert client.get("/api/label/count", headers=alice).json() == {"labels": 3}

    # Taken back within the undo window: the label stays, withdrawn, and counts no more.
    session.execute(update(Label).where(Label.query_id == shown[2]).values(answered_at=utcnow()))
    session.commit()
    taken = client.post(f"/api/label/{shown[2]}/withdraw", json={}, headers=alice)
    assert taken.status_code == 200, taken.text
    after = client.get(path, headers=OPERATOR).json()
    assert after["total"] == 2 and after["by_source"]["human"] == 2
    assert after["median_answer_s"] == 7.0  # (4 + 10) / 2
    assert [b["labels"] for b in after["buckets"]] == [2]
    assert client.get("/api/label/count", headers=alice).json() == {"labels": 2}
