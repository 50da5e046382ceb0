"""Where the label API's queue work runs (`LabellerCall.serve`): on the event loop when the
write lock is free and no request waits for the label thread, else on the label thread, so a
request never overtakes one queued there."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from server_helpers import bearer, new_labeller
from sqlalchemy.orm import Session, sessionmaker

from labelqueue import authenticate, make_engine, migrate, session_factory
from server.app import create_app
from server.deps import LabellerCall, LabelThreads
from server.settings import Settings


@pytest.fixture
def sessions(tmp_path: Path) -> Iterator[sessionmaker[Session]]:
    url = f"sqlite:///{tmp_path / 'queue.db'}"
    migrate(url)
    engine = make_engine(url)
    yield session_factory(engine)
    engine.dispose()


def thread_of_a_write(session: Session, **_: Any) -> str:
    """Opens a transaction that may write, as every label service does; the thread it ran on."""
    with session.begin():
        session.connection()
    return threading.current_thread().name


def serve_twice(call: LabellerCall, *, hold: threading.Event | None = None) -> list[str]:
    """Two requests at once: the first held on the label thread until `hold` is set."""
    assert call.threads is not None

    def held() -> str:
        assert hold is not None
        hold.wait(5)
        return threading.current_thread().name

    async def both() -> list[str]:
        first = (
            asyncio.ensure_future(call.threads.run(held)) if hold is not None else None
        )
        await asyncio.sleep(0.05)  # the first is now waiting on the label thread
        second = asyncio.ensure_future(call.serve(thread_of_a_write))
        await asyncio.sleep(0.05)
        if hold is not None:
            hold.set()
        done = [await second]
        return done if first is None else [await first, *done]

    return asyncio.run(both())


def labeller_call(sessions: sessionmaker[Session], threads: LabelThreads,
                  inline: bool = True) -> LabellerCall:
    settings = Settings(database_url="sqlite://", secret_key="label-threads-secret-0123")
    return LabellerCall(settings, sessions, 1, threads, inline)


def test_the_work_runs_on_the_event_loop_when_nothing_waits(
    sessions: sessionmaker[Session],
) -> None:
    with ThreadPoolExecutor(1, "label-api") as executor:
        [second] = serve_twice(labeller_call(sessions, LabelThreads(executor)))
    assert second == threading.current_thread().name  # asyncio.run's loop runs here


def test_the_work_queues_behind_a_request_waiting_for_the_label_thread(
    sessions: sessionmaker[Session],
) -> None:
    with ThreadPoolExecutor(1, "label-api") as executor:
        first, second = serve_twice(
            labeller_call(sessions, LabelThreads(executor)), hold=threading.Event()
        )
    assert first.startswith("label-api") and second.startswith("label-api")


def test_without_inline_the_work_always_runs_on_the_label_thread(
    sessions: sessionmaker[Session],
) -> None:
    with ThreadPoolExecutor(1, "label-api") as executor:
        [second] = serve_twice(labeller_call(sessions, LabelThreads(executor), inline=False))
    assert second.startswith("label-api")


@pytest.mark.parametrize("inline", [True, False])
def test_a_token_not_in_the_cache_is_checked_where_the_queue_work_runs(
    settings: Settings, monkeypatch: pytest.MonkeyPatch, inline: bool
) -> None:
    """Not on AnyIO's threads: behind a busy event loop, those checks made the slowest
    requests. Inline, the check (a read, which takes no lock) runs on the event loop."""
    checked_on: list[str] = []

    def recording(session: Session, *, token: str) -> Any:
        checked_on.append(threading.current_thread().name)
        return authenticate(session, token=token)

    monkeypatch.setattr("server.deps.authenticate", recording)
    settings = settings.model_copy(update={"label_inline": inline, "auth_cache_seconds": 0})
    with TestClient(create_app(settings)) as client:
        token = new_labeller(client, "alice")

        async def loop_thread() -> str:
            return threading.current_thread().name

        loop_name = client.portal.call(loop_thread)  # type: ignore[union-attr]
        for _ in range(2):  # no cache: each request checks the token
            assert client.get("/api/label/next", headers=bearer(token)).status_code == 204
    assert len(checked_on) == 2
    expected = loop_name if inline else "label-api_0"
    assert checked_on == [expected, expected]
