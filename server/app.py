"""The app factory: `create_app(settings)` -> FastAPI; `uvicorn server.app:app` serves it."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING, Any

from anyio import to_thread
from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi
from starlette.routing import BaseRoute

from labelqueue import make_engine, migrate, session_factory
from server import curves
from server.deps import LabelThreads, TokenCache
from server.errors import install_error_handlers
from server.export_job import ExportProcess
from server.middleware import HardeningMiddleware
from server.ratelimit import RateLimit
from server.routes import (
    browse,
    external,
    instructions,
    invites,
    label,
    labellers,
    pages,
    participants,
    quality,
    runs,
    stats,
    undo,
)
from server.routes import export as export_routes
from server.settings import Settings, settings_or_exit
from server.upload_sweep import sweep_forever

if TYPE_CHECKING:
    from fastapi.telemetry import TelemetryConfig


TELEMETRY_OFF: TelemetryConfig = {"tracing": False, "metrics": False, "logs": False}


def create_app(settings: Settings | None = None) -> FastAPI:
    """The API over the queue database `settings.database_url`, migrated at start-up; without
    `settings`, the environment's (`settings_or_exit`: a wrong one ends the process in one
    line)."""
    settings = settings or settings_or_exit()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        migrate(settings.database_url)
        engine = make_engine(settings.database_url, background_checkpoints=True)
        app.state.sessions = session_factory(engine)
        app.state.token_cache = TokenCache(settings.auth_cache_seconds)
        to_thread.current_default_thread_limiter().total_tokens = settings.threadpool_size
        # The label API's queue work (server.deps.LabellerCall.serve); other routes use AnyIO's.
        app.state.label_threads = LabelThreads(
            ThreadPoolExecutor(settings.label_thread_count, "label-api")
        )
        sweeper = asyncio.create_task(sweep_forever(app.state.sessions, settings))
        try:
            yield
        finally:
            sweeper.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sweeper
            app.state.label_threads.executor.shutdown()
            app.state.export_process.close()
            curves.close()
            engine.dispose()

    app = FastAPI(
        title="S-EPOA labelling",
        version="0.1.0",
        lifespan=lifespan,
        # FastAPI's native OpenTelemetry asks the global providers on every request whether
        # anyone listens; the app configures none, so it is off (settings.opentelemetry).
        telemetry=None if settings.opentelemetry else TELEMETRY_OFF,
    )
    app.state.settings = settings
    app.state.export_process = ExportProcess()  # started at the first export
    app.state.join_limit = RateLimit(settings.join_per_s, settings.join_burst)
    app.state.lease_limit = RateLimit(settings.lease_per_s, settings.lease_burst)
    install_error_handlers(app)
    app.add_middleware(HardeningMiddleware, limit=settings.body_limit_bytes,
                       uploads=(external.UPLOADS, settings.clip_upload_bytes))
    # The label API first: it is the busiest, and a request tries the routes in turn. Next
    # and submit are plain Starlette routes on the app's own router (an included router's
    # routes are matched twice per request), documented by `label.documented`.
    app.router.routes.extend(label.hot_routes)
    document_also(app, label.documented.routes)
    app.include_router(label.router)
    app.include_router(external.router)  # before runs: /api/runs/external
    app.include_router(runs.router)
    app.include_router(runs.workers_router)
    app.include_router(labellers.router)
    app.include_router(export_routes.router)
    app.include_router(stats.router)
    app.include_router(instructions.router)
    app.include_router(participants.router)  # before invites: /api/invites/verify-codes
    app.include_router(invites.router)
    app.include_router(undo.router)
    app.include_router(quality.router)
    app.include_router(browse.router)
    app.include_router(pages.router)
    app.include_router(participants.pages)
    app.mount("/static", pages.static_files(), name="static")

    @app.get("/healthz", tags=["health"])
    def healthz() -> dict[str, str]:
        return {"status": "ok"}

    return app


def document_also(app: FastAPI, routes: Sequence[BaseRoute]) -> None:
    """The app's OpenAPI document, with `routes` described first: FastAPI routes the app does
    not serve, declared for operations that plain Starlette routes serve."""

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = get_openapi(
                title=app.title, version=app.version, openapi_version=app.openapi_version,
                routes=[*routes, *app.routes],
            )
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def __getattr__(name: str) -> FastAPI:
    # `uvicorn server.app:app`: built on first access, so importing this module stays cheap.
    if name == "app":
        return create_app()
    raise AttributeError(name)
