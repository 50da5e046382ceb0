"""What the browser tests share: the live server's handle and the worker's and operator's
moves on it (fixtures are in conftest.py)."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
from hidden_truth import SECRET_RETURNS
from sqlalchemy.orm import Session, sessionmaker

from labelqueue import claim_run, push_queries, set_clips
from server.settings import Settings

OPERATOR_TOKEN = "web-test-operator-token-0123456789"
SECRET_KEY = "web-test-secret-key-0123456789"
TASK = "dmc:cheetah_run"
SEGMENT = 40  # steps per clip: 1.2 s at 100/3 fps, so a clip plays through quickly


@dataclass(frozen=True)
class Labeller:
    id: int
    token: str


@dataclass
class LiveServer:
    """The running server, and what a trainer and an operator would do to its database."""

    url: str
    settings: Settings
    sessions: sessionmaker[Session]
    clips: list[tuple[Path, Path]]

    def api(self, method: str, path: str, **kwargs: Any) -> Any:
        headers = {"Authorization": f"Bearer {OPERATOR_TOKEN}"}
        response = httpx.request(method, self.url + path, headers=headers, timeout=30, **kwargs)
        assert response.is_success, response.text
        return response.json()

    def api_text(self, method: str, path: str) -> list[Any]:
        """A JSON-lines answer (an export) as its rows."""
        headers = {"Authorization": f"Bearer {OPERATOR_TOKEN}"}
        response = httpx.request(method, self.url + path, headers=headers, timeout=30)
        assert response.is_success, response.text
        return [json.loads(line) for line in response.text.splitlines()]

    def new_labeller(self, name: str) -> Labeller:
        created = self.api("POST", "/api/labellers", json={"name": name})
        return Labeller(id=created["id"], token=created["token"])

    def new_human_run(self, **fields: Any) -> int:
        """A human-taught run, claimed by a worker (so its queries can be labelled)."""
        run_id: int = self.api(
            "POST",
            "/api/runs",
            json={"task": TASK, "algo": "sepoa", "budget": 10, "preset": "tiny"} | fields,
        )["id"]
        with self.sessions() as session:
            claimed = claim_run(session, worker_id=f"web-test-worker-{run_id}")
        # The oldest queued run is claimed: a test that queues a run must stop it again.
        assert claimed is not None and claimed.id == run_id, "another run is still queued"
        return run_id

    def push_rendered_queries(self, run_id: int, n: int, needs: int = 1) -> list[int]:
        """`n` queries pushed as a worker would, each with two real clips and wanting `needs`
        labellers' answers (the run's `feedback.labels_per_query`); their ids."""
        specs = [
            {
                "round": 0,
                "position": i,
                "segment_length": SEGMENT,
                "first_trajectory": 0,
                "first_start": 10 * i,
                "second_trajectory": 1,
                "second_start": 40 + 10 * i,
                "needs_labels": needs,
                **SECRET_RETURNS,
            }
            for i in range(n)
        ]
        with self.sessions() as session:
            ids = push_queries(session, run_id=run_id, queries=specs)
            for k, query_id in enumerate(ids):
                files = self.clips[k % len(self.clips)]
                keys = [f"run{run_id}/q{query_id}-{side}.mp4" for side in ("first", "second")]
                for key, source in zip(keys, files, strict=True):
                    target = self.settings.clips_root / key
                    target.parent.mkdir(parents=True, exist_ok=True)
                    shutil.copyfile(source, target)
                set_clips(session, query_id=query_id, first_clip=keys[0], second_clip=keys[1])
        return ids

    def stop_run(self, run_id: int) -> None:
        """Out of the way of later tests: a stopped run's queries are offered to no one."""
        if self.api("GET", f"/api/runs/{run_id}")["status"] in ("stopped", "finished", "failed"):
            return
        if self.api("POST", f"/api/runs/{run_id}/stop")["status"] == "stopping":
            self.api("POST", f"/api/runs/{run_id}/stop?force=true")  # no worker to finish it
