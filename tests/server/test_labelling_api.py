"""POST /api/runs/labelling: an operator queues a labelling-only run over a dataset export in
the server's datasets folder; a dataset no worker could serve is a 422 naming the problem, and
nothing is stored."""

from __future__ import annotations

import shutil

import pytest
from fastapi.testclient import TestClient
from labelling_helpers import drop_states, edit_info, exported_dataset, malformed_copies
from server_helpers import OPERATOR, bearer, new_labeller

from server.settings import Settings

DATASET = "sepoa/dmc-cheetah_run/source-v0"


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    return exported_dataset(tmp_path_factory.mktemp("api") / "datasets", dataset_id=DATASET)


@pytest.fixture
def datasets(source, settings: Settings):
    """The server's datasets folder, holding the source dataset."""
    root = settings.data_dir / "datasets"
    shutil.copytree(source, root / DATASET)
    return root


def test_an_operator_queues_a_labelling_run_over_a_dataset(client: TestClient, datasets):
    answer = client.post("/api/runs/labelling", headers=OPERATOR, json={
        "dataset": DATASET, "budget": 40, "per_round": 8, "preset": "tiny",
        "selection": "uniform", "clip_size": "128x128", "instruction": "Which runs faster?"})
    assert answer.status_code == 201, answer.text
    run = answer.json()
    assert (run["status"], run["task"], run["algo"], run["budget"], run["teacher"]) == (
        "queued", "dmc:cheetah_run", "pebble", 40, "human")
    assert run["dataset"] == str((datasets / DATASET).resolve())
    assert run["name"] == f"label {DATASET}" and run["instruction_text"] == "Which runs faster?"
    assert run["config"]["feedback.per_round"] == 8
    assert run["config"]["feedback.selection"] == "uniform"
    assert client.get(f"/api/runs/{run['id']}", headers=OPERATOR).json()["dataset"] \
        == run["dataset"]
    # A training run has none.
    trained = client.post("/api/runs", headers=OPERATOR, json={
        "task": "dmc:cheetah_run", "algo": "pebble", "preset": "tiny"}).json()
    assert trained["dataset"] is None
    listed = client.get("/api/runs/labelling", headers=OPERATOR).json()
    assert [r["id"] for r in listed] == [run["id"]]


def test_a_dataset_no_worker_could_serve_is_a_422_naming_it(client: TestClient, datasets):
    for name, change in (("unknown", {"task": "dmc:cheetah_fly"}), ("spaces", {"obs_dim": 5})):
        shutil.copytree(datasets / DATASET, datasets / "bad" / name)
        edit_info(datasets / "bad" / name, **change)
    shutil.copytree(datasets / DATASET, datasets / "bad" / "stateless")
    drop_states(datasets / "bad" / "stateless")
    cases = {
        "missing": ({"dataset": "sepoa/nothing-v0"}, ["body", "dataset"],
                    "no dataset 'sepoa/nothing-v0' in the server's datasets folder"),
        "outside": ({"dataset": "sepoa/../../x"}, ["body", "dataset"], "pattern"),
        "unknown task": ({"dataset": "bad/unknown"}, ["body", "dataset"],
                         "task 'dmc:cheetah_fly' is not one this project knows"),
        "spaces": ({"dataset": "bad/spaces"}, ["body", "dataset"],
                   "do not match sepoa.json (obs_dim 5"),
        "no states": ({"dataset": "bad/stateless"}, ["body", "dataset"],
                      "has no physics states"),
        "segment": ({"segment_length": 61}, ["body", "segment_length"],
                    "segment length 61: give 1 to 60"),
        "config": ({"config": {"reward.widht": 3}}, ["body", "config", "reward.widht"],
                   "reward.widht"),
        "teacher": ({"teacher_params": {"eps": -1}}, ["body", "teacher_params", "eps"], "eps"),
        "selection": ({"selection": "entropy"}, ["body", "selection"], "uniform"),
        "path": ({"dataset": "/etc"}, ["body", "dataset"], "pattern"),
    }
    for name, (change, loc, message) in cases.items():
        answer = client.post("/api/runs/labelling", headers=OPERATOR,
                             json={"dataset": DATASET, "budget": 10} | change)
        assert answer.status_code == 422, (name, answer.text)
        [detail] = answer.json()["detail"]
        assert detail["loc"] == loc and message in detail["msg"], (name, detail)
    assert client.get("/api/runs", headers=OPERATOR).json() == []


def test_only_operators_queue_labelling_runs(client: TestClient, datasets):
    body = {"dataset": DATASET, "budget": 10}
    assert client.post("/api/runs/labelling", json=body).status_code == 401
    token = new_labeller(client, "bob")
    assert client.post("/api/runs/labelling", headers=bearer(token), json=body).status_code \
        == 403
    assert client.get("/api/runs", headers=OPERATOR).json() == []


def test_a_malformed_dataset_is_a_422_naming_its_problem(client: TestClient, datasets):
    cases = {name: (str(path.relative_to(datasets)), message) for name, (path, message)
             in malformed_copies(datasets / DATASET, datasets / "bad").items()}
    cases["long name"] = ("bad/" + "x" * 290, "no dataset 'bad/xxx")
    for name, (dataset, message) in cases.items():
        answer = client.post("/api/runs/labelling", headers=OPERATOR,
                             json={"dataset": dataset, "budget": 10})
        assert answer.status_code == 422, (name, answer.text)
        [detail] = answer.json()["detail"]
        assert detail["loc"] == ["body", "dataset"] and message in detail["msg"], (name, detail)
    assert client.get("/api/runs", headers=OPERATOR).json() == []
