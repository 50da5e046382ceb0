"""The label page when its API calls fail, or are refused for good, in a real headless
Chromium against a real server; failures are injected by intercepting the page's requests."""

from __future__ import annotations

from typing import Any

from web_helpers import LiveServer


def calls(page: Any) -> list[str]:
    """The label API calls the page makes from now on, as "METHOD path?query"."""
    made: list[str] = []

    def note(request: Any) -> None:
        if "/api/label/" in request.url:
            made.append(f"{request.method} {request.url.split('/api', 1)[1]}")

    page.on("request", note)
    return made


def test_a_run_that_cannot_be_labelled_is_said_for_good_and_not_asked_again(
    live: LiveServer, page: Any
) -> None:
    labeller = live.new_labeller("jo-no-run")
    made = calls(page)
    page.goto(f"{live.url}/label?run=987654#token={labeller.token}")
    alert = page.locator("#notice[role=alert]")
    alert.wait_for()
    assert alert.inner_text() == "Run 987654 does not exist"
    page.wait_for_timeout(6000)  # past a retry's 5 s and a passing notice's 5 s
    assert alert.is_visible() and "987654" in alert.inner_text()
    assert len([call for call in made if call.startswith("GET /label/next")]) == 1

    page.goto(f"{live.url}/label?run=abc")
    alert.wait_for()
    page.wait_for_timeout(5500)
    assert alert.is_visible() and "is not a run id" in alert.inner_text()
