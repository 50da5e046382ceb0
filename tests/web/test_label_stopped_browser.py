"""A label page that has stopped labelling (a pause mid-session, the study complete, signed
out), in a real headless Chromium against a real server: what its keys and buttons still do."""

from __future__ import annotations

import time
from typing import Any

from web_helpers import LiveServer

from labelqueue import LabellerPause, labels_for_queries

SHOWN = "#pairs .pair:not([hidden])"
ANSWERABLE = '[data-choice="left"]:not([disabled])'


def standing(live: LiveServer, query_id: int, timeout: float = 5.0) -> list[Any]:
    deadline = time.monotonic() + timeout
    while True:
        with live.sessions() as session:
            labels = labels_for_queries(session, query_ids=[query_id])
        if labels or time.monotonic() > deadline:
            return labels
        time.sleep(0.05)


def test_a_labeller_paused_mid_session_keeps_the_pause_said_and_nothing_answers(
    live: LiveServer, page: Any, runs: list[int]
) -> None:
    kim = live.new_labeller("kim-paused")
    runs.append(run_id := live.new_human_run(config={"feedback.gold_min_accuracy": 0.8}))
    live.push_rendered_queries(run_id, 1)  # nothing to preload: the page asks every 2 s
    page.goto(f"{live.url}/label?run={run_id}#token={kim.token}")
    page.wait_for_selector("#flag:not([disabled])")
    with live.sessions() as session:  # as three wrong answers on check pairs would have done
        session.add(LabellerPause(run_id=run_id, labeller_id=kim.id, gold_answers=3,
                                  gold_correct=0))
        session.commit()
    alert = page.locator("#notice[role=alert]")
    alert.wait_for()
    said = alert.inner_text()
    assert said.startswith("Paused: 0 of your 3 answers on check pairs")
    assert page.is_hidden("#stage")
    assert page.is_disabled("#flag")
    assert all(page.eval_on_selector_all("[data-choice]", "bs => bs.map(b => b.disabled)"))
    page.keyboard.press("f")  # no pair: no flag dialog, no "thank you"
    page.keyboard.press("u")  # no "no answer to take back" in place of the pause
    page.wait_for_timeout(300)
    assert page.evaluate("document.querySelector('#flag-dialog').open") is False
    assert alert.inner_text() == said
    page.wait_for_timeout(5500)  # longer than a passing notice stays
    assert alert.is_visible() and alert.inner_text() == said


def test_the_answer_that_completes_a_study_cannot_be_taken_back(
    live: LiveServer, page: Any, runs: list[int]
) -> None:
    runs.append(run_id := live.new_human_run())
    first, *_ = live.push_rendered_queries(run_id, 3)  # pairs are left after the target
    invite = live.api("POST", "/api/invites", json={"run_id": run_id, "target_answers": 1})
    page.goto(f"{invite['url']}?participant=P-last")
    page.click("#join-start")
    page.wait_for_url(f"**/label?run={run_id}")
    page.wait_for_selector(ANSWERABLE)
    page.keyboard.press("1")
    page.wait_for_selector("#completion:not([hidden])")
    code = page.inner_text("#completion-code")
    assert page.is_hidden("#undo")
    page.keyboard.press("Backspace")
    page.keyboard.press("u")
    page.wait_for_timeout(1000)
    assert [label.choice for label in standing(live, first)] == ["left"]
    assert page.is_visible("#completion") and page.inner_text("#completion-code") == code
    assert page.is_hidden("#stage")
    checked = live.api("POST", "/api/invites/verify", json={"code": code})
    assert (checked["participant"], checked["counted"]) == ("P-last", 1)


def test_a_token_typed_after_signing_out_is_typed_not_taken_as_keys(
    live: LiveServer, page: Any, runs: list[int]
) -> None:
    lee = live.new_labeller("lee-signs-out")
    runs.append(run_id := live.new_human_run())
    live.push_rendered_queries(run_id, 2)
    page.goto(f"{live.url}/label?run={run_id}#token={lee.token}")
    page.wait_for_selector("#flag:not([disabled])")
    page.click("#sign-out")
    page.wait_for_selector("#signin", state="visible")
    page.click("#signin-token")
    page.keyboard.type("7.abcfdeF")  # f and F: the flag shortcut; s, 1, u: answers and Undo
    page.keyboard.type(" s1u")
    assert page.input_value("#signin-token") == "7.abcfdeF s1u"
    assert page.evaluate("document.querySelector('#flag-dialog').open") is False
    assert page.evaluate("document.activeElement.id") == "signin-token"
