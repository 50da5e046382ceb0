"""The HTML pages: served without a token (their JS loads the data), linking static files that
are served, and holding no ground truth."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient
from server_helpers import running_run_with_queries
from sqlalchemy.orm import Session

from server.settings import Settings

PAGES = ["/", "/label", "/label?run=1", "/runs", "/runs/1", "/runs/999999"]
CONTENT_TYPES = {".js": "text/javascript", ".css": "text/css"}
# Names of the hidden query columns: the labeller's page has no business with any of them.
HIDDEN_FIELDS = ["_return", "model_p", "shadow", "distinguishable", "score"]


def static_links(client: TestClient, html: str) -> set[str]:
    """Every /static file a page loads, and every module those files import, recursively."""
    found: set[str] = set()
    todo = re.findall(r'(?:src|href)="(/static/[^"]+)"', html)
    while todo:
        path = todo.pop()
        if path in found:
            continue
        found.add(path)
        if path.endswith(".js"):
            text = client.get(path).text
            folder = path.rsplit("/", 1)[0]
            todo += [f"{folder}/{name}" for name in re.findall(r'from "\./([\w.-]+)"', text)]
    return found


@pytest.mark.parametrize("path", PAGES)
def test_each_page_is_html_whose_static_files_are_served(client: TestClient, path: str) -> None:
    page = client.get(path)  # no token: the browser keeps it, and the page's JS sends it
    assert page.status_code == 200
    assert page.headers["content-type"].startswith("text/html")
    assert '<link rel="stylesheet" href="/static/style.css">' in page.text
    links = static_links(client, page.text)
    if path != "/":
        assert any(link.endswith(".js") for link in links), "the page loads its script"
    for link in links:
        response = client.get(link)
        assert response.status_code == 200, link
        suffix = link[link.rindex(".") :]
        assert response.headers["content-type"].startswith(CONTENT_TYPES[suffix]), link
        # Re-checked by the browser on every use, so an upgrade never runs stale JS.
        assert response.headers["cache-control"] == "no-cache"


def test_pages_and_their_scripts_hold_no_ground_truth(
    client: TestClient, session: Session, settings: Settings, secret_returns: dict[str, float]
) -> None:
    running_run_with_queries(client, session, settings)  # ground truth now in the database
    for path in PAGES:
        page = client.get(path).text
        texts = [page] + [client.get(link).text for link in static_links(client, page)]
        for text in texts:
            assert not [v for v in secret_returns.values() if str(v) in text], path

    label_page = client.get("/label").text
    for link in static_links(client, label_page) - {"/static/style.css"}:
        script = client.get(link).text
        assert not [name for name in HIDDEN_FIELDS if name in script], link


def test_the_label_page_shows_each_answer_with_its_keys(client: TestClient) -> None:
    page = client.get("/label").text
    keys = {
        "left": ["←", "1"],
        "right": ["→", "2"],
        "equal": ["↑", "3"],
        "cant_tell": ["↓", "4"],
        "skip": ["S", "5"],
    }
    for choice, expected in keys.items():
        button = re.search(rf'<button[^>]*data-choice="{choice}"[^>]*>(.*?)</button>', page, re.S)
        assert button is not None, choice
        assert re.findall(r"<kbd>(.*?)</kbd>", button[1]) == expected
        assert "disabled" in button[0]  # until both clips have played through once
    assert 'id="waiting"' in page and "Waiting for the trainer" in page


def test_a_run_page_renders_for_any_run_id_and_hands_it_to_its_script(
    client: TestClient,
) -> None:
    page = client.get("/runs/424242").text  # no such run: the page's JS shows the API's 404
    assert 'data-run-id="424242"' in page
    assert client.get("/runs/not-a-number").status_code == 422


def test_static_files_stay_inside_the_web_folder(client: TestClient) -> None:
    assert client.get("/static/../../server/settings.py").status_code == 404
    assert client.get("/static/%2e%2e/templates/base.html").status_code == 404
    assert client.get("/static/no-such-file.js").status_code == 404
