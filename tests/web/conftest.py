"""A real server (uvicorn in a subprocess, temp SQLite DB), real clips and a headless Chromium.

Debian's chromium is driven by the `playwright` package (never `playwright install`). A missing
browser fails these tests rather than skipping them: CI installs it (scripts/setup.sh
--for-tests).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from web_helpers import OPERATOR_TOKEN, SECRET_KEY, SEGMENT, TASK, LiveServer

from labelqueue import make_engine, session_factory
from server.settings import Settings

ROOT = Path(__file__).resolve().parents[2]
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
]


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


@pytest.fixture(scope="session")
def rendered_clips(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[Path, Path]]:
    """Three pairs of real h264 clips of a random-action cheetah episode, rendered off-screen
    from its stored physics states (as the worker renders query segments)."""
    from trainer.clips import ClipConfig, render_query_clips
    from trainer.envs import make_env
    from trainer.trajectories import Trajectory

    steps = 100
    rng = np.random.default_rng(0)
    with make_env(TASK, 0, episode_length=steps) as env:
        env.reset()
        states = []
        for _ in range(steps):
            states.append(env.physics_state())
            env.step(rng.uniform(-1, 1, env.action_dim).astype(np.float32))
        episode = Trajectory(
            id=0,
            obs=np.zeros((steps, env.obs_dim), np.float32),
            actions=np.zeros((steps, env.action_dim), np.float32),
            true_rewards=np.zeros(steps, np.float32),
            states=np.array(states),
            context=env.episode_context(),
            success=False,
        )
    out = tmp_path_factory.mktemp("clips")
    pairs = []
    with make_env(TASK, 0, episode_length=steps) as render_env:  # an env of its own for clips
        for i in range(3):
            names = render_query_clips(
                render_env,
                episode,
                10 * i,
                episode,
                40 + 10 * i,
                SEGMENT,
                out,
                f"pair{i}",
                ClipConfig(),
            )
            pairs.append((out / names[0], out / names[1]))
    return pairs


@pytest.fixture(scope="session")
def live(
    tmp_path_factory: pytest.TempPathFactory, rendered_clips: list[tuple[Path, Path]]
) -> Iterator[LiveServer]:
    data = tmp_path_factory.mktemp("server") / "data"
    settings = Settings(
        database_url=f"sqlite:///{data / 'queue.db'}",
        data_dir=data,
        operator_token=OPERATOR_TOKEN,
        secret_key=SECRET_KEY,
    )
    port = free_port()
    env = os.environ | {
        "SEPOA_DATABASE_URL": settings.database_url,
        "SEPOA_DATA_DIR": str(data),
        "SEPOA_OPERATOR_TOKEN": OPERATOR_TOKEN,
        "SEPOA_SECRET_KEY": SECRET_KEY,
    }
    command = [
        sys.executable,
        "-m",
        "uvicorn",
        "--factory",
        "server.app:create_app",
        "--host",
        "127.0.0.1",
        "--port",
        str(port),
        "--log-level",
        "warning",
    ]
    server = subprocess.Popen(command, cwd=ROOT, env=env, stderr=subprocess.PIPE, text=True)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                if httpx.get(url + "/healthz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if server.poll() is not None or time.monotonic() > deadline:
                server.kill()
                pytest.fail(f"the server did not start:\n{server.communicate()[1]}")
            time.sleep(0.1)
        engine = make_engine(settings.database_url)
        yield LiveServer(url, settings, session_factory(engine), rendered_clips)
        engine.dispose()
    finally:
        server.terminate()
        try:
            server.wait(timeout=10)
        except subprocess.TimeoutExpired:
            server.kill()


@pytest.fixture(scope="session")
def browser() -> Iterator[Any]:
    if not CHROMIUM.exists():
        pytest.fail(
            f"{CHROMIUM} is missing: the browser tests need Debian's chromium "
            "(apt-get install -y --no-install-recommends chromium; scripts/setup.sh "
            "--for-tests does)"
        )
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.fail("the browser tests need the `playwright` package: pip install -e '.[dev]'")
    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield chromium
        chromium.close()


@pytest.fixture
def page(browser: Any) -> Iterator[Any]:
    """A fresh browser context (its own localStorage) and page."""
    context = browser.new_context(viewport={"width": 1200, "height": 900})
    page = context.new_page()
    page.set_default_timeout(10_000)
    yield page
    context.close()


@pytest.fixture
def runs(live: LiveServer) -> Iterator[list[int]]:
    """Runs a test makes, stopped afterwards; other tests' open runs are stopped first, so that
    their leftover pairs do not reach this test's labellers."""
    for run in live.api("GET", "/api/runs"):
        if run["status"] in ("running", "paused", "queued"):
            live.stop_run(run["id"])
    made: list[int] = []
    yield made
    for run_id in made:
        live.stop_run(run_id)
