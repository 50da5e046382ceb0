"""The labeller's screen on common laptop windows and on a phone, in a real headless Chromium:
big clips, with the instruction, the player and the answers in view without scrolling; the
instruction open for a run's first pair, then folded to one line, opened again by a click or I.

With SEPOA_SCREENSHOT_DIR set, each window's first pair is saved there as
label-page-<width>x<height>.png (docs/ holds them)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from test_labeller_experience_browser import (
    ANSWERABLE,
    DECODED,
    SHOWN,
    context_page,
    in_view,
    screenshot,
)
from web_helpers import LiveServer

CONTROLS = ("#instruction", "#play", "#frame-back", "#scrub", "#frame-next", "#frame-info",
            '[data-choice="left"]', '[data-choice="equal"]', '[data-choice="right"]',
            "#replay", '[data-choice="cant_tell"]', '[data-choice="skip"]', "#flag")
CLIP_BOXES = f"""() => [...document.querySelectorAll('{SHOWN} video')].map(v => {{
    const r = v.getBoundingClientRect();
    return {{left: r.left, top: r.top, width: r.width, height: r.height, bottom: r.bottom}};
}})"""


@pytest.fixture
def run_id(live: LiveServer) -> Iterator[int]:
    for run in live.api("GET", "/api/runs"):  # others' leftover pairs stay out of this test
        if run["status"] in ("running", "paused", "queued"):
            live.stop_run(run["id"])
    made = live.new_human_run()
    live.push_rendered_queries(made, 2)
    yield made
    live.stop_run(made)


def settle(page: Any) -> None:
    page.wait_for_function(DECODED, arg=SHOWN)
    page.wait_for_selector(ANSWERABLE)
    page.wait_for_timeout(200)  # the clips' fit runs on the next frame


def folded_height(page: Any) -> float:
    return float(page.eval_on_selector("#instruction", "el => el.getBoundingClientRect().height"))


@pytest.mark.parametrize("width,height", [(1366, 768), (1280, 720)])
def test_on_a_laptop_big_clips_and_everything_in_view(
    live: LiveServer, browser: Any, run_id: int, width: int, height: int
) -> None:
    labeller = live.new_labeller(f"lap-{width}")
    page = context_page(browser, width, height)
    page.goto(f"{live.url}/label?run={run_id}#token={labeller.token}")
    settle(page)

    # The first pair: the instruction open, the clips at least 320 px tall, nothing scrolled.
    assert page.get_attribute("#instruction-more", "aria-expanded") == "true"
    boxes = page.evaluate(CLIP_BOXES)
    print(f"{width}x{height} open: clips {[(b['width'], b['height']) for b in boxes]}")
    assert all(box["height"] >= 320 for box in boxes), boxes
    for selector in (f"{SHOWN} .clip:first-child video", f"{SHOWN} .clip:last-child video",
                     *CONTROLS):
        assert in_view(page, selector), (width, height, selector)
    assert page.evaluate("scrollY") == 0
    screenshot(page, f"label-page-{width}x{height}.png")
    open_height = folded_height(page)

    # The second pair: the instruction folded to one line; the clips take the room it leaves.
    page.keyboard.press("ArrowLeft")
    page.wait_for_function("document.querySelector('#count-session').textContent === '1'")
    settle(page)
    assert page.get_attribute("#instruction-more", "aria-expanded") == "false"
    line = folded_height(page)
    assert line < 50 < open_height
    assert "as fast as possible" in page.inner_text("#instruction-body")  # its goal
    folded = page.evaluate(CLIP_BOXES)
    assert folded[0]["height"] > boxes[0]["height"]
    for selector in (f"{SHOWN} .clip:first-child video", f"{SHOWN} .clip:last-child video",
                     *CONTROLS):
        assert in_view(page, selector), (width, height, "folded", selector)

    # I opens it again (and keeps it open), I folds it; so does a click.
    page.keyboard.press("i")
    assert page.get_attribute("#instruction-more", "aria-expanded") == "true"
    assert folded_height(page) == pytest.approx(open_height, abs=2)
    page.keyboard.press("I")
    assert page.get_attribute("#instruction-more", "aria-expanded") == "false"
    page.click("#instruction-more")
    assert page.get_attribute("#instruction-more", "aria-expanded") == "true"
    assert in_view(page, '[data-choice="right"]')

    # The words: the frame, and the speed in one sentence.
    assert page.inner_text("#frame-info").startswith("frame ")
    assert " of 40" in page.inner_text("#frame-info")
    assert page.inner_text("#speed-note") == "Slowed to 1/3 of real time."
    page.click('[data-speed="2"]')
    assert page.inner_text("#speed-note") == "Slowed to 2/3 of real time."
    page.context.close()


def test_on_a_phone_the_clips_take_the_full_width(
    live: LiveServer, browser: Any, run_id: int
) -> None:
    labeller = live.new_labeller("phone-390")
    page = context_page(browser, 390, 844)
    page.goto(f"{live.url}/label?run={run_id}#token={labeller.token}")
    settle(page)

    assert page.evaluate("document.documentElement.scrollWidth") <= 390  # no sideways scroll
    top, bottom = page.evaluate(CLIP_BOXES)
    print(f"390x844: clips {top['width']}x{top['height']}, {bottom['width']}x{bottom['height']}")
    assert top["bottom"] <= bottom["top"]  # one above the other
    # The page's width, less a margin (and a desktop browser's scrollbar; a phone's overlays).
    page_width = page.evaluate("document.body.clientWidth")
    assert min(top["width"], bottom["width"]) >= page_width - 16
    for selector in CONTROLS:  # the open instruction scrolls inside itself
        assert in_view(page, selector), selector
    # Top and bottom, in the buttons and in the clips' note.
    assert page.get_by_role("button", name="Top is better", exact=True).count() == 1
    assert page.get_by_role("button", name="Bottom is better", exact=True).count() == 1
    note = page.inner_text("#clip-info")
    assert "top starts at step" in note and "bottom at step" in note and "left" not in note
    screenshot(page, "label-page-390x844.png")

    # Folded from the second pair on: one line, opened by a tap.
    page.click('[data-choice="left"]')
    page.wait_for_function("document.querySelector('#count-session').textContent === '1'")
    settle(page)
    assert page.get_attribute("#instruction-more", "aria-expanded") == "false"
    assert folded_height(page) < 50
    for selector in (f"{SHOWN} .clip:first-child video", *CONTROLS):
        assert in_view(page, selector), ("folded", selector)
    page.click("#instruction-more")
    assert page.get_attribute("#instruction-more", "aria-expanded") == "true"
    page.context.close()
