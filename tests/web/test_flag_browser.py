"""Flagging a pair in a real headless Chromium: F or the button opens the dialog (the clips
pause), Esc and Cancel close it, a reason is required, "Flag and skip" stores a skip with the
flag and the note and moves on; the run page counts the flags and shows the note; the export
has them."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

from web_helpers import OPERATOR_TOKEN, LiveServer

from labelqueue import Label, labels_for_queries

SHOWN = "#pairs .pair:not([hidden])"
DECODED = """selector => {
    const videos = [...document.querySelectorAll(`${selector} video`)];
    return videos.length === 2 && videos.every(v => v.readyState >= 2 && v.videoWidth > 0);
}"""


def screenshot(page: Any, name: str, selector: str | None = None) -> None:
    """With SEPOA_SCREENSHOT_DIR set, the page (or one element) as a PNG there (docs/)."""
    folder = os.environ.get("SEPOA_SCREENSHOT_DIR")
    if folder:
        target = page.locator(selector) if selector else page
        target.screenshot(path=str(Path(folder) / name))


def stored(live: LiveServer, query_id: int, timeout: float = 5.0) -> Label:
    deadline = time.monotonic() + timeout
    while True:
        with live.sessions() as session:
            labels = labels_for_queries(session, query_ids=[query_id])
        if labels or time.monotonic() > deadline:
            assert len(labels) == 1, labels
            return labels[0]
        time.sleep(0.05)


def test_a_labeller_flags_a_pair_and_the_operator_sees_it(live: LiveServer, page: Any) -> None:
    erin = live.new_labeller("erin-flags")
    run_id = live.new_human_run()
    first, second, _ = live.push_rendered_queries(run_id, 3)
    try:
        page.goto(f"{live.url}/label?run={run_id}#token={erin.token}")
        page.wait_for_function(DECODED, arg=SHOWN)
        assert int(page.get_attribute(SHOWN, "data-query-id")) == first

        # F opens the dialog at once (a broken clip may never play through) and pauses the
        # clips; Esc closes it and changes nothing.
        page.keyboard.press("f")
        page.wait_for_selector("#flag-dialog[open]")
        assert page.get_attribute("#play", "aria-pressed") == "true"
        page.keyboard.press("Escape")
        page.wait_for_selector("#flag-dialog:not([open])", state="attached")
        assert int(page.get_attribute(SHOWN, "data-query-id")) == first
        # The answer keys work again once it is closed; the button opens it too.
        page.click("#flag")
        page.wait_for_selector("#flag-dialog[open]")
        # A reason is required: sending without one keeps the dialog open.
        page.click("#flag-send")
        assert page.is_visible("#flag-dialog")
        page.click("#flag-cancel")
        page.wait_for_selector("#flag-dialog:not([open])", state="attached")

        page.keyboard.press("F")
        page.check("#flag-dialog input[value=not_visible]")
        page.fill("#flag-note", "the cheetah is off the left edge")
        screenshot(page, "label-page-flag.png", "#flag-dialog")
        page.click("#flag-send")
        page.wait_for_selector(f'{SHOWN}[data-query-id="{second}"]')
        assert "flagged (agent not visible) and skipped" in page.text_content("#notice")
        label = stored(live, first)
        assert (label.choice, label.answer, label.flag) == ("skip", "skip", "not_visible")
        assert label.flag_note == "the cheetah is off the left edge"

        # The second pair: flagged "clip broken" without a note (F does nothing until the
        # page enables the pair's buttons, as for the answer keys).
        page.wait_for_selector("#flag:not([disabled])")
        page.keyboard.press("f")
        page.wait_for_selector("#flag-dialog[open]")
        page.check("#flag-dialog input[value=clip_broken]")
        page.keyboard.press("Enter")  # submits the form
        label = stored(live, second)
        assert (label.flag, label.flag_note) == ("clip_broken", None)

        # The run page counts them and shows the latest with the note.
        page.goto(f"{live.url}/runs/{run_id}#token={OPERATOR_TOKEN}")
        page.wait_for_selector("#flag-facts [data-flag=not_visible]")
        assert page.text_content("#flag-facts [data-flag=not_visible]") == "1"
        assert page.text_content("#flag-facts [data-flag=clip_broken]") == "1"
        assert page.text_content("#flag-facts [data-flag=other]") == "0"
        assert "2 on 2 pairs" in page.text_content("#flag-facts")
        latest = page.inner_text("#flag-latest")
        assert f"pair {second}: clip broken (erin-flags" in latest
        assert "the cheetah is off the left edge" in latest
        screenshot(page, "run-flags.png", "#flags-card")

        # The export has both, as skips.
        rows = {row["query_id"]: row
                for row in live.api_text("GET", f"/api/export?format=jsonl&run_id={run_id}")}
        assert (rows[first]["flag"], rows[first]["flag_note"]) == (
            "not_visible", "the cheetah is off the left edge")
        assert (rows[second]["flag"], rows[second]["answer"]) == ("clip_broken", "skip")
    finally:
        live.stop_run(run_id)
