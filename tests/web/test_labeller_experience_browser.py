"""What a labeller sees, in a real headless Chromium against a real server: the instruction of
the pair's run above the clips (kept in view, changing visibly with the run), clips decoded at
their new size and shown at most twice it, one clock at the chosen speed, a phone-width layout
with the clips stacked and the answers in view, text that passes WCAG AA contrast, and invite
links that sign a new browser in (or say plainly why they cannot).

With SEPOA_SCREENSHOT_DIR set, the desktop and phone layouts are saved there as PNG files
(docs/label-page-desktop.png and docs/label-page-phone.png come from here)."""

from __future__ import annotations

import os
import time
from datetime import timedelta
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import update
from web_helpers import OPERATOR_TOKEN, LiveServer

from labelqueue import Label, find_labeller, labels_for_queries
from labelqueue.models import utcnow
from runvocab.instructions import default_instruction

SHOWN = "#pairs .pair:not([hidden])"
DECODED = """selector => {
    const videos = [...document.querySelectorAll(`${selector} video`)];
    return videos.length === 2 && videos.every(v => v.readyState >= 2 && v.videoWidth > 0);
}"""
ANSWERABLE = '[data-choice="left"]:not([disabled])'
CUSTOM = "Prefer the clip where the cheetah keeps its head up.\nFalling over is worst."
# Every element with text of its own: its colour against the first opaque background behind it.
CONTRAST = """() => {
    const rgb = s => (s.match(/[\\d.]+/g) || []).map(Number);
    const lum = ([r, g, b]) => {
        const f = c => {
            c /= 255;
            return c <= 0.03928 ? c / 12.92 : ((c + 0.055) / 1.055) ** 2.4;
        };
        return 0.2126 * f(r) + 0.7152 * f(g) + 0.0722 * f(b);
    };
    const background = el => {
        for (; el; el = el.parentElement) {
            const c = rgb(getComputedStyle(el).backgroundColor);
            if (c.length === 3 || c[3] === 1) return c.slice(0, 3);
        }
        return [255, 255, 255];
    };
    const failures = [];
    for (const el of document.querySelectorAll("body *")) {
        const own = [...el.childNodes].some(n => n.nodeType === 3 && n.textContent.trim());
        const box = el.getBoundingClientRect();
        if (!own || box.width === 0 || el.closest("[hidden], :disabled, video")) continue;
        const style = getComputedStyle(el);
        if (style.visibility === "hidden" || style.display === "none") continue;
        const [a, b] = [lum(rgb(style.color)), lum(background(el))];
        const ratio = (Math.max(a, b) + 0.05) / (Math.min(a, b) + 0.05);
        const large = parseFloat(style.fontSize) >= 24
            || (parseFloat(style.fontSize) >= 18.66 && Number(style.fontWeight) >= 700);
        const text = el.textContent.trim().slice(0, 30);
        if (ratio < (large ? 3 : 4.5))
            failures.push(`${el.tagName}.${el.className} "${text}" ${ratio.toFixed(2)}`);
    }
    return failures;
}"""


def context_page(browser: Any, width: int, height: int) -> Any:
    page = browser.new_context(viewport={"width": width, "height": height}).new_page()
    page.set_default_timeout(15_000)
    return page


def in_view(page: Any, selector: str) -> bool:
    """The element is wholly inside the viewport, and nothing covers its corners or centre."""
    return bool(page.eval_on_selector(selector, """el => {
        const r = el.getBoundingClientRect();
        const inside = r.width > 0 && r.top >= 0 && r.left >= 0 && r.bottom <= innerHeight
            && r.right <= innerWidth;
        const d = 8;  // inside rounded corners
        const points = [[r.left + d, r.top + d], [r.right - d, r.top + d],
                        [r.left + d, r.bottom - d], [r.right - d, r.bottom - d],
                        [(r.left + r.right) / 2, (r.top + r.bottom) / 2]];
        return inside && points.every(([x, y]) => el.contains(document.elementFromPoint(x, y)));
    }"""))


def screenshot(page: Any, name: str, full_page: bool = False) -> None:
    folder = os.environ.get("SEPOA_SCREENSHOT_DIR")
    if folder:
        page.screenshot(path=str(Path(folder) / name), full_page=full_page)


def test_the_pairs_instruction_is_shown_and_changes_visibly_with_the_run(
    live: LiveServer, browser: Any, runs: list[int]
) -> None:
    labeller = live.new_labeller("dana")
    runs.append(plain := live.new_human_run())
    (first,) = live.push_rendered_queries(plain, 1)
    runs.append(custom := live.new_human_run(instruction=CUSTOM, clip_size="256x256"))
    (second,) = live.push_rendered_queries(custom, 1)

    page = context_page(browser, 1200, 620)  # short: the page scrolls
    page.goto(f"{live.url}/label#token={labeller.token}")
    page.wait_for_function(DECODED, arg=SHOWN)
    assert int(page.get_attribute(SHOWN, "data-query-id")) == first
    # The task's own instruction, above the clips, with the task's name.
    assert page.get_attribute("#instruction", "data-run") == str(plain)
    goal = default_instruction("dmc:cheetah_run").split("\n")[0]
    assert page.inner_text("#instruction-body .goal") == goal
    assert page.inner_text("#instruction-task") == "cheetah run"
    assert page.is_hidden("#instruction-new")
    top = page.eval_on_selector("#instruction", "el => el.getBoundingClientRect().bottom")
    clip_top = page.eval_on_selector(f"{SHOWN} video", "el => el.getBoundingClientRect().top")
    assert top <= clip_top
    # Kept in view: scrolled to the bottom, the instruction is still on screen.
    page.evaluate("window.scrollTo(0, document.body.scrollHeight)")
    assert page.evaluate("scrollY") > 0 and in_view(page, "#instruction")
    page.evaluate("window.scrollTo(0, 0)")

    # The clips decode at their new size (256 x 256) and are shown at most twice that.
    sizes = page.eval_on_selector_all(f"{SHOWN} video", """videos => videos.map(v =>
        [v.videoWidth, v.videoHeight, v.getBoundingClientRect().width])""")
    assert [(w, h) for w, h, _ in sizes] == [(256, 256), (256, 256)]
    assert all(0 < shown <= 2 * 256 for _, _, shown in sizes)
    # How clip time relates to the task's: cheetah steps are 10 ms, so a third of real time.
    assert page.inner_text("#speed-note") == "Slowed to 1/3 of real time."

    page.wait_for_selector(ANSWERABLE)
    page.keyboard.press("ArrowRight")
    # The next pair is the other run's: its own instruction, flagged as a new task.
    page.wait_for_selector(f'#instruction[data-run="{custom}"]')
    assert int(page.get_attribute(SHOWN, "data-query-id")) == second
    paragraphs = page.eval_on_selector_all("#instruction-body p", "ps => ps.map(p => p.innerText)")
    assert paragraphs == CUSTOM.split("\n")
    assert page.is_visible("#instruction-new") and "changed" in page.get_attribute(
        "#instruction", "class")
    assert page.inner_text("#instruction-body .goal") == CUSTOM.split("\n")[0]
    page.context.close()


def test_one_clock_at_the_chosen_speed_and_answers_by_keyboard_alone(
    live: LiveServer, browser: Any, runs: list[int]
) -> None:
    labeller = live.new_labeller("erin")
    runs.append(run_id := live.new_human_run())
    first, _ = live.push_rendered_queries(run_id, 2)
    page = context_page(browser, 1200, 900)
    page.goto(f"{live.url}/label?run={run_id}#token={labeller.token}")
    page.wait_for_function(DECODED, arg=SHOWN)

    # Speed by keyboard: Tab to the 2x button, Enter; both clips play twice as fast, together.
    page.focus('[data-speed="1"]')
    page.keyboard.press("Tab")
    page.keyboard.press("Enter")
    assert page.get_attribute('[data-speed="2"]', "aria-pressed") == "true"
    assert page.inner_text("#speed-note") == "Slowed to 2/3 of real time."
    page.wait_for_function(f"""() => [...document.querySelectorAll('{SHOWN} video')]
        .every(v => !v.paused && v.playbackRate > 1.5 && v.currentTime > 0.2)""")
    gaps = page.evaluate(f"""() => new Promise(done => {{
        const [a, b] = document.querySelectorAll('{SHOWN} video');
        let gap = 0; const until = performance.now() + 800;
        (function sample() {{
            if (!a.paused && !b.paused && !a.seeking && !b.seeking)
                gap = Math.max(gap, Math.abs(a.currentTime - b.currentTime));
            if (performance.now() < until) requestAnimationFrame(sample); else done(gap);
        }})();
    }})""")
    assert gaps < 0.25
    # The whole pair and every answer are in view at once on a desktop window (the speed
    # buttons, which follow the answers, scrolled the page when focused).
    page.wait_for_selector(ANSWERABLE)
    page.evaluate("window.scrollTo(0, 0)")
    for selector in (f"{SHOWN} .clip:first-child video", f"{SHOWN} .clip:last-child video",
                     "#instruction", '[data-choice="left"]', '[data-choice="skip"]'):
        assert in_view(page, selector), selector
    screenshot(page, "label-page-desktop.png")
    # Every answer button has a name of its own that says what it does.
    for name in ("Left is better", "Right is better", "Equally good", "Can’t tell", "Skip",
                 "Replay"):
        assert page.get_by_role("button", name=name, exact=True).count() == 1, name
    page.wait_for_selector(ANSWERABLE)
    page.keyboard.press("4")  # can't tell
    deadline = time.monotonic() + 5
    while not (labels := labels_for_queries_of(live, first)) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert [label.choice for label in labels] == ["cant_tell"]
    assert page.evaluate(CONTRAST) == []
    page.context.close()


def labels_for_queries_of(live: LiveServer, query_id: int) -> list[Any]:
    with live.sessions() as session:
        return labels_for_queries(session, query_ids=[query_id])


def test_on_laptop_windows_the_clips_player_and_answers_are_all_in_view_uncovered(
    live: LiveServer, browser: Any, runs: list[int]
) -> None:
    # cheetah_run's instruction, open on the first pair, is four lines at these widths: the
    # clips take what it leaves (test_laptop_screen_browser.py: folded on the next pairs).
    labeller = live.new_labeller("gil")
    runs.append(run_id := live.new_human_run())
    live.push_rendered_queries(run_id, 1)
    heights = {}
    for width, height in ((1366, 768), (1280, 720), (1280, 800)):
        page = context_page(browser, width, height)
        page.goto(f"{live.url}/label?run={run_id}#token={labeller.token}")
        page.wait_for_function(DECODED, arg=SHOWN)
        page.wait_for_selector(ANSWERABLE)
        page.wait_for_timeout(200)  # the clips' fit runs on the next frame
        # Nothing needs a scroll, and the sticky answers cover no control.
        for selector in (f"{SHOWN} .clip:first-child video", f"{SHOWN} .clip:last-child video",
                         "#instruction", "#play", "#frame-back", "#scrub", "#frame-next",
                         '[data-choice="left"]', '[data-choice="right"]', "#replay",
                         '[data-choice="skip"]'):
            assert in_view(page, selector), (width, height, selector)
        heights[height] = page.eval_on_selector(
            f"{SHOWN} video", "v => v.getBoundingClientRect().height")
        # Above the least clip height, the answers end at the window's foot.
        foot = page.eval_on_selector("#answer-bar", "b => b.getBoundingClientRect().bottom")
        assert height - 12 <= foot <= height, (width, height, foot)
        page.context.close()
    # A taller window gives the clips the height it adds.
    assert heights[720] < heights[768] and heights[720] < heights[800]
    assert heights[800] - heights[720] == pytest.approx(80, abs=2)


def test_a_phone_width_stacks_the_clips_and_keeps_the_answers_in_view(
    live: LiveServer, browser: Any, runs: list[int]
) -> None:
    labeller = live.new_labeller("fay")
    runs.append(run_id := live.new_human_run(clip_size="320x240"))
    live.push_rendered_queries(run_id, 1)
    page = context_page(browser, 375, 667)
    page.goto(f"{live.url}/label?run={run_id}#token={labeller.token}")
    page.wait_for_function(DECODED, arg=SHOWN)
    page.wait_for_selector(ANSWERABLE)

    assert page.evaluate("document.documentElement.scrollWidth") <= 375  # no sideways scroll
    boxes = page.eval_on_selector_all(f"{SHOWN} video", """videos => videos.map(v => {
        const r = v.getBoundingClientRect(); return [r.left, r.top, r.right, r.bottom]; })""")
    (left0, top0, right0, bottom0), (left1, top1, right1, bottom1) = boxes
    assert bottom0 <= top1  # one above the other, each the page's width
    assert right0 - left0 >= page.evaluate("document.body.clientWidth") - 16
    for selector in ("#instruction", '[data-choice="left"]', '[data-choice="equal"]',
                     '[data-choice="right"]', '[data-choice="cant_tell"]',
                     '[data-choice="skip"]', "#replay", "#play", "#scrub"):
        assert in_view(page, selector), selector
    # The sides are named as they are laid out; the buttons' names say so too.
    assert page.get_by_role("button", name="Top is better", exact=True).count() == 1
    assert page.get_by_role("button", name="Bottom is better", exact=True).count() == 1
    # The instruction shows its goal, open on the first pair; its button folds it to one line,
    # which leaves the top clip in view too, and opens it again.
    assert page.is_visible("#instruction-body .goal")
    page.click("#instruction-more")
    assert page.get_attribute("#instruction-more", "aria-expanded") == "false"
    assert page.is_visible("#instruction-body .goal")
    page.wait_for_timeout(200)  # the clips' fit runs on the next frame
    assert in_view(page, f"{SHOWN} .clip:first-child video")
    page.click("#instruction-more")
    assert page.get_attribute("#instruction-more", "aria-expanded") == "true"
    assert page.evaluate(CONTRAST) == []
    screenshot(page, "label-page-phone.png")
    page.context.close()


def test_an_invite_link_signs_a_new_browser_in_and_its_answer_is_its_own(
    live: LiveServer, browser: Any, runs: list[int]
) -> None:
    runs.append(run_id := live.new_human_run())
    (query_id,) = live.push_rendered_queries(run_id, 1)
    invite = live.api("POST", "/api/invites",
                      json={"run_id": run_id, "max_uses": 5, "target_answers": 1,
                            "completion_code": "DONE-7"})

    page = context_page(browser, 1000, 900)  # a fresh browser: no token of any kind
    page.goto(f"{invite['url']}?participant=PID42")
    page.wait_for_selector("#join-start:not([hidden])")
    assert "PID42" in page.inner_text("#join-status")
    assert "forward" in page.inner_text(".join-instruction")  # the run's instruction
    assert "Can’t tell" in page.inner_text(".howto")
    assert page.evaluate("document.activeElement.id") == "join-start"
    assert page.evaluate(CONTRAST) == []
    page.keyboard.press("Enter")  # keyboard alone: the focused Start link
    page.wait_for_url(f"**/label?run={run_id}")
    page.wait_for_function(DECODED, arg=SHOWN)
    page.wait_for_selector(ANSWERABLE)
    page.keyboard.press("1")

    joined = find_labeller_when(live, "PID42")
    deadline = time.monotonic() + 5
    while not (labels := labels_for_queries_of(live, query_id)) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert [(label.labeller_id, label.choice) for label in labels] == [(joined, "left")]
    # The target (one answer) is reached: the participant's own completion code is shown.
    page.wait_for_selector("#completion:not([hidden])")
    code = page.inner_text("#completion-code")
    assert code.startswith("DONE-7-")
    assert live.api("POST", "/api/invites/verify", json={"code": code})["participant"] == "PID42"
    # Opening the link again in this browser keeps the labeller it made.
    page.goto(f"{invite['url']}?participant=PID42")
    page.wait_for_selector("#join-start:not([hidden])")
    assert live.api("GET", "/api/invites")[-1]["uses"] == 1
    page.context.close()


def find_labeller_when(live: LiveServer, name: str) -> int:
    with live.sessions() as session:
        labeller = find_labeller(session, name=name)
    assert labeller is not None
    return labeller.id


def test_a_revoked_invite_link_is_refused_with_a_plain_page(
    live: LiveServer, browser: Any
) -> None:
    invite = live.api("POST", "/api/invites", json={})
    live.api("POST", f"/api/invites/{invite['id']}/revoke")
    page = context_page(browser, 1000, 800)
    response = page.goto(invite["url"])
    assert response.status == 410
    assert "withdrawn" in page.inner_text(".join-refused")
    assert "Traceback" not in page.content()
    assert page.evaluate("localStorage.getItem('sepoa.labeller-token')") is None
    page.context.close()


def test_operators_set_instructions_and_clip_sizes_and_make_and_revoke_invite_links(
    live: LiveServer, browser: Any, runs: list[int]
) -> None:
    page = context_page(browser, 1300, 1000)
    page.on("dialog", lambda dialog: dialog.accept())
    page.goto(f"{live.url}/runs#token={OPERATOR_TOKEN}")
    page.wait_for_selector("#invites-body tr")
    # A new run with its own instruction and the widescreen clip size.
    page.fill("#new-run [name=task]", "dmc:walker_run")
    page.fill("#new-run [name=name]", "walker-wide")
    page.select_option("#new-run [name=clip_size]", "320x240")
    page.fill("#new-run [name=instruction]", "Upright first.\nThen faster is better.")
    page.click("#new-run [type=submit]")
    page.wait_for_selector("#runs-body a:text('walker-wide')")
    run = next(r for r in live.api("GET", "/api/runs") if r["name"] == "walker-wide")
    runs.append(run["id"])
    assert run["clip_size"] == "320x240"
    assert run["instruction"] == "Upright first.\nThen faster is better."

    # An invite link for that run, with a target; it is listed with its link, then revoked.
    page.wait_for_selector(f'#new-invite [name=run_id] option[value="{run["id"]}"]',
                           state="attached")
    page.select_option("#new-invite [name=run_id]", str(run["id"]))
    page.fill("#new-invite [name=max_uses]", "3")
    page.fill("#new-invite [name=target_answers]", "20")
    page.fill("#new-invite [name=note]", "pilot")
    page.click("#new-invite [type=submit]")
    page.wait_for_selector("#new-invite-result code")
    url = page.inner_text("#new-invite-result code")
    invite = next(i for i in live.api("GET", "/api/invites") if i["url"] == url)
    assert (invite["run_id"], invite["max_uses"], invite["target_answers"]) == (run["id"], 3, 20)
    row = f'#invites-body tr[data-invite="{invite["id"]}"]'
    page.wait_for_selector(row)
    assert "open" in page.inner_text(row) and "0 / 3" in page.inner_text(row)
    screenshot(page, "runs-page.png", full_page=True)
    page.click(f"{row} button:text('Revoke')")
    page.wait_for_function(f"""() => document.querySelector('{row}')
        ?.textContent.includes('revoked')""")
    assert next(i for i in live.api("GET", "/api/invites")
                if i["id"] == invite["id"])["state"] == "revoked"
    # A refused invite explains itself field by field.
    page.fill("#new-invite [name=max_uses]", "0")
    page.click("#new-invite [type=submit]")
    page.wait_for_selector("#new-invite-errors:not([hidden])")
    assert "max_uses" in page.inner_text("#new-invite-errors")

    # The run page edits the instruction later, and goes back to the task's own.
    page.goto(f"{live.url}/runs/{run['id']}")
    page.wait_for_function("document.querySelector('#instruction-text').value.length > 0")
    assert page.input_value("#instruction-text") == "Upright first.\nThen faster is better."
    page.fill("#instruction-text", "Faster is better.")
    page.click("#instruction-form [type=submit]")
    page.wait_for_selector("#notice:has-text('Instruction saved')")  # the PUT has answered
    assert page.inner_text("#instruction-origin") == "the operator's"
    assert live.api("GET", f"/api/runs/{run['id']}")["instruction"] == "Faster is better."
    page.click("#instruction-reset")
    page.wait_for_function("document.querySelector('#instruction-origin').textContent"
                           ".includes('task')")
    assert live.api("GET", f"/api/runs/{run['id']}")["instruction"] is None
    assert page.input_value("#instruction-text") == default_instruction("dmc:walker_run")
    screenshot(page, "run-page.png", full_page=True)
    page.context.close()


def test_undo_brings_the_last_pair_back_and_the_export_shows_the_withdrawal(
    live: LiveServer, browser: Any, runs: list[int]
) -> None:
    labeller = live.new_labeller("gus")
    runs.append(run_id := live.new_human_run())
    first, second, _ = live.push_rendered_queries(run_id, 3)
    page = context_page(browser, 1200, 900)
    page.goto(f"{live.url}/label?run={run_id}#token={labeller.token}")
    page.wait_for_function(DECODED, arg=SHOWN)
    page.wait_for_selector(ANSWERABLE)
    assert page.is_hidden("#undo")

    page.keyboard.press("1")  # a mis-key: left
    page.wait_for_selector(f'{SHOWN}[data-query-id="{second}"]')
    assert page.is_visible("#undo")
    deadline = time.monotonic() + 5
    while not labels_for_queries_of(live, first) and time.monotonic() < deadline:
        time.sleep(0.05)
    page.wait_for_function("document.querySelector('#count-session').textContent === '1'")
    page.keyboard.press("Backspace")
    # The pair comes back on screen, the one that replaced it waits, preloaded.
    page.wait_for_selector(f'{SHOWN}[data-query-id="{first}"]')
    page.wait_for_function(DECODED, arg=SHOWN)
    assert "taken back" in page.inner_text("#notice")
    assert page.get_attribute(f'#pairs .pair[data-query-id="{second}"]', "hidden") is not None
    assert page.inner_text("#count-session") == "0"
    assert labels_for_queries_of(live, first) == []  # the trainer will not see it

    page.wait_for_selector(ANSWERABLE)
    page.keyboard.press("2")  # the intended answer
    page.wait_for_selector(f'{SHOWN}[data-query-id="{second}"]')
    deadline = time.monotonic() + 5
    while not labels_for_queries_of(live, first) and time.monotonic() < deadline:
        time.sleep(0.05)
    [kept] = labels_for_queries_of(live, first)
    assert kept.choice == "right"
    rows = [row for row in live.api_text("GET", f"/api/export?format=jsonl&run_id={run_id}")
            if row["query_id"] == first]
    assert [(row["choice"], row["withdrawn_at"] is not None) for row in rows] == [
        ("left", True), ("right", False)]

    # Too late: the server says so, plainly, and the answer stands.
    with live.sessions() as session, session.begin():
        session.execute(update(Label).where(Label.id == kept.id)
                        .values(answered_at=utcnow() - timedelta(seconds=30)))
    page.keyboard.press("u")
    page.wait_for_function("document.querySelector('#notice').textContent.includes('10 s only')")
    assert "Undo refused" in page.inner_text("#notice")
    assert int(page.get_attribute(SHOWN, "data-query-id")) == second
    assert [label.id for label in labels_for_queries_of(live, first)] == [kept.id]
    page.context.close()
