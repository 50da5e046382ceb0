"""The teacher-calibration report over REST: people's answers through the label API, the report
of a run or of all runs (the same as `sepoa report --calibration` on the export), its figure,
and refusals."""

from __future__ import annotations

import os
import random
from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from server_helpers import OPERATOR, bearer, new_labeller, new_run
from sqlalchemy.orm import Session

from labelqueue import claim_run, export_rows, push_queries, set_clips
from labelstats.calibration import calibration_report
from rundata.export_read import read_export
from server import curves
from server.settings import Settings
from server.side_process import NICENESS


def human_run(client: TestClient, session: Session, settings: Settings, *, algo: str,
              n: int, seed: int) -> int:
    """A claimed human-taught run with `n` rendered queries of varied returns (R_avg near 100),
    each wanting two answers."""
    run_id: int = new_run(client, algo=algo)["id"]
    claimed = claim_run(session, worker_id=f"worker-{run_id}")
    assert claimed is not None and claimed.id == run_id
    rng = random.Random(seed)
    specs = []
    for i in range(n):
        first, second = 100 + rng.uniform(-50, 50), 100 + rng.uniform(-50, 50)
        specs.append({"round": 0, "position": i, "segment_length": 50,
                      "first_trajectory": 2 * i, "first_start": 0,
                      "second_trajectory": 2 * i + 1, "second_start": 0,
                      "first_segment_return": first / 20, "second_segment_return": second / 20,
                      "first_trajectory_return": first, "second_trajectory_return": second,
                      "needs_labels": 2})
    for query_id in push_queries(session, run_id=run_id, queries=specs):
        keys = [f"run{run_id}/q{query_id}-{side}.mp4" for side in ("a", "b")]
        for key in keys:
            path = settings.clips_root / key
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(b"fake mp4 " * 20)
        set_clips(session, query_id=query_id, first_clip=keys[0], second_clip=keys[1])
    return run_id


def answer_all(client: TestClient, token: str, run_id: int, pick: Any) -> int:
    """The labeller answers every query of the run it is given, `pick(shown)` choosing."""
    answered = 0
    while True:
        shown = client.get(f"/api/label/next?run_id={run_id}", headers=bearer(token))
        if shown.status_code == 204:
            return answered
        body = {"choice": pick(shown.json()), "left_is_first": shown.json()["left_is_first"],
                "shown_at": datetime.now(UTC).isoformat()}
        response = client.post(f"/api/label/{shown.json()['query_id']}", json=body,
                               headers=bearer(token))
        assert response.status_code == 201, response.text
        answered += 1


def test_the_report_of_a_run_and_of_all_runs_equals_the_exports(
    client: TestClient, session: Session, settings: Settings, tmp_path: Path
) -> None:
    sepoa = human_run(client, session, settings, algo="sepoa", n=12, seed=1)
    pebble = human_run(client, session, settings, algo="pebble", n=8, seed=2)
    lefty, coin = new_labeller(client, "lefty"), new_labeller(client, "coin")
    rng = random.Random(0)
    for run_id in (sepoa, pebble):
        assert answer_all(client, lefty, run_id, lambda _shown: "left") > 0
        assert answer_all(client, coin, run_id,
                          lambda _shown: rng.choice(["left", "right", "cant_tell"])) > 0

    response = client.get(f"/api/quality/calibration?run_id={sepoa}", headers=OPERATOR)
    assert response.status_code == 200, response.text
    report = response.json()
    assert report["runs"] == [sepoa] and report["rows"] == 24
    assert [(g["name"], g["rates"]["answers"]) for g in report["labellers"]] == [
        ("lefty", 12), ("coin", 12)]
    assert report["labellers"][0]["position"]["left_share"] == 1.0
    assert [a["algo"] for a in report["algos"]] == ["sepoa"]

    everything = client.get("/api/quality/calibration", headers=OPERATOR).json()
    assert everything["runs"] == [sepoa, pebble]
    assert [(a["algo"], a["queries"], a["rates"]["answers"]) for a in everything["algos"]] == [
        ("pebble", 8, 16), ("sepoa", 12, 24)]
    # The same numbers as the report of the exported file.
    exported = client.get("/api/export?format=csv", headers=OPERATOR)
    path = tmp_path / "labels.csv"
    path.write_bytes(exported.content)
    from_file = calibration_report(read_export(str(path)))
    assert everything["everyone"]["fit"]["eps"] == from_file.everyone.fit.eps
    assert everything["labellers"][1]["rates"] == asdict(from_file.labellers[1].rates)

    narrow = client.get(f"/api/quality/calibration?run_id={sepoa}&bins=0,0.5,inf",
                        headers=OPERATOR).json()
    assert narrow["edges"] == [0.0, 0.5, None]
    assert sum(b["rates"]["answers"] for b in narrow["everyone"]["bins"]) == 24

    png = client.get(f"/api/quality/calibration.png?run_id={sepoa}", headers=OPERATOR)
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    assert png.content.startswith(b"\x89PNG")


def test_an_empty_run_has_an_empty_report_and_a_figure(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id = human_run(client, session, settings, algo="sepoa", n=1, seed=3)
    report = client.get(f"/api/quality/calibration?run_id={run_id}", headers=OPERATOR).json()
    assert report["rows"] == 0 and report["labellers"] == [] and report["algos"] == []
    assert report["everyone"]["fit"]["eps"] is None
    png = client.get(f"/api/quality/calibration.png?run_id={run_id}", headers=OPERATOR)
    assert png.status_code == 200 and png.content.startswith(b"\x89PNG")


def test_bad_requests_are_refused(client: TestClient) -> None:
    labeller = new_labeller(client, "ann")
    for path in ("/api/quality/calibration", "/api/quality/calibration.png"):
        assert client.get(path).status_code == 401
        assert client.get(path, headers=bearer(labeller)).status_code == 403
        missing = client.get(f"{path}?run_id=99", headers=OPERATOR)
        assert missing.status_code == 404 and "run 99 does not exist" in missing.json()["detail"]
        assert client.get(f"{path}?run_id=0", headers=OPERATOR).status_code == 422
        for bins, why in [("0.2,0.5", "first edge must be 0"), ("0,1,0.5", "must increase"),
                          ("0,x", "comma-separated")]:
            refused = client.get(f"{path}?bins={bins}", headers=OPERATOR)
            assert refused.status_code == 422 and why in refused.json()["detail"], refused.text


def _crowd_run(client: TestClient, session: Session, settings: Settings) -> tuple[int, dict]:
    """A human-taught run asking 3 answers per query, with 6 queries and 4 gold pairs (gold rate
    0.5, a labeller paused below 20% on 3 gold answers); the true answer of each query id."""
    config = {"feedback.labels_per_query": 3, "feedback.gold_rate": 0.5,
              "feedback.gold_min_accuracy": 0.2, "feedback.gold_min_answers": 3}
    run_id: int = new_run(client, algo="pebble", config=config)["id"]
    assert claim_run(session, worker_id="worker-crowd") is not None
    rng = random.Random(3)
    specs = []
    for i in range(10):
        first, second = 100 + rng.uniform(-50, 50), 100 + rng.uniform(-50, 50)
        spec = {"round": 0, "position": i, "segment_length": 50, "first_trajectory": 2 * i,
                "first_start": 0, "second_trajectory": 2 * i + 1, "second_start": 0,
                "first_segment_return": first / 20, "second_segment_return": second / 20,
                "first_trajectory_return": first, "second_trajectory_return": second,
                "distinguishable": True}
        specs.append(spec | ({"gold": True} if i >= 6 else {"needs_labels": 3}))
    truth = {}
    for query_id, spec in zip(push_queries(session, run_id=run_id, queries=specs), specs,
                              strict=True):
        keys = [f"run{run_id}/q{query_id}-{side}.mp4" for side in ("a", "b")]
        for key in keys:
            (settings.clips_root / key).parent.mkdir(parents=True, exist_ok=True)
            (settings.clips_root / key).write_bytes(b"fake mp4 " * 20)
        set_clips(session, query_id=query_id, first_clip=keys[0], second_clip=keys[1])
        truth[query_id] = ("first" if spec["first_segment_return"] > spec["second_segment_return"]
                           else "second")
    return run_id, truth


def test_three_labellers_per_query_their_agreement_gold_accuracy_and_a_pause(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, truth = _crowd_run(client, session, settings)

    def side(shown: dict, answer: str) -> str:
        return "left" if (answer == "first") == shown["left_is_first"] else "right"

    def flip(answer: str) -> str:
        return "second" if answer == "first" else "first"

    right, lefty, wrong = (new_labeller(client, name) for name in ("right", "lefty", "wrong"))
    given = {
        "right": answer_all(client, right, run_id, lambda s: side(s, truth[s["query_id"]])),
        "lefty": answer_all(client, lefty, run_id, lambda _s: "left"),
    }
    # The labeller who is always wrong is paused once 3 gold answers are in, all wrong.
    answered = 0
    while (shown := client.get(f"/api/label/next?run_id={run_id}", headers=bearer(wrong))
           ).status_code == 200:
        body = {"choice": side(shown.json(), flip(truth[shown.json()["query_id"]])),
                "shown_at": datetime.now(UTC).isoformat()}
        posted = client.post(f"/api/label/{shown.json()['query_id']}", json=body,
                             headers=bearer(wrong))
        assert posted.status_code == 201, posted.text
        answered += 1
    assert shown.status_code == 403 and "paused" in shown.json()["detail"]
    assert "0 of your 3 answers on check pairs were right" in shown.json()["detail"]
    # Every query went to each labeller once at most: 6 queries + 4 gold pairs for the others.
    assert given == {"right": 10, "lefty": 10}

    rows = list(export_rows(session, run_id=run_id))
    per_query: dict[int, list[str]] = {}
    for row in rows:
        per_query.setdefault(row["query_id"], []).append(row["labeller_name"])
    assert all(len(names) == len(set(names)) for names in per_query.values())
    run = client.get(f"/api/runs/{run_id}", headers=OPERATOR).json()
    # Gold answers cost no budget: the run counts the answers to its 6 queries only.
    assert run["labels_used"] == sum(not row["gold"] for row in rows) >= 12
    assert sum(row["gold"] for row in rows) == 8 + 3  # right's and lefty's 4, wrong's 3

    agreement = client.get(f"/api/quality/agreement?run_id={run_id}", headers=OPERATOR)
    assert agreement.status_code == 200, agreement.text
    report = agreement.json()
    assert report["everyone"]["queries"] == 10
    by_name = {a["labeller_name"]: a for a in report["labellers"]}
    assert by_name["right"]["shared_queries"] == 10

    quality = client.get(f"/api/quality/labellers?run_id={run_id}", headers=OPERATOR)
    assert quality.status_code == 200, quality.text
    people = {q["labeller_name"]: q for q in quality.json()}
    assert people["right"]["gold_accuracy"]["rate"] == 1.0
    assert people["right"]["gold_accuracy"]["n"] == 4
    assert people["wrong"]["gold_accuracy"] == people["wrong"]["gold_accuracy"] | {"k": 0, "n": 3}
    assert people["wrong"]["paused"] and not people["right"]["paused"]
    assert people["lefty"]["left"]["rate"] == 1.0 and people["lefty"]["left_p_value"] < 0.01
    assert people["right"]["accuracy"]["rate"] == 1.0

    # The operator lifts the pause: the labeller gets the run's queries again (none are left
    # for them here but the gold pair they have not seen), and their answers stayed.
    lifted = client.delete(f"/api/quality/runs/{run_id}/pauses/{people['wrong']['labeller_id']}",
                           headers=OPERATOR)
    assert lifted.status_code == 204, lifted.text
    again = client.get(f"/api/label/next?run_id={run_id}", headers=bearer(wrong))
    assert again.status_code in (200, 204)
    missing = client.delete(f"/api/quality/runs/{run_id}/pauses/{people['wrong']['labeller_id']}",
                            headers=OPERATOR)
    assert missing.status_code == 404 and "not paused" in missing.json()["detail"]


def test_the_figure_is_drawn_by_the_run_pages_drawing_process(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id = human_run(client, session, settings, algo="sepoa", n=4, seed=5)
    assert answer_all(client, new_labeller(client, "lefty"), run_id, lambda _shown: "left") == 4
    png = client.get(f"/api/quality/calibration.png?run_id={run_id}", headers=OPERATOR)
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    # The figure of the run's report, drawn by a process of lower priority than the server's.
    report = calibration_report(export_rows(session, run_id=run_id))
    assert png.content == curves.draw_calibration(report, f"Teacher calibration · Run {run_id}")
    assert curves._drawer.run(os.getpid) != os.getpid()
    assert curves._drawer.run(os.nice, 0) == min(19, os.nice(0) + NICENESS)


def test_pages_share_one_drawing_until_the_labels_change(
    client: TestClient, session: Session, settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    from figures import calibration as plots

    # Drawn in the test's process, where `plots.calibration_png` can be watched.
    class Here:
        def run(self, function: Any, *args: Any) -> Any:
            return function(*args)

    monkeypatch.setattr(curves, "_drawer", Here())
    drawings: list[int] = []
    draw = plots.calibration_png

    def counted(report: Any, **kwargs: Any) -> bytes:
        drawings.append(report.rows)
        return draw(report, **kwargs)

    monkeypatch.setattr(plots, "calibration_png", counted)
    run_id = human_run(client, session, settings, algo="pebble", n=3, seed=6)
    answer_all(client, new_labeller(client, "lefty"), run_id, lambda _shown: "left")
    path = f"/api/quality/calibration.png?run_id={run_id}"
    pages = [client.get(path, headers=OPERATOR) for _ in range(3)]
    assert drawings == [3]
    assert all(page.content == pages[0].content for page in pages)
    # Another run's figure, then this one's after new labels: each drawn once.
    assert client.get("/api/quality/calibration.png", headers=OPERATOR).status_code == 200
    assert drawings == [3, 3]
    answer_all(client, new_labeller(client, "coin"), run_id, lambda _shown: "right")
    again = client.get(path, headers=OPERATOR)
    assert drawings == [3, 3, 6] and again.content != pages[0].content
    assert client.get(path, headers=OPERATOR).content == again.content
    assert drawings == [3, 3, 6]
