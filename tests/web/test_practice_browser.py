"""The practice round in a real headless Chromium: a run with `feedback.practice_pairs` 2 shows
its gold pairs first, marked "Practice pair i of 2"; each answer is explained (right or not, and
which clip the true reward prefers, by a ratio) until Continue; then the real pairs come, with
no mark; the practice answers are stored as such and shown in the labeller's quality row."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

from sqlalchemy import update
from web_helpers import OPERATOR_TOKEN, SECRET_RETURNS, LiveServer

from labelqueue import labels_for_queries
from labelqueue.gold import GOLD_NEEDS_LABELS
from labelqueue.models import Query

SHOWN = "#pairs .pair:not([hidden])"
DECODED = """selector => {
    const videos = [...document.querySelectorAll(`${selector} video`)];
    return videos.length === 2 && videos.every(v => v.readyState >= 2 && v.videoWidth > 0);
}"""


def screenshot(page: Any, name: str, selector: str | None = None) -> None:
    folder = os.environ.get("SEPOA_SCREENSHOT_DIR")
    if folder:
        target = page.locator(selector) if selector else page
        target.screenshot(path=str(Path(folder) / name))


def answer_when_ready(page: Any, key: str) -> None:
    page.wait_for_selector('[data-choice="left"]:not([disabled])', timeout=15_000)
    page.keyboard.press(key)


def test_a_practice_round_is_explained_then_real_pairs_follow(
    live: LiveServer, page: Any
) -> None:
    fay = live.new_labeller("fay-practice")
    run_id = live.new_human_run(config={"feedback.practice_pairs": 2})
    real, gold1, gold2 = live.push_rendered_queries(run_id, 3)
    with live.sessions() as session:  # two of them the run's practice pairs: gold pairs a
        # push reserves so (labelqueue.practice)
        session.execute(update(Query).where(Query.id.in_([gold1, gold2]))
                        .values(gold=True, needs_labels=GOLD_NEEDS_LABELS, practice=True))
        session.commit()
    try:
        page.goto(f"{live.url}/label?run={run_id}#token={fay.token}")
        page.wait_for_function(DECODED, arg=SHOWN)
        # The gold pairs come first, marked as practice.
        assert int(page.get_attribute(SHOWN, "data-query-id")) == gold1
        page.wait_for_selector("#practice-banner:not([hidden])")
        assert "Practice pair 1 of 2" in page.inner_text("#practice-banner")

        # First segment (return 987.125) against the second (-654.375): "left" is right when
        # the first is on the left.
        first_left = page.get_attribute(SHOWN, "data-left-is-first") == "true"
        answer_when_ready(page, "ArrowLeft")
        page.wait_for_selector("#practice-dialog[open]")
        verdict = page.inner_text("#practice-verdict")
        assert verdict.startswith("Right" if first_left else "Not this time")
        assert "you answered “left”" in verdict
        better = "left" if first_left else "right"
        explanation = page.inner_text("#practice-explanation")
        assert explanation.startswith(f"The {better} clip is better")
        assert "lost some" in explanation  # the other segment's return is below zero
        assert not any(str(v) in page.content() for v in SECRET_RETURNS.values())
        assert "Practice pair 1 of 2" in page.inner_text("#practice-title")
        assert page.is_hidden("#stage")  # a screen of its own: the next pair waits behind it
        screenshot(page, "label-page-practice.png", "#practice-dialog")
        # Keys do not answer the pair behind the dialog; Enter continues.
        page.keyboard.press("ArrowRight")
        page.keyboard.press("Enter")
        page.wait_for_selector("#practice-dialog:not([open])", state="attached")

        assert int(page.get_attribute(SHOWN, "data-query-id")) == gold2
        assert "Practice pair 2 of 2" in page.inner_text("#practice-banner")
        answer_when_ready(page, "ArrowUp")  # "equally good": wrong, the returns differ
        page.wait_for_selector("#practice-dialog[open]")
        assert page.inner_text("#practice-verdict").startswith("Not this time")
        assert "last practice pair" in page.inner_text("#practice-next")
        page.click("#practice-continue")

        # The real pair: no mark, no explanation after it.
        page.wait_for_selector(f'{SHOWN}[data-query-id="{real}"]')
        assert page.is_hidden("#practice-banner")
        answer_when_ready(page, "ArrowLeft")
        page.wait_for_function("document.querySelector('#count-session').textContent === '3'")
        page.wait_for_timeout(300)
        assert page.is_hidden("#practice-dialog")

        deadline = time.monotonic() + 5
        while True:
            with live.sessions() as session:
                labels = {lab.query_id: lab
                          for lab in labels_for_queries(session, query_ids=[gold1, gold2, real])}
            if len(labels) == 3 or time.monotonic() > deadline:
                break
            time.sleep(0.05)
        assert [labels[q].practice for q in (gold1, gold2, real)] == [True, True, False]

        # The labeller's quality row shows the practice round apart.
        page.goto(f"{live.url}/runs?quality_run={run_id}#token={OPERATOR_TOKEN}")
        cell = page.wait_for_selector('#quality-body tr[data-labeller="fay-practice"] td.practice')
        assert cell.inner_text() == f"{1 if first_left else 0}/2 right"
    finally:
        live.stop_run(run_id)


def test_the_answer_time_starts_once_the_pair_is_in_view_after_the_explanation(
    live: LiveServer, page: Any
) -> None:
    gil = live.new_labeller("gil-practice")
    run_id = live.new_human_run(config={"feedback.practice_pairs": 1})
    real, gold = live.push_rendered_queries(run_id, 2)
    with live.sessions() as session:
        session.execute(update(Query).where(Query.id == gold)
                        .values(gold=True, needs_labels=GOLD_NEEDS_LABELS, practice=True))
        session.commit()
    try:
        page.goto(f"{live.url}/label?run={run_id}#token={gil.token}")
        page.wait_for_function(DECODED, arg=SHOWN)
        assert int(page.get_attribute(SHOWN, "data-query-id")) == gold
        answer_when_ready(page, "ArrowLeft")
        page.wait_for_selector("#practice-dialog[open]")
        page.wait_for_timeout(4000)  # reading the explanation; the real pair waits behind it
        page.keyboard.press("Enter")
        shown = time.monotonic()
        page.wait_for_selector("#practice-dialog:not([open])", state="attached")
        assert int(page.get_attribute(SHOWN, "data-query-id")) == real
        answer_when_ready(page, "ArrowLeft")
        on_screen = time.monotonic() - shown
        deadline = time.monotonic() + 5
        while True:
            with live.sessions() as session:
                labels = labels_for_queries(session, query_ids=[real])
            if labels or time.monotonic() > deadline:
                break
            time.sleep(0.05)
        [label] = labels
        answer_time = (label.answered_at - label.shown_at).total_seconds()
        # The time it was in view, not the time spent reading the practice explanation.
        assert answer_time < on_screen + 1.0, (answer_time, on_screen)
    finally:
        live.stop_run(run_id)
