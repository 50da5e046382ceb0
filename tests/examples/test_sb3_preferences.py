"""examples/sb3_preferences.py against a real server on a free port: a scripted labeller answers
its pairs on the label API, as a browser does, by their hidden true returns; the reward learned
from those answers orders held-out segments by their true returns, and SAC trains on it."""

from __future__ import annotations

import importlib.util
import json
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import httpx
import pytest
import uvicorn
from sqlalchemy.orm import Session, sessionmaker

from labelqueue import Query, make_engine, session_factory
from server.app import create_app
from server.settings import Settings

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "sb3_preferences.py"
OPERATOR = {"Authorization": "Bearer examples-operator-token-0123456789"}


@contextmanager
def served(settings: Settings) -> Iterator[str]:
    """The app behind uvicorn on a free port; its URL."""
    server = uvicorn.Server(uvicorn.Config(create_app(settings), host="127.0.0.1", port=0,
                                           log_level="error"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 30
        while not server.started:
            assert time.monotonic() < deadline, "uvicorn did not start"
            time.sleep(0.05)
        yield f"http://127.0.0.1:{server.servers[0].sockets[0].getsockname()[1]}"
    finally:
        server.should_exit = True
        thread.join(timeout=20)


class ScriptedLabeller(threading.Thread):
    """A labeller answering a run's pairs on the label API (the routes the label page calls) by
    the pairs' hidden true returns, which it reads from the queue database as the scripted
    teacher does: the label API never gives them."""

    def __init__(self, url: str, token: str, run_id: int, sessions: sessionmaker[Session]):
        super().__init__(daemon=True)
        self.url, self.run_id, self.sessions = url, run_id, sessions
        self.headers = {"Authorization": f"Bearer {token}"}
        self.stop = threading.Event()
        self.answered = 0

    def run(self) -> None:
        with httpx.Client(base_url=self.url, headers=self.headers, timeout=30) as http:
            while not self.stop.is_set():
                shown = http.get("/api/label/next", params={"run_id": self.run_id})
                if shown.status_code in (204, 429):  # none yet; asked too often (2/s)
                    self.stop.wait(float(shown.headers.get("retry-after", 0.5)))
                    continue
                shown.raise_for_status()
                pair = shown.json()
                with self.sessions() as session:
                    query = session.get(Query, pair["query_id"])
                    assert query is not None
                    first, second = query.first_segment_return, query.second_segment_return
                assert first is not None and second is not None
                better_left = (first > second) == pair["left_is_first"]
                choice = "equal" if first == second else "left" if better_left else "right"
                http.post(f"/api/label/{pair['query_id']}", json={
                    "choice": choice, "left_is_first": pair["left_is_first"],
                    "shown_at": datetime.now(UTC).isoformat()}).raise_for_status()
                self.answered += 1


@pytest.mark.slow
def test_sac_trains_on_a_reward_learned_from_answers_over_the_label_api(tmp_path: Path) -> None:
    settings = Settings(database_url=f"sqlite:///{tmp_path / 'queue.db'}", data_dir=tmp_path,
                        operator_token=OPERATOR["Authorization"].split()[1],
                        secret_key="examples-secret-key-0123456789")
    summary = tmp_path / "summary.json"
    temp = tmp_path / "tmp"
    temp.mkdir()
    with served(settings) as url:
        run = httpx.post(f"{url}/api/runs/external", headers=OPERATOR, json={
            "task": "gym:HalfCheetah-v5", "budget": 16,
            "instruction": "Which cheetah runs forward faster?"}).json()
        token = httpx.post(f"{url}/api/runs/{run['id']}/tokens", headers=OPERATOR).json()["token"]
        labeller = httpx.post(f"{url}/api/labellers", headers=OPERATOR,
                              json={"name": "scripted"}).json()["token"]
        engine = make_engine(settings.database_url)
        teacher = ScriptedLabeller(url, labeller, run["id"], session_factory(engine))
        teacher.start()
        try:
            done = subprocess.run(
                [sys.executable, str(EXAMPLE), "--preset", "tiny", "--url", url, "--token", token,
                 "--run", str(run["id"]), "--summary", str(summary)],
                cwd=ROOT, capture_output=True, text=True, timeout=300,
                env={**os.environ, "TMPDIR": str(temp)})
        finally:
            teacher.stop.set()
            teacher.join(timeout=30)
            engine.dispose()
        quality = httpx.get(f"{url}/api/quality/labellers", params={"run_id": run["id"]},
                            headers=OPERATOR).json()
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-4000:]
    assert not list(temp.glob("SB3-*"))  # SB3's logger left no folder behind
    result = json.loads(summary.read_text())
    # Every pair it asked was answered, on the label API, and trained on.
    assert result["pairs_asked"] == result["answers_used"] == teacher.answered == 16
    assert [(row["labeller_name"], row["answers"]) for row in quality] == [("scripted", 16)]
    # The learned reward orders segments nobody was asked about by their true returns.
    held_out = result["held_out"]
    assert held_out["segments"] >= 40 and held_out["pairs_in_true_order"] > 0.6
    # SAC trained on it: an update per step after the first round, on rewards that track the
    # environment's though it never saw them.
    assert result["sac_updates"] >= 2 * 300 - 2
    assert result["replay_reward_vs_true"] > 0.3


def _example(monkeypatch: pytest.MonkeyPatch, rendered: list[bool]) -> Any:
    """The example as a module, whose rendering check (its first step) notes in `rendered`
    that it ran."""
    spec = importlib.util.spec_from_file_location("sb3_preferences", EXAMPLE)
    assert spec is not None and spec.loader is not None
    example = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, example)  # where its dataclasses look
    spec.loader.exec_module(example)
    monkeypatch.setattr(example, "choose_backend", lambda say: rendered.append(True))
    return example


def test_a_server_it_cannot_use_or_a_bad_size_is_one_line_before_anything_runs(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """No server there, a token it refuses, clips of a size no clip has: the example says so
    in one line (SystemExit's message) at once, where it rendered and trained first and then
    ended in a traceback (a StudyError after half a minute of retries, a ValueError)."""
    rendered: list[bool] = []
    example = _example(monkeypatch, rendered)
    with socket.socket() as closed:
        closed.bind(("127.0.0.1", 0))
        nobody = f"http://127.0.0.1:{closed.getsockname()[1]}"
    settings = Settings(database_url=f"sqlite:///{tmp_path / 'queue.db'}", data_dir=tmp_path,
                        operator_token=OPERATOR["Authorization"].split()[1],
                        secret_key="examples-secret-key-0123456789")
    with served(settings) as url:
        run = httpx.post(f"{url}/api/runs/external", headers=OPERATOR, json={
            "task": "gym:HalfCheetah-v5", "budget": 16}).json()
        cases = [
            ([nobody, "run.1.not-a-token", "1"], [], [nobody, "gave up after 3 tries"]),
            ([url, "run.1.not-a-token", str(run["id"])], [], ["401"]),
            ([url, "x", "1"], ["--size", "7"], ["--size 7", "64, 512"]),
        ]
        for (where, token, run_id), more, words in cases:
            started = time.monotonic()
            with pytest.raises(SystemExit) as exited:
                example.main(["--preset", "tiny", "--url", where, "--token", token,
                              "--run", run_id, *more])
            said = str(exited.value.code)
            assert "\n" not in said and all(word in said for word in words), said
            assert time.monotonic() - started < 10, said
    assert rendered == []
