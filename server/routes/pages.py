"""The HTML pages (Jinja2 templates in web/templates) and their static files (web/static).

A page is a shell without data and needs no token: the bearer token lives in the browser
(localStorage), and the page's JS sends it with every API call. So any run id renders a page,
and an unknown run shows the API's 404 message there (an id no run can have, such as -5, its
422), once: the page stops refreshing.
"""

from __future__ import annotations

import os
from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles
from fastapi.templating import Jinja2Templates
from starlette.responses import Response
from starlette.types import Scope

from runvocab.clip_format import CLIP_SIZES
from runvocab.names import ALGOS, SIZE_PRESETS, all_tasks

ALGO_TITLES = {"pebble": "PEBBLE (fastest start)", "sepoa": "S-EPOA (pretrains first)",
               "surf": "SURF", "rune": "RUNE", "rime": "RIME", "sac": "SAC (true reward)"}
"""the new-run form's algorithms: PEBBLE first, the one whose first pairs come soonest (a
demo's choice); S-EPOA pretrains skills before anything else"""
assert set(ALGO_TITLES) == set(ALGOS)
WEB_DIR = Path(__file__).resolve().parents[2] / "web"
templates = Jinja2Templates(directory=WEB_DIR / "templates")
router = APIRouter(include_in_schema=False)


class RevalidatedStaticFiles(StaticFiles):
    """Static files the browser re-checks on every use (a 304 when unchanged), so a page never
    runs yesterday's JS against today's API after an upgrade."""

    def file_response(
        self,
        full_path: str | os.PathLike[str],
        stat_result: os.stat_result,
        scope: Scope,
        status_code: int = 200,
    ) -> Response:
        response = super().file_response(full_path, stat_result, scope, status_code)
        response.headers["Cache-Control"] = "no-cache"
        return response


def static_files() -> StaticFiles:
    """What the app mounts at /static."""
    return RevalidatedStaticFiles(directory=WEB_DIR / "static")


def page(request: Request, template: str, **context: object) -> HTMLResponse:
    return templates.TemplateResponse(request, template, context)


@router.get("/", response_class=HTMLResponse)
def home(request: Request) -> HTMLResponse:
    return page(request, "home.html", nav="home")


@router.get("/label", response_class=HTMLResponse)
def label_page(request: Request) -> HTMLResponse:
    """The labeller's page; `?run=<id>` labels one run only (read by the page's JS)."""
    return page(request, "label.html", nav="label")


@router.get("/runs", response_class=HTMLResponse)
def runs_page(request: Request) -> HTMLResponse:
    """The runs list and the new-run form, whose choices are the run vocabulary's names."""
    return page(request, "runs.html", nav="runs", tasks=all_tasks(), algos=ALGO_TITLES,
                presets=SIZE_PRESETS, clip_sizes=CLIP_SIZES)


@router.get("/labels", response_class=HTMLResponse)
def labels_page(request: Request) -> HTMLResponse:
    """The label browser (operators): stored labels with filters, each with its two clips, the
    answer, the shadow label and the true returns (`?run=`, `?labeller=`, ... set filters)."""
    return page(request, "labels.html", nav="labels")


@router.get("/runs/{run_id}", response_class=HTMLResponse)
def run_page(request: Request, run_id: int) -> HTMLResponse:
    return page(request, "run.html", nav="runs", run_id=run_id)
