"""The worker trains the configuration stored with a run when it was created, not the presets
of the day it is claimed; a run stored without one (before migration 0015) is resolved as it
always was, and still trains."""

from __future__ import annotations

import json

import pytest
from sqlalchemy import update
from worker_helpers import RUN, database, run_row, worker_config

from labelqueue import Run, RunStatus, create_run
from labelqueue.run_config import run_config
from runvocab.config import PRESETS, to_dict
from trainer.worker import run_worker

HOST_FIELDS = ("run_dir", "threads", "device")
SHORT = RUN | {"teacher": "scripted", "config": RUN["config"] | {"steps": 500}}


def forget_resolved(sessions, run_id: int, **fields) -> None:
    """Make the row a run stored before resolved configurations were kept."""
    with sessions() as session:
        session.execute(update(Run).where(Run.id == run_id)
                        .values(resolved_config=None, **fields))
        session.commit()


def trained_config(data, run_id: int) -> dict:
    stored = json.loads((data / "runs" / f"run-{run_id}" / "config.json").read_text())
    stored["skill"].pop("snapshot_dir")
    return {name: value for name, value in stored.items() if name not in HOST_FIELDS}


def test_a_stored_run_trains_its_stored_config_and_an_old_one_todays_presets(
        tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    url, sessions = database(tmp_path)
    with sessions() as session:
        kept = create_run(session, name="kept", **SHORT)
        old = create_run(session, name="old", **SHORT)
    forget_resolved(sessions, old.id)
    monkeypatch.setitem(PRESETS, "tiny", PRESETS["tiny"] | {"sac.hidden_dim": 16})
    data = tmp_path / "data"
    assert run_worker(worker_config(url, data)) == 2

    for run in (kept, old):
        assert run_row(sessions, run.id).status is RunStatus.FINISHED
    stored = to_dict(run_config(run_row(sessions, kept.id)))
    stored["skill"].pop("snapshot_dir")
    expected = json.loads(json.dumps(
        {name: value for name, value in stored.items() if name not in HOST_FIELDS}))
    assert trained_config(data, kept.id) == expected
    assert trained_config(data, kept.id)["sac"]["hidden_dim"] == 32  # the preset when stored
    assert trained_config(data, old.id)["sac"]["hidden_dim"] == 16  # resolved when claimed


def test_an_old_run_that_cannot_start_fails_with_the_reason(tmp_path) -> None:
    url, sessions = database(tmp_path)
    with sessions() as session:
        typo = create_run(session, name="typo", **RUN)
        bad = create_run(session, name="bad", **RUN)
    forget_resolved(sessions, typo.id, task="dmc:cheetah_rnu")
    forget_resolved(sessions, bad.id, config={"steps": "many"})
    run_worker(worker_config(url, tmp_path / "data"))
    assert run_row(sessions, typo.id).status is RunStatus.FAILED
    assert "cheetah_run" in (run_row(sessions, typo.id).error or "")  # did you mean
    assert run_row(sessions, bad.id).error == (
        "ConfigError: config field 'steps' takes int, got 'many'")
