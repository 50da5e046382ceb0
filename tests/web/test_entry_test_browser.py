"""An invite's entry test in a real headless Chromium on a phone-sized screen: the operator sets
it in the invite form (and sees it in the list of links); a participant who gets too few of
the run's practice pairs right is told so after the last one (no Undo after a practice answer:
the test measures the first try), then shown that their practice is over, that they did not
pass, and that there is no code; no more pairs come, and the participants page says they are
not to be paid.

With SEPOA_SCREENSHOT_DIR set, the message is saved there (docs/entry-test-failed-phone.png)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import update
from web_helpers import OPERATOR_TOKEN, LiveServer

from labelqueue.gold import GOLD_NEEDS_LABELS
from labelqueue.models import Query

PHONE = {"width": 390, "height": 844}
SHOWN = "#pairs .pair:not([hidden])"
ANSWERABLE = '[data-choice="left"]:not([disabled])'


@pytest.fixture
def run_id(live: LiveServer) -> Iterator[int]:
    """A human-taught run with two practice pairs and two ordinary pairs, all rendered; other
    tests' open runs are stopped first, and this one afterwards."""
    for run in live.api("GET", "/api/runs"):
        if run["status"] in ("running", "paused", "queued"):
            live.stop_run(run["id"])
    made = live.new_human_run(config={"feedback.practice_pairs": 2})
    first, second, *_ = live.push_rendered_queries(made, 4)
    with live.sessions() as session:  # reserved as a push reserves them (labelqueue.practice)
        session.execute(update(Query).where(Query.id.in_([first, second]))
                        .values(gold=True, needs_labels=GOLD_NEEDS_LABELS, practice=True))
        session.commit()
    yield made
    live.stop_run(made)


def phone(browser: Any) -> Any:
    context = browser.new_context(viewport=PHONE, has_touch=True, is_mobile=True)
    page = context.new_page()
    page.set_default_timeout(15_000)
    return page


def test_a_participant_who_fails_the_entry_test_is_let_go_without_a_code(
    live: LiveServer, browser: Any, run_id: int
) -> None:
    # The operator sets the test in the invite form, on a phone.
    page = phone(browser)
    page.goto(f"{live.url}/runs#token={OPERATOR_TOKEN}")
    form = "#new-invite"
    page.wait_for_selector(f"{form} [name=run_id] option[value='{run_id}']", state="attached")
    page.select_option(f"{form} [name=run_id]", str(run_id))
    page.wait_for_function("document.querySelector('#invite-run-quality').dataset.practice "
                           "=== '2'")
    assert page.locator(f"{form} [name=entry_pass]").is_visible()
    assert page.get_attribute(f"{form} [name=entry_pass]", "max") == "2"
    page.fill(f"{form} [name=entry_pass]", "2")
    page.fill(f"{form} [name=completion_code]", "ENTRY")
    page.click(f"{form} button[type=submit]")
    page.wait_for_selector("#new-invite-result code")
    invite = max(live.api("GET", "/api/invites"), key=lambda made: made["id"])
    assert (invite["run_id"], invite["entry_pass"]) == (run_id, 2)
    row = page.wait_for_selector(f'#invites-body tr[data-invite="{invite["id"]}"] .entry-test')
    assert row.inner_text() == "entry test: pass 2 practice"
    page.context.close()

    # A participant gets the first practice pair right and the second wrong: 1 of 2.
    page = phone(browser)
    page.goto(f"{invite['url']}?PROLIFIC_PID=ENTRY-1")
    page.wait_for_selector("#join-start:not([hidden])")
    page.click("#join-start")
    page.wait_for_url("**/label?run=*")
    for index, right in ((1, True), (2, False)):
        page.wait_for_selector(ANSWERABLE)
        assert f"Practice pair {index} of 2" in page.inner_text("#practice-banner")
        first_left = page.get_attribute(SHOWN, "data-left-is-first") == "true"
        page.click(f'[data-choice="{"left" if first_left == right else "right"}"]')
        page.wait_for_selector("#practice-dialog[open]")
        if index == 1:
            page.click("#practice-continue")
            page.wait_for_selector("#practice-dialog:not([open])", state="attached")
            # The test measures the first try: no Undo once the explanation was read.
            page.wait_for_selector("#stage:not([hidden])")
            assert page.is_hidden("#undo")
    assert "did not pass this study's entry test" in page.inner_text("#practice-next")
    page.click("#practice-continue")

    page.wait_for_selector("#completion:not([hidden])")
    assert page.inner_text("#completion-title") == \
        "Practice over: you did not pass the entry test"
    why = page.inner_text("#completion-why")
    assert "You got 1 practice pair right; this study asks for 2." in why
    assert "did not pass" in why and "no completion code" in why and "Thank you" in why
    assert page.is_hidden("#completion-code-row") and page.is_hidden("#completion-redirect")
    assert page.is_hidden("#stage") and page.is_hidden("#waiting")
    assert page.evaluate("document.documentElement.scrollWidth <= innerWidth")
    folder = os.environ.get("SEPOA_SCREENSHOT_DIR")
    if folder:
        page.screenshot(path=str(Path(folder) / "entry-test-failed-phone.png"))
    # No more pairs: a reload shows the same end, and the lease says why.
    page.reload()
    page.wait_for_selector("#completion:not([hidden])")
    assert page.is_hidden("#stage")
    page.context.close()

    # The participants page: failed the entry test, not to be paid.
    page = phone(browser)
    page.goto(f"{live.url}/invites/{invite['id']}/participants#token={OPERATOR_TOKEN}")
    row = page.wait_for_selector("#participants-body tr:has(code)")
    text = row.inner_text()
    assert "ENTRY-1" in text and "failed the entry test" in text and "not to be paid" in text
    assert row.get_attribute("data-valid") is None  # not an earned code
    page.context.close()
