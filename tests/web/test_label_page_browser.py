"""The label page in a real headless Chromium against a real server: real h264 clips decode and
play in step, answers go by keyboard, the next pair is preloaded and swapped in, an empty queue
is waited on without a reload, and a refused token brings back the sign-in form."""

from __future__ import annotations

import json
import time
from datetime import timedelta
from typing import Any

import httpx
from web_helpers import OPERATOR_TOKEN, SECRET_RETURNS, LiveServer

from labelqueue import Label, labels_for_queries
from server import clips

SHOWN = "#pairs .pair:not([hidden])"
PRELOADED = "#pairs .pair[hidden]"

# Both videos of the pair element a selector names decode: they have a frame and a size.
DECODED = """selector => {
    const videos = [...document.querySelectorAll(`${selector} video`)];
    return videos.length === 2 && videos.every(v => v.readyState >= 2 && v.videoWidth > 0);
}"""
# Both videos of the shown pair have played past 0.3 s at the same time.
PLAYING = f"""() => {{
    const videos = [...document.querySelectorAll('{SHOWN} video')];
    return videos.length === 2 && videos.every(v => v.currentTime > 0.3 && !v.paused);
}}"""
# The largest gap between the two clips' times over ~1 s of playback, in seconds.
MAX_GAP = f"""() => new Promise(done => {{
    const [a, b] = document.querySelectorAll('{SHOWN} video');
    let gap = 0;
    const until = performance.now() + 1000;
    (function sample() {{
        if (!a.paused && !b.paused && !a.seeking && !b.seeking)
            gap = Math.max(gap, Math.abs(a.currentTime - b.currentTime));
        if (performance.now() < until) requestAnimationFrame(sample); else done(gap);
    }})();
}})"""


def stored_label(live: LiveServer, query_id: int, timeout: float = 5.0) -> Label:
    deadline = time.monotonic() + timeout
    while True:
        with live.sessions() as session:
            labels = labels_for_queries(session, query_ids=[query_id])
        if labels or time.monotonic() > deadline:
            assert len(labels) == 1, f"query {query_id} has labels {labels}"
            return labels[0]
        time.sleep(0.05)


def shown_query(page: Any) -> int:
    return int(page.get_attribute(SHOWN, "data-query-id"))


def test_a_labeller_watches_both_clips_and_answers_with_the_keyboard(
    live: LiveServer, page: Any
) -> None:
    alice = live.new_labeller("alice")
    run_id = live.new_human_run()
    first, second, third = live.push_rendered_queries(run_id, 3)

    page.goto(f"{live.url}/label#token={alice.token}")
    page.wait_for_function(DECODED, arg=SHOWN)
    assert shown_query(page) == first
    # The token moved from the address bar to this browser's storage.
    assert "token" not in page.url
    assert page.evaluate("localStorage.getItem('sepoa.labeller-token')") == alice.token

    # Nothing can be answered before both clips have played through once: a key does nothing.
    assert page.is_disabled('[data-choice="right"]')
    page.keyboard.press("2")
    # Both clips decode and play, driven by one clock.
    page.wait_for_function(PLAYING)
    assert page.evaluate(MAX_GAP) < 0.2
    page.wait_for_selector('[data-choice="left"]:not([disabled])')

    # The next pair is leased and already decoded, hidden, while this one is shown.
    page.wait_for_function(DECODED, arg=PRELOADED)
    assert int(page.get_attribute(PRELOADED, "data-query-id")) == second
    left_is_first = page.get_attribute(SHOWN, "data-left-is-first") == "true"
    assert left_is_first == clips.left_is_first(
        settings=live.settings, query_id=first, labeller_id=alice.id
    )
    assert page.text_content("#count-session") == "0"

    page.keyboard.press("ArrowLeft")
    # Swapped in at once, already decoded: no waiting for the answer to be stored.
    assert shown_query(page) == second
    assert page.evaluate(DECODED, SHOWN)

    label = stored_label(live, first)
    assert (label.choice, label.labeller_id, label.source) == ("left", alice.id, "human")
    assert label.left_is_first == left_is_first
    assert label.answer == ("first" if left_is_first else "second")
    assert label.shown_at is not None
    assert timedelta(seconds=1) < label.answered_at - label.shown_at < timedelta(seconds=30)
    page.wait_for_function("document.querySelector('#count-session').textContent === '1'")
    assert page.text_content("#count-total") == "1"
    # The operator's export lists the answer as given, with the sides it was shown on.
    exported = httpx.get(f"{live.url}/api/export?format=jsonl&run_id={run_id}",
                         headers={"Authorization": f"Bearer {OPERATOR_TOKEN}"})
    [row] = [json.loads(line) for line in exported.text.splitlines()]
    assert (row["query_id"], row["labeller_name"], row["choice"]) == (first, "alice", "left")
    assert row["left_segment"] == ("first" if left_is_first else "second")

    # The pair after that is preloaded in turn; the first one is gone from the page.
    page.wait_for_selector(f'{PRELOADED}[data-query-id="{third}"]', state="attached")
    assert page.query_selector(f'[data-query-id="{first}"]') is None
    # No ground truth reached the page.
    html = page.content()
    assert not [value for value in SECRET_RETURNS.values() if str(value) in html]


def test_an_empty_queue_is_waited_on_and_new_work_appears_without_a_reload(
    live: LiveServer, page: Any
) -> None:
    bob = live.new_labeller("bob")
    run_id = live.new_human_run()

    page.goto(f"{live.url}/label?run={run_id}#token={bob.token}")
    page.wait_for_selector("#waiting", state="visible")
    assert page.is_hidden("#stage")
    page.evaluate("window.sameDocument = true")

    (query_id,) = live.push_rendered_queries(run_id, 1)
    page.wait_for_selector(f'{SHOWN}[data-query-id="{query_id}"]', timeout=6000)
    page.wait_for_function(DECODED, arg=SHOWN)
    assert page.is_hidden("#waiting")
    assert page.evaluate("window.sameDocument") is True  # picked up by polling, not a reload


def test_a_refused_token_brings_back_the_sign_in_form(live: LiveServer, page: Any) -> None:
    carol = live.new_labeller("carol")
    run_id = live.new_human_run()

    page.goto(f"{live.url}/label?run={run_id}#token=not-a-real-token")
    page.wait_for_selector("#signin", state="visible")
    assert "invalid or revoked" in page.text_content("#signin-error")
    assert page.is_hidden("#app")
    assert page.evaluate("localStorage.getItem('sepoa.labeller-token')") is None

    page.fill("#signin-token", carol.token)
    page.click("#signin-form button[type=submit]")
    page.wait_for_selector("#waiting", state="visible")
    assert page.is_hidden("#signin")
