"""The label page's player in a real headless Chromium: pause, frame steps, jumps and the
scrubber move both clips together on one timeline, by button and by key; the clip's length and
where each clip starts in its episode are shown."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

from web_helpers import SEGMENT, LiveServer

SHOWN = "#pairs .pair:not([hidden])"
DECODED = """selector => {
    const videos = [...document.querySelectorAll(`${selector} video`)];
    return videos.length === 2 && videos.every(v => v.readyState >= 2 && v.videoWidth > 0);
}"""
# Both clips' times, whether they are paused, and whether either is still seeking.
TIMES = f"""() => [...document.querySelectorAll('{SHOWN} video')].map(
    v => ({{t: v.currentTime, paused: v.paused, seeking: v.seeking}}))"""
FPS = 100 / 3


def screenshot(page: Any, name: str, selector: str | None = None) -> None:
    """With SEPOA_SCREENSHOT_DIR set, the page (or one element) as a PNG there (docs/)."""
    folder = os.environ.get("SEPOA_SCREENSHOT_DIR")
    if folder:
        target = page.locator(selector) if selector else page
        target.screenshot(path=str(Path(folder) / name))


def frame_shown(page: Any) -> int:
    match = re.fullmatch(r"frame (\d+) of (\d+)", page.text_content("#frame-info"))
    assert match, page.text_content("#frame-info")
    assert int(match[2]) == SEGMENT
    return int(match[1])


def settled(page: Any, frame: int) -> list[dict[str, Any]]:
    """Waits until both clips are paused on frame `frame` (1-based) and returns their times."""
    page.wait_for_function(
        f"""() => {{
            const vs = [...document.querySelectorAll('{SHOWN} video')];
            return vs.length === 2 && vs.every(v => v.paused && !v.seeking
                && Math.abs(v.currentTime - ({frame} - 0.5) / {FPS}) < 0.002);
        }}""")
    assert frame_shown(page) == frame
    return list(page.evaluate(TIMES))


def test_pause_step_jump_and_scrub_keep_both_clips_on_one_frame(
    live: LiveServer, page: Any
) -> None:
    dana = live.new_labeller("dana-player")
    run_id = live.new_human_run()
    (query_id,) = live.push_rendered_queries(run_id, 1)
    try:
        page.goto(f"{live.url}/label?run={run_id}#token={dana.token}")
        page.wait_for_function(DECODED, arg=SHOWN)
        left_is_first = page.get_attribute(SHOWN, "data-left-is-first") == "true"
        left_start, right_start = (0, 40) if left_is_first else (40, 0)  # the pushed starts
        info = page.inner_text("#clip-info")  # as shown: left and right on a wide window
        assert f"Each clip: {SEGMENT} steps" in info
        assert f"left starts at step {left_start} of its episode" in info
        assert f"right at step {right_start}" in info

        # Space pauses both clips where they are; the timeline no longer moves.
        page.wait_for_function(f"document.querySelector('{SHOWN} video').currentTime > 0.2")
        page.keyboard.press("Space")
        assert page.get_attribute("#play", "aria-pressed") == "true"
        assert page.text_content("#play-label") == "Play"
        page.wait_for_function(f"[...document.querySelectorAll('{SHOWN} video')]"
                               ".every(v => v.paused && !v.seeking)")
        frame = frame_shown(page)
        page.wait_for_timeout(300)
        assert frame_shown(page) == frame

        # "." and "," step one frame; both clips show the same frame.
        page.keyboard.press(".")
        a, b = settled(page, frame + 1)
        assert abs(a["t"] - b["t"]) < 1e-3
        page.keyboard.press(",")
        page.keyboard.press(",")
        settled(page, frame - 1)
        # The buttons do the same.
        page.click("#frame-next")
        settled(page, frame)
        page.click("#frame-back")
        settled(page, frame - 1)

        # Home and End: the first and last frame; J and L: ten frames back and on.
        page.keyboard.press("Home")
        settled(page, 1)
        page.keyboard.press("l")
        settled(page, 11)
        page.keyboard.press("j")
        settled(page, 1)
        page.keyboard.press(",")  # already on the first frame: stays
        settled(page, 1)
        page.keyboard.press("End")
        settled(page, SEGMENT)

        # The scrubber puts both clips on any frame.
        page.fill("#scrub", "25")
        a, b = settled(page, 26)
        assert abs(a["t"] - b["t"]) < 1e-3
        assert page.input_value("#scrub") == "25"
        screenshot(page, "label-page-player.png", "#stage")

        # Space (or the button) plays again from there, both clips together.
        page.click("#play")
        assert page.get_attribute("#play", "aria-pressed") == "false"
        page.wait_for_function(f"[...document.querySelectorAll('{SHOWN} video')]"
                               ".some(v => !v.paused)")
        page.wait_for_function(
            "() => { const m = document.querySelector('#frame-info').textContent"
            ".match(/frame (\\d+)/); return m && Number(m[1]) !== 26; }")
        page.keyboard.press("k")
        assert page.get_attribute("#play", "aria-pressed") == "true"
        page.keyboard.press("k")
        assert page.get_attribute("#play", "aria-pressed") == "false"

        # The answer keys still answer after the player was used.
        page.wait_for_selector('[data-choice="left"]:not([disabled])', timeout=15_000)
        page.keyboard.press("ArrowLeft")
        page.wait_for_function("document.querySelector('#count-session').textContent === '1'")
        assert query_id
    finally:
        live.stop_run(run_id)
