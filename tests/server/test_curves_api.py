"""The run page's figure: a run's evaluation curve beside its peers', drawn by the report's
plotting code."""

from __future__ import annotations

import os
from typing import Any

import pytest
from fastapi.testclient import TestClient
from server_helpers import OPERATOR, bearer, new_labeller, new_run
from sqlalchemy.orm import Session

from figures import curves as plots
from labelqueue import write_metrics
from server import curves
from server.side_process import NICENESS


@pytest.fixture
def drawn_here(monkeypatch: pytest.MonkeyPatch) -> None:
    """Figures drawn in the test's process, where `plots.curves_png` can be watched."""
    class Here:
        def run(self, function: Any, *args: Any) -> Any:
            return function(*args)

    monkeypatch.setattr(curves, "_drawer", Here())


def _evaluated_run(client: TestClient, session: Session, *, algo: str, eps: float,
                   returns: list[float], task: str = "dmc:cheetah_run") -> int:
    run_id: int = new_run(client, algo=algo, task=task,
                          teacher_params={"eps": eps})["id"]
    for i, value in enumerate(returns):
        write_metrics(session, run_id=run_id, stream="eval", step=1000 * (i + 1),
                      values={"return": value, "success_rate": 0.0})
    return run_id


def test_the_figure_groups_peers_by_algorithm_and_draws_the_run_itself(
    client: TestClient, session: Session, monkeypatch: pytest.MonkeyPatch, drawn_here: None
) -> None:
    mine = _evaluated_run(client, session, algo="pebble", eps=0.3, returns=[1, 2, 3])
    _evaluated_run(client, session, algo="pebble", eps=0.3, returns=[3, 4])
    _evaluated_run(client, session, algo="sepoa", eps=0.3, returns=[5, 6, 7])
    _evaluated_run(client, session, algo="sepoa", eps=0.1, returns=[9, 9])  # another eps
    _evaluated_run(client, session, algo="sepoa", eps=0.3, returns=[9, 9],
                   task="dmc:walker_run")  # another task
    drawn: dict[str, Any] = {}
    draw = plots.curves_png

    def capture(curves: Any, **kwargs: Any) -> bytes:
        drawn.update(curves=curves, **kwargs)
        return draw(curves, **kwargs)

    monkeypatch.setattr(plots, "curves_png", capture)
    response = client.get(f"/api/runs/{mine}/curves.png", headers=OPERATOR)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "image/png"
    assert response.content.startswith(plots.PNG_SIGNATURE)
    curves = drawn["curves"]
    assert sorted(curves) == ["pebble (2 runs)", "sepoa (1 run)", "this run (pebble, seed 0)"]
    assert [list(values) for _, values in curves["pebble (2 runs)"]] == [[1, 2, 3], [3, 4]]
    assert list(curves["this run (pebble, seed 0)"][0][0]) == [1000, 2000, 3000]
    assert "ε = 0.3" in drawn["title"]
    # The pebble band: mean and sample std of both seeds on the steps both reached.
    band = plots.align(curves["pebble (2 runs)"])
    assert list(band.steps) == [1000, 2000] and list(band.mean) == [2, 3]


def test_figures_are_drawn_by_a_process_of_lower_priority_than_the_server(
    client: TestClient, session: Session
) -> None:
    run_id = _evaluated_run(client, session, algo="pebble", eps=0.25, returns=[1.5, 2.5])
    response = client.get(f"/api/runs/{run_id}/curves.png", headers=OPERATOR)
    assert response.status_code == 200 and response.content.startswith(plots.PNG_SIGNATURE)
    # The same PNG as drawn here, but not drawn by the server's process.
    figure = (("pebble (1 run)", (((1000, 2000), (1.5, 2.5)),)),
              ("this run (pebble, seed 0)", (((1000, 2000), (1.5, 2.5)),)))
    title = "dmc:cheetah_run · tiny · human teacher, ε = 0.25"
    assert response.content == curves.draw(figure, title, "evaluation return")
    assert curves._drawer.run(os.getpid) != os.getpid()
    assert curves._drawer.run(os.nice, 0) == min(19, os.nice(0) + NICENESS)


def test_the_figure_is_for_operators_of_existing_runs(client: TestClient) -> None:
    run_id = new_run(client)["id"]
    labeller = new_labeller(client, "ann")
    assert client.get(f"/api/runs/{run_id}/curves.png").status_code == 401
    assert client.get(f"/api/runs/{run_id}/curves.png",
                      headers=bearer(labeller)).status_code == 403
    assert client.get("/api/runs/999/curves.png", headers=OPERATOR).status_code == 404
    assert client.get(f"/api/runs/{run_id}/curves.png?metric=loss",
                      headers=OPERATOR).status_code == 422
    # A run without evaluations yet still gets a (blank) figure.
    empty = client.get(f"/api/runs/{run_id}/curves.png?metric=success_rate", headers=OPERATOR)
    assert empty.status_code == 200 and empty.content.startswith(plots.PNG_SIGNATURE)


def test_open_run_pages_share_one_drawing_until_a_new_evaluation(
    client: TestClient, session: Session, monkeypatch: pytest.MonkeyPatch, drawn_here: None
) -> None:
    run_id = _evaluated_run(client, session, algo="rune", eps=0.2, returns=[4, 5])
    drawings: list[Any] = []
    draw = plots.curves_png

    def counted(curves: Any, **kwargs: Any) -> bytes:
        drawings.append(curves)
        return draw(curves, **kwargs)

    monkeypatch.setattr(plots, "curves_png", counted)
    pages = [client.get(f"/api/runs/{run_id}/curves.png", headers=OPERATOR) for _ in range(3)]
    assert len(drawings) == 1
    assert all(page.content == pages[0].content for page in pages)
    write_metrics(session, run_id=run_id, stream="eval", step=3000, values={"return": 6})
    again = client.get(f"/api/runs/{run_id}/curves.png", headers=OPERATOR)
    assert len(drawings) == 2 and again.content != pages[0].content
    assert [list(values) for _, values in drawings[1]["this run (rune, seed 0)"]] == [[4, 5, 6]]


def test_peers_share_the_teacher_kind_and_the_error_rate_the_run_trains_with(
    client: TestClient, session: Session, monkeypatch: pytest.MonkeyPatch, drawn_here: None
) -> None:
    def evaluated(returns: list[float], **body: Any) -> int:
        run_id: int = new_run(client, algo="pebble", **body)["id"]
        for i, value in enumerate(returns):
            write_metrics(session, run_id=run_id, stream="eval", step=1000 * (i + 1),
                          values={"return": value})
        return run_id

    mine = evaluated([1, 2], teacher="scripted", config={"teacher.eps": 0.3})
    evaluated([3, 4], teacher="scripted", teacher_params={"eps": 0.3}, seed=1)
    evaluated([], teacher="scripted", teacher_params={"eps": 0.3}, seed=2)  # none yet
    evaluated([9, 9], teacher="scripted", seed=3)  # eps 0
    evaluated([8, 8], teacher="human", config={"teacher.eps": 0.3}, seed=4)  # people teach it
    drawn: dict[str, Any] = {}
    monkeypatch.setattr(plots, "curves_png",
                        lambda curves, **kwargs: drawn.update(curves=curves, **kwargs) or b"")
    assert client.get(f"/api/runs/{mine}/curves.png", headers=OPERATOR).status_code == 200
    assert sorted(drawn["curves"]) == ["pebble (2 runs)", "this run (pebble, seed 0)"]
    assert [list(v) for _, v in drawn["curves"]["pebble (2 runs)"]] == [[1, 2], [3, 4]]
    assert "scripted teacher, ε = 0.3" in drawn["title"]
