"""A paid study on a phone, in a real headless Chromium: the practice pair's explanation is a
screen of its own, a participant left with nothing to label finishes with their code after the
invite's wait, and the operator's participants page lists them with the code earned and checks
codes for this study (another study's code is not paid). With
SEPOA_SCREENSHOT_DIR=docs it writes the three phone screenshots."""

from __future__ import annotations

from typing import Any

from sqlalchemy import update
from test_study_browser import join_and_start, phone, screenshot
from web_helpers import OPERATOR_TOKEN, LiveServer

from crowdstudy.completion import participant_code
from labelqueue.gold import GOLD_NEEDS_LABELS
from labelqueue.keys import server_key
from labelqueue.models import Invite, Query


def test_practice_nothing_left_and_the_list_to_pay_from_on_a_phone(
    live: LiveServer, browser: Any, runs: list[int]  # noqa: F811
) -> None:
    runs.append(run_id := live.new_human_run(config={"feedback.practice_pairs": 1}))
    practice, real = live.push_rendered_queries(run_id, 2)
    with live.sessions() as session:  # reserved as the run's practice pair, as a push does
        session.execute(update(Query).where(Query.id == practice).values(
            gold=True, practice=True, needs_labels=GOLD_NEEDS_LABELS))
        session.commit()
    invite = live.api("POST", "/api/invites", json={
        "run_id": run_id, "target_answers": 5, "wait_limit_s": 1, "completion_code": "PAY"})
    page = phone(browser)
    join_and_start(page, invite["url"], "P-pay")

    page.wait_for_selector('[data-choice="left"]:not([disabled])')
    page.click('[data-choice="left"]')
    page.wait_for_selector("#practice-dialog[open]")
    assert page.is_hidden("#stage")  # the next pair waits behind the explanation
    screenshot(page, "practice-phone.png")
    page.click("#practice-continue")

    page.wait_for_selector('[data-choice="right"]:not([disabled])')
    assert int(page.get_attribute("#pairs .pair:not([hidden])", "data-query-id")) == real
    page.click('[data-choice="right"]')
    # One real answer of five, and nothing left: after the invite's wait, finished, with a code.
    page.wait_for_selector("#completion:not([hidden])", timeout=30_000)
    assert page.inner_text("#completion-title") == "Finished: nothing left to label"
    code = page.inner_text("#completion-code")
    assert code.startswith("PAY-")
    screenshot(page, "nothing-left-phone.png")
    page.context.close()

    operator = phone(browser)
    operator.goto(f"{live.url}/invites/{invite['id']}/participants#token={OPERATOR_TOKEN}")
    operator.wait_for_selector("#participants-body tr[data-valid]")
    row = operator.inner_text("#participants-body tr")
    assert "P-pay" in row and code in row and "earned" in row and "1 practice" in row
    screenshot(operator, "participants-phone.png")
    # Codes checked on this study's page: a code of another study's participant is not paid.
    other = live.api("POST", "/api/invites", json={"run_id": run_id})
    zed = live.api("POST", f"/api/join/{other['code']}", json={"participant": "Z-other"})
    with live.sessions() as session:
        others = participant_code(server_key(session), session.get_one(Invite, other["id"]),
                                  zed["labeller_id"])
    operator.fill("#codes", f"{code}\n{others}")
    operator.click("#codes-form button[type=submit]")
    operator.wait_for_selector("#codes-result li:nth-child(2)")
    [paid, refused] = operator.locator("#codes-result li").all_inner_texts()
    assert paid.startswith(f"{code} — pay P-pay")
    assert refused == (f"{others} — another study's code (invite {other['id']}): not to be "
                       "paid for this one")
    operator.context.close()
