"""Label quality in a real headless Chromium: two labellers answer the same queries of a run that
asks for two answers per query (one through the label page), the export holds both answers,
the runs page's quality table and the run page's agreement card show them; a labeller the gold
threshold paused sees why on the label page, and an operator lets them go on from the table."""

from __future__ import annotations

import time
from datetime import UTC, datetime
from typing import Any

import httpx
from web_helpers import OPERATOR_TOKEN, Labeller, LiveServer

from labelqueue import labels_for_queries
from labelqueue.models import LabellerPause

SHOWN = "#pairs .pair:not([hidden])"


def as_labeller(
    live: LiveServer, who: Labeller, method: str, path: str, **kwargs: Any
) -> httpx.Response:
    return httpx.request(
        method,
        live.url + path,
        timeout=30,
        headers={"Authorization": f"Bearer {who.token}"},
        **kwargs,
    )


def answer_by_rest(live: LiveServer, who: Labeller, run_id: int, expect: int, answer: str) -> None:
    """`who` leases the run's next query (it must be `expect`) and gives `answer` (first or
    second), clicking the side the server put that segment on."""
    leased = as_labeller(live, who, "GET", f"/api/label/next?run_id={run_id}")
    assert leased.status_code == 200, leased.text
    query = leased.json()
    assert query["query_id"] == expect
    left = (answer == "first") == query["left_is_first"]
    sent = as_labeller(
        live,
        who,
        "POST",
        f"/api/label/{expect}",
        json={
            "choice": "left" if left else "right",
            "left_is_first": query["left_is_first"],
            "shown_at": datetime.now(UTC).isoformat(),
        },
    )
    assert sent.status_code == 201, sent.text


def stored_answers(live: LiveServer, query_id: int, count: int) -> dict[int, str]:
    deadline = time.monotonic() + 5
    while True:
        with live.sessions() as session:
            labels = labels_for_queries(session, query_ids=[query_id])
        if len(labels) >= count or time.monotonic() > deadline:
            return {label.labeller_id: str(label.answer.value) for label in labels}
        time.sleep(0.05)


def test_two_labellers_answer_one_query_and_the_operator_sees_their_agreement(
    live: LiveServer, page: Any
) -> None:
    bob, carol = live.new_labeller("bob-k2"), live.new_labeller("carol-k2")
    run_id = live.new_human_run(config={"feedback.labels_per_query": 2})
    try:
        first, second = live.push_rendered_queries(run_id, 2, needs=2)

        # Bob answers the first pair on the label page, once both clips have played.
        page.goto(f"{live.url}/label?run={run_id}#token={bob.token}")
        page.wait_for_selector(f'{SHOWN}[data-query-id="{first}"]')
        page.wait_for_selector('[data-choice="left"]:not([disabled])')
        page.click('[data-choice="left"]')
        bobs = stored_answers(live, first, 1)[bob.id]
        page.goto("about:blank")  # the label page stops leasing

        # Bob's second answer and both of Carol's by REST: they agree on the first pair only.
        answer_by_rest(live, bob, run_id, second, "first")
        answer_by_rest(live, carol, run_id, first, bobs)
        answer_by_rest(live, carol, run_id, second, "second")

        # (a) The export holds both answers to the first query, each under its labeller.
        rows = live.api_text("GET", f"/api/export?format=jsonl&run_id={run_id}")
        of_first = [row for row in rows if row["query_id"] == first]
        assert sorted(row["labeller_name"] for row in of_first) == ["bob-k2", "carol-k2"]
        assert {row["answer"] for row in of_first} == {bobs}
        assert all(row["labels_per_query"] == 2 and row["query_answers"] == 2 for row in of_first)

        # (b) The quality table, chosen for this run by the address, shows both labellers.
        page.goto(f"{live.url}/runs?quality_run={run_id}#token={OPERATOR_TOKEN}")
        page.wait_for_selector('#quality-body tr[data-labeller="carol-k2"]')
        assert page.input_value("#quality-run") == str(run_id)
        assert page.inner_text("#quality-caption") == f"Each labeller's answers on run {run_id}"
        assert page.locator("#quality-body tr").count() == 2
        for name in ("bob-k2", "carol-k2"):
            row = page.locator(f'#quality-body tr[data-labeller="{name}"]')
            assert row.locator("th[scope=row]").inner_text() == name
            assert row.locator("td.answer-count").inner_text() == "2"
            # One pair agreed, one did not: 0.50, on the two queries they share.
            assert row.locator("td.agreement").inner_text() == "0.50 on 2 shared"
            assert "[" in row.locator("td.left-share").inner_text()  # a share with its interval
            assert "paused" not in row.inner_text()
        assert page.locator("table.quality th[scope=col]").count() == 13  # with Practice
        # The table fits its card: no sideways scroll.
        wrap = page.eval_on_selector("#labeller-quality .table-wrap",
                                     "w => [w.scrollWidth, w.clientWidth]")
        assert wrap[0] <= wrap[1], wrap

        # The run page's Agreement card: half the pairs agree; κ below chance.
        page.goto(f"{live.url}/runs/{run_id}#token={OPERATOR_TOKEN}")
        page.wait_for_selector("#agreement-rounds tr th")
        facts = page.inner_text("#agreement-facts")
        assert "Pairwise agreement\n0.50" in facts
        assert "Fleiss' κ\n-0.33" in facts
        assert "Queries with ≥ 2 answers\n2" in facts
        assert page.inner_text("#agreement-rounds tr").split() == ["0", "2", "0.50", "-0.33"]
        page.click("#quality-link")
        page.wait_for_selector('#quality-body tr[data-labeller="bob-k2"]')
        assert page.input_value("#quality-run") == str(run_id)
    finally:
        live.stop_run(run_id)


def test_a_paused_labeller_is_told_why_and_an_operator_lets_them_go_on(
    live: LiveServer, page: Any
) -> None:
    dave = live.new_labeller("dave-gold")
    run_id = live.new_human_run(config={"feedback.gold_min_accuracy": 0.8})
    try:
        first, second = live.push_rendered_queries(run_id, 2)
        answer_by_rest(live, dave, run_id, first, "second")
        with live.sessions() as session:  # as three wrong gold answers would have done
            session.add(
                LabellerPause(run_id=run_id, labeller_id=dave.id, gold_answers=3, gold_correct=0)
            )
            session.commit()

        asked: list[str] = []
        page.on("request", lambda r: asked.append(r.url) if "/api/label/next" in r.url else None)
        page.goto(f"{live.url}/label?run={run_id}#token={dave.token}")
        alert = page.locator("#notice[role=alert]")
        alert.wait_for()
        assert alert.inner_text() == (
            "Paused: 0 of your 3 answers on check pairs were right, below the 80% this run "
            "asks for; an operator can let you go on"
        )
        # Not a refused token: still signed in, and the page stops asking.
        assert page.is_hidden("#signin")
        assert page.evaluate("localStorage.getItem('sepoa.labeller-token')") == dave.token
        assert page.is_hidden("#waiting") and page.is_hidden("#stage")
        page.wait_for_timeout(2500)
        assert len(asked) == 1
        assert page.is_visible("#notice[role=alert]")

        # The operator's table shows the pause for this run and lifts it.
        page.goto(f"{live.url}/runs?quality_run={run_id}#token={OPERATOR_TOKEN}")
        row = page.locator('#quality-body tr[data-labeller="dave-gold"]')
        row.locator(".badge.paused").wait_for()
        page.once("dialog", lambda dialog: dialog.accept())
        row.get_by_role("button", name="Let go on").click()
        page.wait_for_selector('#notice:has-text("dave-gold may answer")')
        row.locator(".badge.paused").wait_for(state="detached")
        leased = as_labeller(live, dave, "GET", f"/api/label/next?run_id={run_id}")
        assert leased.status_code == 200 and leased.json()["query_id"] == second
    finally:
        live.stop_run(run_id)
