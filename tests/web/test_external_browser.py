"""An external run's pushed clips in a real headless Chromium: frame arrays a client pushed with
`sepoa.client` decode and play on the label page, and the answer given there comes back to the
client with the pair's key; the page names no episode step for them."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
from web_helpers import LiveServer

from sepoa.client import Pair, Study

SHOWN = "#pairs .pair:not([hidden])"
DECODED = """selector => {
    const videos = [...document.querySelectorAll(`${selector} video`)];
    return videos.length === 2 && videos.every(v => v.readyState >= 2 && v.videoWidth > 0);
}"""


def moving_square(shift: int, frames: int = 30, size: int = 96) -> np.ndarray:
    """A white square crossing a dark field, `shift` pixels a frame."""
    video = np.full((frames, size, size, 3), 30, np.uint8)
    for t in range(frames):
        x = (t * shift) % (size - 16)
        video[t, 40:56, x:x + 16] = 230
    return video


def test_pushed_frames_play_on_the_label_page_and_the_answer_reaches_the_client(
    live: LiveServer, page: Any
) -> None:
    run = live.api("POST", "/api/runs/external", json={
        "task": "gym:HalfCheetah-v5", "budget": 5,
        "instruction": "Which square moves faster? The faster one is better."})
    token = live.api("POST", f"/api/runs/{run['id']}/tokens")["token"]
    study = Study(live.url, token, run["id"], progress=False)
    [query] = study.ask([Pair(moving_square(1), moving_square(3), key="slow-vs-fast",
                              returns=(1.0, 3.0), meta={"episodes": [11, 12]})])
    ivy = live.new_labeller("ivy-external")
    page.goto(f"{live.url}/label?run={run['id']}#token={ivy.token}")
    page.wait_for_function(DECODED, arg=SHOWN)
    assert int(page.get_attribute(SHOWN, "data-query-id")) == query.query_id
    widths = page.evaluate(f"[...document.querySelectorAll('{SHOWN} video')].map(v => "
                           "[v.videoWidth, v.videoHeight])")
    assert widths == [[96, 96], [96, 96]]
    assert "episodes" not in page.content()  # the hidden metadata stays on the server
    # Its clips are the client's uploads: the page states no step of an episode it never knew.
    assert page.inner_text("#clip-info").strip() == "Each clip: 30 steps"
    page.wait_for_selector('[data-choice="left"]:not([disabled])')  # played through once
    folder = os.environ.get("SEPOA_SCREENSHOT_DIR")
    if folder:
        page.screenshot(path=str(Path(folder) / "external-label-page.png"))
    left_is_first = page.get_attribute(SHOWN, "data-left-is-first") == "true"
    page.keyboard.press("ArrowRight" if left_is_first else "ArrowLeft")  # the fast square
    [event] = study.answers(wait=10)
    assert (event.key, event.labeller, event.answer, event.aggregate, event.complete) == (
        "slow-vs-fast", "ivy-external", "second", "second", True)
    assert event.meta == {"episodes": [11, 12]}
    # The quality pages read the run as any other: its one answer matched the true returns.
    [row] = live.api("GET", f"/api/quality/labellers?run_id={run['id']}")
    assert (row["labeller_name"], row["answers"]) == ("ivy-external", 1)
