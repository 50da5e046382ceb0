"""The operators' label browser in a real headless Chromium: filters by run, labeller,
correctness against the hidden truth, flag and gold (also from the address), and a row opens
its pair: both clips, on the sides the labeller saw, with the answer, the shadow label and the
true returns. Labellers get none of it."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import httpx
from sqlalchemy import update
from web_helpers import OPERATOR_TOKEN, SECRET_RETURNS, LiveServer

from labelqueue import lease_next_query, submit_label
from labelqueue.models import Query
from server import clips

ROWS = "#labels-body tr[data-label-id]"


def screenshot(page: Any, name: str, selector: str | None = None) -> None:
    folder = os.environ.get("SEPOA_SCREENSHOT_DIR")
    if folder:
        target = page.locator(selector) if selector else page
        target.screenshot(path=str(Path(folder) / name))


def answer(live: LiveServer, labeller_id: int, run_id: int, click: str, **flag: Any) -> int:
    with live.sessions() as session:
        query = lease_next_query(session, labeller_id=labeller_id, run_id=run_id)
        assert query is not None
        left_first = clips.left_is_first(settings=live.settings, query_id=query.id,
                                         labeller_id=labeller_id)
        label, _ = submit_label(session, query_id=query.id, labeller_id=labeller_id,
                                choice=click, left_is_first=left_first, **flag)
    return label.id


def shown_ids(page: Any) -> set[int]:
    return {int(x) for x in page.eval_on_selector_all(
        ROWS, "rows => rows.map(r => r.dataset.labelId)")}


def filtered(page: Any, name: str, value: str, expected: set[int]) -> None:
    page.select_option(f"#filters [name={name}]", value)
    page.wait_for_function(
        f"ids => {{ const got = [...document.querySelectorAll('{ROWS}')]"
        ".map(r => Number(r.dataset.labelId)).sort((a, b) => a - b);"
        " return JSON.stringify(got) === JSON.stringify(ids); }",
        arg=sorted(expected))


def test_an_operator_filters_labels_and_opens_a_pair(live: LiveServer, page: Any) -> None:
    run_id = live.new_human_run()
    live.push_rendered_queries(run_id, 4)
    people = {name: live.new_labeller(f"{name}-browser") for name in ("ann", "ben", "cat")}
    # Segment returns: first 987.125, second -654.375, so "first" is the true answer.
    with live.sessions() as session:
        session.execute(update(Query).where(Query.run_id == run_id)
                        .values(shadow_choice="first"))
        session.commit()
    try:
        # ann clicks the side the first segment is on (correct), and her pair is made a gold
        # pair; ben clicks the second segment's (incorrect); cat flags one and says equal.
        ids = {}
        with live.sessions() as session:
            q = lease_next_query(session, labeller_id=people["ann"].id, run_id=run_id)
            assert q is not None
            first_left = clips.left_is_first(settings=live.settings, query_id=q.id,
                                             labeller_id=people["ann"].id)
            label, _ = submit_label(session, query_id=q.id, labeller_id=people["ann"].id,
                                    choice="left" if first_left else "right",
                                    left_is_first=first_left)
            ids["ann"] = label.id
            session.execute(update(Query).where(Query.id == q.id).values(gold=True))
            session.commit()
        with live.sessions() as session:
            q = lease_next_query(session, labeller_id=people["ben"].id, run_id=run_id)
            assert q is not None
            first_left = clips.left_is_first(settings=live.settings, query_id=q.id,
                                             labeller_id=people["ben"].id)
            label, _ = submit_label(session, query_id=q.id, labeller_id=people["ben"].id,
                                    choice="right" if first_left else "left",
                                    left_is_first=first_left)
            ids["ben"] = label.id
        ids["cat"] = answer(live, people["cat"].id, run_id, "skip", flag="not_visible",
                            flag_note="off screen")
        ids["cat-equal"] = answer(live, people["cat"].id, run_id, "equal")

        page.goto(f"{live.url}/labels?run={run_id}#token={OPERATOR_TOKEN}")
        page.wait_for_selector(ROWS)
        assert shown_ids(page) == set(ids.values())
        assert "4 labels match" in page.text_content("#matching")
        screenshot(page, "label-browser-list.png", "main > section >> nth=0")

        filtered(page, "correct", "false", {ids["ben"], ids["cat-equal"]})
        filtered(page, "correct", "true", {ids["ann"]})
        filtered(page, "correct", "", set(ids.values()))
        filtered(page, "flagged", "true", {ids["cat"]})
        filtered(page, "flagged", "", set(ids.values()))
        filtered(page, "gold", "true", {ids["ann"]})
        filtered(page, "gold", "false", {ids["ben"], ids["cat"], ids["cat-equal"]})
        filtered(page, "gold", "", set(ids.values()))
        filtered(page, "labeller_id", str(people["cat"].id), {ids["cat"], ids["cat-equal"]})
        assert f"labeller_id={people['cat'].id}" in page.url  # the view can be linked to
        filtered(page, "labeller_id", "", set(ids.values()))

        # ben's label: both clips side by side on his sides, answer, shadow label, returns.
        page.click(f'{ROWS}[data-label-id="{ids["ben"]}"]')
        page.wait_for_selector("#detail:not([hidden])")
        page.wait_for_function("""() => ['left-video', 'right-video'].every(id => {
            const v = document.getElementById(id);
            return v.readyState >= 2 && v.videoWidth > 0; })""")
        facts = page.inner_text("#detail-facts")
        assert "incorrect" in facts and "Shadow label" in facts and "first" in facts
        assert "987.1" in facts and "-654.4" in facts
        captions = page.inner_text("#left-caption") + page.inner_text("#right-caption")
        assert "true return 987.1" in captions and "true return -654.4" in captions
        screenshot(page, "label-browser.png")

        # The address sets the filters: the run page's link to its flagged pairs.
        page.goto(f"{live.url}/labels?run={run_id}&flagged=true")
        page.wait_for_selector(ROWS)
        assert shown_ids(page) == {ids["cat"]}

        # Labellers get none of it.
        for path in ("/api/labels", f"/api/labels/{ids['ben']}"):
            response = httpx.get(live.url + path,
                                 headers={"Authorization": f"Bearer {people['ben'].token}"})
            assert response.status_code == 403, response.text
            assert str(SECRET_RETURNS["first_segment_return"]) not in response.text
    finally:
        live.stop_run(run_id)
