"""examples/sb3_preferences.py trained on answers given in a real headless Chromium: its
HalfCheetah pairs play on the label page, a person's clicks there (by the pairs' true returns,
read from the queue database, never sent to the page) reach it, and SAC trains on the reward
learned from them. With SEPOA_SCREENSHOT_DIR=docs it writes docs/sb3-label-page.png."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

from web_helpers import LiveServer

from labelqueue import Query

ROOT = Path(__file__).resolve().parents[2]
SHOWN = "#pairs .pair:not([hidden])"
DECODED = """selector => {
    const videos = [...document.querySelectorAll(`${selector} video`)];
    return videos.length === 2 && videos.every(v => v.readyState >= 2 && v.videoWidth > 0);
}"""
PAIRS = 6


def test_the_sb3_example_trains_on_answers_given_on_the_label_page(
    live: LiveServer, page: Any, tmp_path: Path
) -> None:
    run = live.api("POST", "/api/runs/external", json={
        "task": "gym:HalfCheetah-v5", "budget": PAIRS, "name": "SB3 SAC, HalfCheetah-v5",
        "instruction": "Which cheetah runs forward faster? The faster one is better."})
    token = live.api("POST", f"/api/runs/{run['id']}/tokens")["token"]
    summary = tmp_path / "summary.json"
    example = subprocess.Popen(
        [sys.executable, str(ROOT / "examples" / "sb3_preferences.py"), "--preset", "tiny",
         "--rounds", "1", "--pairs-per-round", str(PAIRS), "--size", "256", "--url", live.url,
         "--token", token, "--run", str(run["id"]), "--summary", str(summary)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        ann = live.new_labeller("ann-sb3")
        page.goto(f"{live.url}/label?run={run['id']}#token={ann.token}")
        answered: list[int] = []
        for n in range(PAIRS):
            # The first pair comes once the example has stepped, rendered and pushed its round.
            page.wait_for_function(DECODED, arg=SHOWN, timeout=120_000)
            query_id = int(page.get_attribute(SHOWN, "data-query-id"))
            assert query_id not in answered
            with live.sessions() as session:
                query = session.get(Query, query_id)
                assert query is not None
                first, second = query.first_segment_return, query.second_segment_return
            assert first is not None and second is not None
            first_faster = first > second
            page.wait_for_selector('[data-choice="left"]:not([disabled])')  # played through
            folder = os.environ.get("SEPOA_SCREENSHOT_DIR")
            if n == 1 and folder:
                page.screenshot(path=str(Path(folder) / "sb3-label-page.png"))
            left_is_first = page.get_attribute(SHOWN, "data-left-is-first") == "true"
            page.keyboard.press("ArrowLeft" if first_faster == left_is_first else "ArrowRight")
            answered.append(query_id)
            if n + 1 < PAIRS:
                page.wait_for_function(
                    f"document.querySelector('{SHOWN}')?.dataset.queryId !== '{query_id}'")
        output, _ = example.communicate(timeout=180)
    finally:
        if example.poll() is None:
            example.kill()
            example.communicate()
        live.stop_run(run["id"])
    assert example.returncode == 0, output[-3000:]
    result = json.loads(summary.read_text())
    # The answers given on the page are the ones it trained on, and SAC trained on that reward.
    assert result["pairs_asked"] == result["answers_used"] == PAIRS
    assert result["sac_updates"] >= 300 - 1
    [row] = live.api("GET", f"/api/quality/labellers?run_id={run['id']}")
    assert (row["labeller_name"], row["answers"]) == ("ann-sb3", PAIRS)
