"""The label page when its API calls fail, or are refused for good, in a real headless
Chromium against a real server; failures are injected by intercepting the page's requests."""

from __future__ import annotations

import re
import time
from typing import Any

from web_helpers import LiveServer

from labelqueue import labels_for_queries

SHOWN = "#pairs .pair:not([hidden])"
ANSWERABLE = '[data-choice="left"]:not([disabled])'
PROGRESS = re.compile(r"/api/label/progress$")


def standing(live: LiveServer, query_id: int) -> list[Any]:
    with live.sessions() as session:
        return labels_for_queries(session, query_ids=[query_id])


def stored_soon(live: LiveServer, query_id: int, timeout: float = 5.0) -> list[Any]:
    deadline = time.monotonic() + timeout
    while not (labels := standing(live, query_id)) and time.monotonic() < deadline:
        time.sleep(0.05)
    return labels


def text_is(page: Any, selector: str, text: str, timeout: float = 10_000) -> None:
    page.wait_for_function("([s, t]) => document.querySelector(s).textContent.trim() === t",
                           arg=[selector, text], timeout=timeout)


def join(page: Any, live: LiveServer, run_id: int, participant: str, target: int) -> None:
    invite = live.api("POST", "/api/invites", json={"run_id": run_id, "target_answers": target})
    page.goto(f"{invite['url']}?participant={participant}")
    page.click("#join-start")
    page.wait_for_url(f"**/label?run={run_id}")


def calls(page: Any) -> list[str]:
    """The label API calls the page makes from now on, as "METHOD path?query"."""
    made: list[str] = []

    def note(request: Any) -> None:
        if "/api/label/" in request.url:
            made.append(f"{request.method} {request.url.split('/api', 1)[1]}")

    page.on("request", note)
    return made


def labelling(live: LiveServer, page: Any, runs: list[int], name: str) -> list[int]:
    """A new labeller `name` on its label page for a new run of three pairs, the first
    answerable; the pairs' query ids."""
    labeller = live.new_labeller(name)
    runs.append(run_id := live.new_human_run())
    queries = live.push_rendered_queries(run_id, 3)
    page.goto(f"{live.url}/label?run={run_id}#token={labeller.token}")
    page.wait_for_selector(ANSWERABLE)
    return queries


def test_an_answer_that_gets_no_answer_is_sent_again_and_counted_once(
    live: LiveServer, page: Any, runs: list[int]
) -> None:
    first, second, _ = labelling(live, page, runs, "hal-hang")
    # The answer reaches the server and is stored, but its response never comes back.
    page.route(f"**/api/label/{first}", lambda route: route.fetch(), times=1)
    made = calls(page)
    page.keyboard.press("1")
    page.wait_for_selector(f'{SHOWN}[data-query-id="{second}"]')
    assert len(stored_soon(live, first)) == 1
    # Given up after 15 s and said, not a page frozen with its answers disabled for good.
    page.wait_for_function("document.querySelector('#notice').textContent.includes('retrying')",
                           timeout=20_000)
    assert "no answer from the server" in page.inner_text("#notice")
    # Sent again: the server answers with the answer it stored; the page counts it once.
    text_is(page, "#count-session", "1", timeout=10_000)
    assert made.count(f"POST /label/{first}") == 2
    assert len(standing(live, first)) == 1
    # The next pair can be answered.
    page.wait_for_selector(ANSWERABLE)


def test_an_undo_that_gets_no_answer_is_sent_again_and_takes_the_answer_back_once(
    live: LiveServer, page: Any, runs: list[int]
) -> None:
    first, second, _ = labelling(live, page, runs, "kai-undo")
    made = calls(page)
    page.keyboard.press("1")
    page.wait_for_selector(f'{SHOWN}[data-query-id="{second}"]')
    text_is(page, "#count-session", "1")
    assert len(stored_soon(live, first)) == 1
    # The undo reaches the server and takes the answer back, but its response never comes back.
    page.route(f"**/api/label/{first}/withdraw", lambda route: route.fetch(), times=1)
    page.keyboard.press("u")
    page.wait_for_function("document.querySelector('#notice').textContent.includes('retrying')",
                           timeout=20_000)
    assert "no answer from the server" in page.inner_text("#notice")
    assert standing(live, first) == []
    # Sent again, it finds nothing left to take back: the pair the first try leased back is
    # shown again, the one it replaced waits, and the answer comes off the count once.
    page.wait_for_selector(f'{SHOWN}[data-query-id="{first}"]', timeout=10_000)
    assert "taken back" in page.inner_text("#notice")
    assert page.get_attribute(f'#pairs .pair[data-query-id="{second}"]', "hidden") is not None
    text_is(page, "#count-session", "0")
    assert made.count(f"POST /label/{first}/withdraw") == 2
    # The pair is answered again, and that answer stands.
    page.wait_for_selector(ANSWERABLE)
    page.keyboard.press("2")
    page.wait_for_selector(f'{SHOWN}[data-query-id="{second}"]')
    [kept] = stored_soon(live, first)
    assert kept.choice == "right"
    text_is(page, "#count-session", "1")


def test_a_progress_failing_at_load_is_asked_again_before_pairs_are_leased(
    live: LiveServer, page: Any, runs: list[int]
) -> None:
    runs.append(run_id := live.new_human_run())
    first, *_ = live.push_rendered_queries(run_id, 3)
    page.route(PROGRESS, lambda route: route.fulfill(status=500, json={"detail": "boom"}), times=1)
    made = calls(page)
    join(page, live, run_id, "P-progress", target=1)
    page.wait_for_selector(ANSWERABLE)
    # The progress came, after a failure, before the first pair was leased.
    asked = [call.split("?")[0] for call in made]
    assert asked[:3] == ["GET /label/progress", "GET /label/progress", "GET /label/next"]
    assert page.inner_text("#count-target").strip() == "· 0 of 1 towards the study"
    page.keyboard.press("1")
    # One answer reaches the target: the study's end, with the code, though pairs are left.
    page.wait_for_selector("#completion:not([hidden])")
    assert page.inner_text("#completion-code")
    assert page.is_hidden("#stage")
    assert len(stored_soon(live, first)) == 1


def test_a_progress_failing_after_an_answer_leaves_it_saved_and_undoable(
    live: LiveServer, page: Any, runs: list[int]
) -> None:
    runs.append(run_id := live.new_human_run())
    first, second, _ = live.push_rendered_queries(run_id, 3)
    join(page, live, run_id, "P-after", target=3)
    page.wait_for_selector(ANSWERABLE)
    text_is(page, "#count-target", "· 0 of 3 towards the study")
    page.route(PROGRESS, lambda route: route.fulfill(status=503, json={"detail": "busy"}),
               times=1)
    page.keyboard.press("1")
    page.wait_for_selector(f'{SHOWN}[data-query-id="{second}"]')
    text_is(page, "#count-session", "1")
    assert len(stored_soon(live, first)) == 1
    page.wait_for_selector("#undo:not([hidden])")
    assert "could not be saved" not in page.inner_text("#notice")
    # The progress is asked again on its own: the count towards the study comes.
    text_is(page, "#count-target", "· 1 of 3 towards the study", timeout=10_000)
    assert "could not be saved" not in page.inner_text("#notice")


def test_a_failed_preload_after_an_answer_asks_again_for_the_preload_only(
    live: LiveServer, page: Any, runs: list[int]
) -> None:
    first, second, third = labelling(live, page, runs, "ida-preload")
    page.route(re.compile(rf"/api/label/next\?.*ahead_of={second}(&|$)"),
               lambda route: route.fulfill(status=500, json={"detail": "boom"}), times=1)
    made = calls(page)
    page.keyboard.press("1")
    page.wait_for_selector(f'{SHOWN}[data-query-id="{second}"]')
    text_is(page, "#count-session", "1")
    # The preload is asked for again 5 s on, and the answer is not sent again.
    page.wait_for_selector(f'#pairs .pair[hidden][data-query-id="{third}"]', state="attached",
                           timeout=10_000)
    assert made.count(f"POST /label/{first}") == 1
    text_is(page, "#count-session", "1")
    # Taken back, the answer comes off the count it was added to.
    page.keyboard.press("u")
    page.wait_for_selector(f'{SHOWN}[data-query-id="{first}"]')
    text_is(page, "#count-session", "0")
    assert standing(live, first) == []


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
