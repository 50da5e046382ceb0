"""The operator's Minari dataset download: a run's stored episodes and labels, zipped under the
dataset id, and the refusals."""

from __future__ import annotations

import io
import os
import zipfile
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from fastapi.testclient import TestClient
from server_helpers import OPERATOR, bearer, new_labeller, running_run_with_queries
from sqlalchemy.orm import Session
from test_export_api import answer

from rundata.episodes import StoredEpisode, episode_path, episodes_dir, write_episode
from server.settings import Settings


def _episode(trajectory: int, length: int = 80) -> StoredEpisode:
    rng = np.random.default_rng(trajectory)
    return StoredEpisode(
        trajectory=trajectory,
        observations=rng.normal(size=(length + 1, 17)).astype(np.float32),
        actions=rng.uniform(-1, 1, (length, 6)).astype(np.float32),
        rewards=rng.uniform(0, 1, length).astype(np.float32),
        states=rng.normal(size=(length + 1, 18)), context=0, success=False)


def test_an_operator_downloads_a_run_as_a_minari_dataset(
    client: TestClient, session: Session, settings: Settings, tmp_path: Path
) -> None:
    import minari

    run_id, _ = running_run_with_queries(client, session, settings, n=1)
    episodes = [_episode(0), _episode(1)]
    for episode in episodes:
        write_episode(episodes_dir(settings.clips_root, run_id), episode)
    answer(client, new_labeller(client, "alice"), "left")

    response = client.get(f"/api/runs/{run_id}/dataset", headers=OPERATOR)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/zip"
    name = f"sepoa/dmc-cheetah_run/run-{run_id}-v0"
    assert name.replace("/", "_") + ".zip" in response.headers["content-disposition"]
    root = tmp_path / "minari"
    with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
        assert all(member.startswith(name + "/") for member in archive.namelist())
        archive.extractall(root)

    os.environ["MINARI_DATASETS_PATH"] = str(root)
    try:
        dataset = minari.load_dataset(name)
    finally:
        del os.environ["MINARI_DATASETS_PATH"]
    assert dataset.total_episodes == 2 and dataset.total_steps == 160
    for i, episode in enumerate(episodes):
        np.testing.assert_array_equal(dataset[i].observations, episode.observations)
        np.testing.assert_array_equal(dataset[i].infos["state"], episode.states)
    labels = pq.read_table(root / name / "labels.parquet").to_pylist()
    assert [(r["labeller_name"], r["first_episode"], r["second_episode"], r["first_start"])
            for r in labels] == [("alice", 0, 1, 10)]

    hdf5 = client.get(f"/api/runs/{run_id}/dataset?format=hdf5", headers=OPERATOR)
    assert hdf5.status_code == 200, hdf5.text
    with zipfile.ZipFile(io.BytesIO(hdf5.content)) as archive:
        assert f"{name}/data/main_data.hdf5" in archive.namelist()


def test_refusals_name_the_problem(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, _ = running_run_with_queries(client, session, settings, n=1)
    url = f"/api/runs/{run_id}/dataset"
    assert client.get(url).status_code == 401
    assert client.get(url, headers=bearer(new_labeller(client, "bob"))).status_code == 403
    missing = client.get("/api/runs/999/dataset", headers=OPERATOR)
    assert missing.status_code == 404 and "run 999" in missing.json()["detail"]
    empty = client.get(url, headers=OPERATOR)
    assert empty.status_code == 409 and "no stored episodes" in empty.json()["detail"]
    write_episode(episodes_dir(settings.clips_root, run_id), _episode(0))
    # Non-ASCII letters would reach the zip's name in a header, which is sent in latin-1.
    for bad_id in ("no spaces allowed", "no-version", "0000", "sepoa/café-v0",
                   "sepoa/\u30c7\u30fc\u30bf-v0", "sepoa/x-v\u0663"):
        bad = client.get(url, params={"dataset_id": bad_id}, headers=OPERATOR)
        # Minari's id pattern is in the OpenAPI document: the 422 names the parameter.
        assert bad.status_code == 422, bad_id
        assert bad.json()["detail"][0]["loc"] == ["query", "dataset_id"], bad_id
    bad = client.get(url, params={"format": "parquet"}, headers=OPERATOR)
    assert bad.status_code == 422 and bad.json()["detail"][0]["loc"] == ["query", "format"]
    damaged = episode_path(episodes_dir(settings.clips_root, run_id), 0)
    damaged.write_bytes(damaged.read_bytes()[:300])
    bad = client.get(url, headers=OPERATOR)
    assert bad.status_code == 422 and f"{damaged} cannot be read" in bad.json()["detail"]


def test_a_label_whose_episode_lands_while_the_export_starts_is_kept(
    client: TestClient, session: Session, settings: Settings, tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import rundata.dataset as dataset

    run_id, _ = running_run_with_queries(client, session, settings, n=1)
    store = episodes_dir(settings.clips_root, run_id)
    write_episode(store, _episode(0))
    answer(client, new_labeller(client, "alice"), "left")  # its pair points into episodes 0, 1
    read_labels = dataset.export_rows

    def as_a_round_lands(*args, **kwargs):  # type: ignore[no-untyped-def]
        write_episode(store, _episode(1))  # between the export's two reads
        return read_labels(*args, **kwargs)

    monkeypatch.setattr(dataset, "export_rows", as_a_round_lands)
    summary = dataset.write_dataset(session, run_id=run_id, clips_root=settings.clips_root,
                                    root=tmp_path)
    assert (summary.labels, summary.labels_left_out, summary.episodes) == (1, 0, 2)
