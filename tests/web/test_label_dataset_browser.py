"""Labelling an imported dataset on the real page: an operator queues a labelling-only run over
a dataset export in the server's datasets folder, a real worker renders the pairs' clips from
the dataset's stored states, a labeller answers both pairs in Chromium, the run finishes, and
the export's labels point at the dataset's episodes."""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
from labelling_helpers import exported_dataset
from web_helpers import LiveServer
from worker_helpers import settle_labels, worker_config

from labelqueue import RunStatus, claim_run
from rundata.dataset import read_dataset
from trainer.worker import scripted_labeller_id, train_claimed_run

DATASET = "sepoa/dmc-cheetah_run/imported-v0"
SHOWN = "#pairs .pair:not([hidden])"
DECODED = """selector => {
    const videos = [...document.querySelectorAll(`${selector} video`)];
    return videos.length === 2 && videos.every(v => v.readyState >= 2 && v.videoWidth > 0);
}"""
GONE = """id => {
    const shown = document.querySelector('#pairs .pair:not([hidden])');
    return !shown || shown.dataset.queryId !== id;
}"""


def test_a_labeller_labels_a_pair_of_an_imported_dataset(live: LiveServer, page: Any) -> None:
    data = live.settings.data_dir
    path = exported_dataset(data / "datasets", dataset_id=DATASET, seed=3)
    dataset = read_dataset(str(path))
    run_id = live.api("POST", "/api/runs/labelling", json={
        "dataset": DATASET, "budget": 2, "per_round": 2, "preset": "tiny",
        "clip_size": "128x128", "config": {"threads": 1}})["id"]
    worker = worker_config(live.settings.database_url, data)
    with live.sessions() as session:
        run = claim_run(session, worker_id=worker.worker_id)
    assert run is not None and run.id == run_id, "another run is still queued"
    serving = threading.Thread(target=train_claimed_run, daemon=True, args=(
        live.sessions, run, worker, scripted_labeller_id(live.sessions)))
    serving.start()

    dora = live.new_labeller("dora")
    page.goto(f"{live.url}/label?run={run_id}#token={dora.token}")
    for _ in range(2):  # both pairs of the round, as their clips come
        page.wait_for_function(DECODED, arg=SHOWN, timeout=60_000)
        shown = page.get_attribute(SHOWN, "data-query-id")
        page.wait_for_selector('[data-choice="left"]:not([disabled])', timeout=30_000)
        page.keyboard.press("ArrowLeft")
        page.wait_for_function(GONE, arg=shown)
    settle_labels(live.sessions, run_id)  # as if the undo window had passed
    serving.join(timeout=120)
    assert live.api("GET", f"/api/runs/{run_id}")["status"] == RunStatus.FINISHED

    exported = live.api_text("GET", f"/api/export?run_id={run_id}")
    assert len(exported) == 2 and {r["labeller_name"] for r in exported} == {"dora"}
    for row in exported:
        assert row["choice"] == "left"
        for side in ("first", "second"):
            episode = dataset.episodes[row[f"{side}_trajectory"]]
            start = row[f"{side}_start"]
            assert row[f"{side}_segment_return"] == episode.rewards[
                start:start + row["segment_length"]].sum(dtype=np.float64)
