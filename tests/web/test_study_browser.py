"""A crowd study from invite to payment, in a real headless Chromium on a phone-sized screen:
a stopped run's invite shows a closed page; a run that ends mid-session gives "study complete"
with the participant's own code, a copy button and the redirect; a worker paused by check pairs
gets the paused screen with their code (or the operator's message); the waiting screen says why.
The operator's run page shows "waiting for 10 answers" while labellers are paused, "waiting for
a free worker" when none is free, and the workers panel shows a dead worker as dead.

With SEPOA_SCREENSHOT_DIR set, the screens are saved there (the docs/study-*.png files)."""

from __future__ import annotations

import os
from datetime import timedelta
from pathlib import Path
from typing import Any

from sqlalchemy import update
from web_helpers import OPERATOR_TOKEN, LiveServer

from labelqueue import LabellerPause, Worker, finish_run, heartbeat, write_metrics
from labelqueue.models import utcnow

PHONE = {"width": 390, "height": 844}
ANSWERABLE = '[data-choice="left"]:not([disabled])'
REDIRECT = "https://study.example.org/complete?cc=C0FFEE"


def phone(browser: Any) -> Any:
    context = browser.new_context(viewport=PHONE, has_touch=True, is_mobile=True)
    page = context.new_page()
    page.set_default_timeout(15_000)
    return page


def screenshot(page: Any, name: str, selector: str | None = None,
               height: int | None = None) -> None:
    """The page (its top `height` pixels), or one element, as a PNG in SEPOA_SCREENSHOT_DIR."""
    folder = os.environ.get("SEPOA_SCREENSHOT_DIR")
    if not folder:
        return
    path = str(Path(folder) / name)
    if selector:
        page.locator(selector).screenshot(path=path)
    elif height:
        width = page.viewport_size["width"]
        page.screenshot(path=path, clip={"x": 0, "y": 0, "width": width, "height": height})
    else:
        page.screenshot(path=path)


def join_and_start(page: Any, url: str, participant: str) -> None:
    page.goto(f"{url}?PROLIFIC_PID={participant}")  # a platform's own parameter
    page.wait_for_selector("#join-start:not([hidden])")
    assert participant in page.inner_text("#join-status")
    page.click("#join-start")
    page.wait_for_url("**/label?run=*")


def test_a_stopped_runs_invite_shows_a_closed_page(
    live: LiveServer, browser: Any, runs: list[int]
) -> None:
    runs.append(run_id := live.new_human_run())
    invite = live.api("POST", "/api/invites", json={"run_id": run_id, "max_uses": 5})
    live.stop_run(run_id)
    page = phone(browser)
    response = page.goto(f"{invite['url']}?participant=P-late")
    assert response.status == 410
    assert page.inner_text("h1") == "This study has ended"
    assert "training run is over" in page.inner_text(".join-refused")
    assert page.evaluate("localStorage.getItem('sepoa.labeller-token')") is None
    listed = next(i for i in live.api("GET", "/api/invites") if i["id"] == invite["id"])
    assert (listed["state"], listed["uses"]) == ("closed", 0)  # nobody took a slot
    screenshot(page, "study-closed-phone.png")
    page.context.close()


def test_participants_sharing_a_browser_each_join_as_themselves(
    live: LiveServer, browser: Any, runs: list[int]
) -> None:
    runs.append(run_id := live.new_human_run())
    invite = live.api("POST", "/api/invites", json={"run_id": run_id, "max_uses": 5})
    page = phone(browser)
    token = "localStorage.getItem('sepoa.labeller-token')"
    join_and_start(page, invite["url"], "SHARED-A")
    first = page.evaluate(token)
    # Another participant's link in the same browser: they join as themselves, not as A.
    join_and_start(page, invite["url"], "SHARED-B")
    second = page.evaluate(token)
    assert second != first
    names = [lab["name"] for lab in live.api("GET", "/api/labellers")]
    assert "SHARED-A" in names and "SHARED-B" in names
    # A's link again: A is given back (a new token, no new use of the link).
    join_and_start(page, invite["url"], "SHARED-A")
    assert page.evaluate(token) not in (first, second)
    listed = next(i for i in live.api("GET", "/api/invites") if i["id"] == invite["id"])
    assert listed["uses"] == 2
    page.context.close()


def test_a_run_that_ends_mid_session_gives_study_complete_with_the_code_and_redirect(
    live: LiveServer, browser: Any, runs: list[int]
) -> None:
    runs.append(run_id := live.new_human_run())
    live.push_rendered_queries(run_id, 1)
    invite = live.api("POST", "/api/invites", json={
        "run_id": run_id, "target_answers": 20, "completion_code": "CHEETAH",
        "redirect_url": REDIRECT, "consent_text": "Your answers are kept for research.\n"
                                                   "You may stop at any time."})
    page = phone(browser)
    page.goto(f"{invite['url']}?PROLIFIC_PID=W-1")
    # The consent text first: nobody joins (or takes a slot) before agreeing.
    page.wait_for_selector("#consent-agree")
    assert "kept for research" in page.inner_text("#consent")
    assert page.is_hidden("#join-start")
    assert live.api("GET", "/api/invites")[-1]["uses"] == 0
    # A phone lists no keyboard keys.
    assert page.is_hidden(".howto kbd") and page.is_visible(".howto .without-keys")
    screenshot(page, "study-consent-phone.png")
    page.click("#consent-agree")
    page.wait_for_selector("#join-start:not([hidden])")
    status = page.inner_text("#join-status")
    assert "W-1" in status and "below" in status
    page.click("#join-start")
    page.wait_for_url(f"**/label?run={run_id}")
    # One run only, with no "all runs" link: the study is that run.
    page.wait_for_function(f"document.querySelector('#scope').textContent === 'Run {run_id}'")
    page.wait_for_selector(ANSWERABLE)
    page.click(ANSWERABLE)
    # Nothing left: the page says why while the run trains on.
    page.wait_for_selector("#waiting:not([hidden])")
    page.wait_for_function("document.querySelector('#waiting-why').textContent.length > 0")
    assert "1 of 20" in page.inner_text("#count-target")
    # Another run's pairs are not theirs: refused, and they stay signed in.
    refused = page.evaluate("""async (other) => {
      const api = await import("/static/api.js");
      try { await api.request("GET", `/api/label/next?run_id=${other}`); return "served"; }
      catch (error) { return `${error.constructor.name} ${error.status}: ${error.message}`; }
    }""", run_id + 1)
    assert refused.startswith(f"ApiError 403: you joined this study for run {run_id}")
    assert page.is_hidden("#signin") and page.is_visible("#app")

    # The run ends (a worker finishes it) before the target: the study is complete anyway.
    with live.sessions() as session:
        finish_run(session, run_id=run_id, worker_id=f"web-test-worker-{run_id}")
    page.wait_for_selector("#completion:not([hidden])")
    assert page.is_hidden("#waiting") and page.is_hidden("#stage")
    assert "has ended" in page.inner_text("#completion-why")
    code = page.inner_text("#completion-code")
    assert code.startswith("CHEETAH-") and len(code) == len("CHEETAH-XXXX-XXXX-XXXX")
    redirect = page.get_attribute("#completion-redirect", "href")
    assert redirect == f"{REDIRECT}&participant=W-1"
    assert page.is_visible("#completion-copy") and page.is_hidden("#completion-more")
    page.context.grant_permissions(["clipboard-read", "clipboard-write"])
    page.click("#completion-copy")
    page.wait_for_function("document.querySelector('#completion-copy').textContent !== 'Copy'")
    screenshot(page, "study-complete-phone.png")
    checked = live.api("POST", "/api/invites/verify", json={"code": code})
    assert (checked["participant"], checked["counted"], checked["why"]) == ("W-1", 1, "runs_over")
    # The platform's page, answered in the browser itself (no request leaves the machine).
    arrived: list[str] = []
    page.route("https://study.example.org/**", lambda route: (
        arrived.append(route.request.url), route.fulfill(body="submission complete")))
    page.click("#completion-redirect")
    page.wait_for_url(f"{REDIRECT}&participant=W-1")
    assert arrived == [f"{REDIRECT}&participant=W-1"]
    page.context.close()


def test_a_worker_paused_by_check_pairs_gets_their_code_or_the_operators_message(
    live: LiveServer, browser: Any, runs: list[int]
) -> None:
    runs.append(run_id := live.new_human_run(config={"feedback.gold_min_accuracy": 0.8}))
    live.push_rendered_queries(run_id, 4)  # each page holds two: the shown and the next
    coded = live.api("POST", "/api/invites", json={"run_id": run_id, "target_answers": 10})
    told = live.api("POST", "/api/invites", json={
        "run_id": run_id, "pause_message": "Please return the study on the platform: you will "
                                           "be paid for the time you spent."})
    pages = []
    for invite, who in ((coded, "GOLD-1"), (told, "GOLD-2")):
        page = phone(browser)
        join_and_start(page, invite["url"], who)
        page.wait_for_selector(ANSWERABLE)
        pages.append(page)
    with live.sessions() as session:  # as three wrong answers on check pairs would have done
        for who in ("GOLD-1", "GOLD-2"):
            labeller = next(lab for lab in live.api("GET", "/api/labellers")
                            if lab["name"] == who)
            session.add(LabellerPause(run_id=run_id, labeller_id=labeller["id"],
                                      gold_answers=3, gold_correct=0))
        session.commit()

    for page in pages:
        page.reload()
        page.wait_for_selector("#completion:not([hidden])")
        assert page.inner_text("#completion-title") == "Your part in this study has ended"
        assert "check pairs" in page.inner_text("#completion-why")
        assert page.is_hidden("#stage") and page.is_hidden("#waiting")
    first, second = pages
    code = first.inner_text("#completion-code")
    assert live.api("POST", "/api/invites/verify", json={"code": code})["why"] == "paused"
    screenshot(first, "study-paused-phone.png")
    assert second.is_hidden("#completion-code-row")
    assert "paid for the time" in second.inner_text("#completion-message")
    for page in pages:
        page.context.close()


def test_the_run_page_says_what_it_waits_for_and_the_workers_panel_shows_a_dead_worker(
    live: LiveServer, browser: Any, runs: list[int]
) -> None:
    runs.append(run_id := live.new_human_run(teacher_params={"eps": 0.0}))
    live.push_rendered_queries(run_id, 10)
    with live.sessions() as session, session.begin():  # other tests' workers: long gone
        session.execute(update(Worker).where(Worker.id != f"web-test-worker-{run_id}")
                        .values(last_seen_at=utcnow() - timedelta(minutes=20)))
        session.merge(Worker(id="gpu-worker-7", host="gpu-host", run_id=None,
                             first_seen_at=utcnow() - timedelta(hours=1),
                             last_seen_at=utcnow() - timedelta(minutes=9)))
    invite = live.api("POST", "/api/invites", json={"run_id": run_id})
    page = phone(browser)
    join_and_start(page, invite["url"], "PAUSED-1")
    page.wait_for_selector(ANSWERABLE)
    page.context.close()
    with live.sessions() as session:
        labeller = next(lab for lab in live.api("GET", "/api/labellers")
                        if lab["name"] == "PAUSED-1")
        session.add(LabellerPause(run_id=run_id, labeller_id=labeller["id"], gold_answers=3,
                                  gold_correct=0))
        session.commit()
        write_metrics(session, run_id=run_id, stream="rounds", step=400,
                      values={"round": 0, "labels_used": 10, "distinguishable_ratio": 0.5})

    page = browser.new_context(viewport={"width": 1366, "height": 900}).new_page()
    page.set_default_timeout(15_000)
    page.goto(f"{live.url}/runs/{run_id}#token={OPERATOR_TOKEN}")
    page.wait_for_selector("#run-activity:not([hidden])")
    assert page.inner_text("#run-activity") == (
        "Waiting for answers: waiting for 10 answers from 0 active labellers (1 paused by "
        "check pairs)")
    assert "people (scripted shadow teacher ε=0)" in page.inner_text("#run-facts")
    # One round: whole-round ticks, not -0.4 ... 0.4.
    page.wait_for_selector("#chart-distinguishable circle")
    ticks = page.eval_on_selector_all("#chart-distinguishable text.tick.x",
                                      "els => els.map(e => e.textContent)")
    assert ticks and all(tick.lstrip("-").isdigit() for tick in ticks), ticks
    screenshot(page, "run-waiting-answers.png", height=470)

    # A second run while the only live worker trains the first: it waits for a free worker.
    queued = live.api("POST", "/api/runs", json={"task": "dmc:walker_run", "algo": "pebble",
                                                 "preset": "tiny"})
    runs.append(queued["id"])
    assert queued["budget"] == 30  # the tiny preset's own
    page.goto(f"{live.url}/runs/{queued['id']}")
    page.wait_for_selector("#run-activity:not([hidden])")
    assert page.inner_text("#run-activity") == (
        "Queued: waiting for a free worker: 1 worker alive, all busy")

    page.goto(f"{live.url}/runs")
    row = f'#workers-body tr[data-worker="web-test-worker-{run_id}"]'
    page.wait_for_selector(row)
    assert "training" in page.inner_text(row) and str(run_id) in page.inner_text(row)
    dead = page.inner_text('#workers-body tr[data-worker="gpu-worker-7"]')
    assert "gpu-host" in dead and "9 min ago" in dead and "dead" in dead
    queued_row = page.locator("#runs-body tr", has_text="dmc:walker_run").first
    assert "waiting for a free worker (1 busy)" in queued_row.inner_text()
    # At 1366 px the labeller-quality table scrolls in its card, its name column in view.
    page.wait_for_selector("#quality-body tr")
    assert page.evaluate("document.documentElement.scrollWidth <= innerWidth")
    assert page.eval_on_selector("table.quality tbody tr > :first-child",
                                 "el => getComputedStyle(el).position") == "sticky"
    # The runs' scripted teacher is no person: nothing to revoke or re-key.
    scripted = page.locator('#labellers-body tr[data-labeller="scripted-teacher"]')
    if scripted.count():
        assert scripted.locator("button").count() == 0
    screenshot(page, "runs-workers.png", "#workers-card")

    # The form: PEBBLE first, the preset's budget and clip length, S-EPOA's estimate.
    assert page.input_value("#new-run [name=algo]") == "pebble"
    page.fill("#new-run [name=task]", "dmc:cheetah_run")
    page.select_option("#new-run [name=preset]", "tiny")
    page.wait_for_function("document.querySelector('#new-run [name=budget]').placeholder"
                           ".startsWith('30')")
    assert "20 steps play in 0.6 s" in page.inner_text("#clip-note")
    page.fill("#new-run [name=segment_length]", "50")
    assert "50 steps play in 1.5 s" in page.inner_text("#clip-note")
    page.select_option("#new-run [name=preset]", "small")
    page.select_option("#new-run [name=algo]", "sepoa")
    page.wait_for_function("document.querySelector('#timing-note').dataset.pretrain === 'yes'")
    assert "S-EPOA first pretrains skills for this task: 200,000 steps" in \
        page.inner_text("#timing-note")
    # The quality controls are inputs of their own, checked by the server as config fields.
    page.fill("#new-run [name=practice_pairs]", "2")
    page.fill("#new-run [name=gold_rate]", "0.2")
    page.fill("#new-run [name=gold_min_accuracy]", "0.7")
    page.fill("#new-run [name=labels_per_query]", "3")
    screenshot(page, "new-run-form.png", "#new-run")
    page.fill("#new-run [name=labels_per_query]", "11")
    page.click("#new-run button[type=submit]")
    page.wait_for_selector("#new-run-errors:not([hidden])")
    assert "feedback.labels_per_query must be between 1 and 10" in \
        page.inner_text("#new-run-errors")
    page.fill("#new-run [name=labels_per_query]", "3")
    page.fill("#new-run [name=segment_length]", "")  # S-EPOA's SURF crops want the preset's
    page.click("#new-run button[type=submit]")
    page.wait_for_function("document.querySelector('#new-run-result').textContent.length > 0")
    made = max((run for run in live.api("GET", "/api/runs") if run["algo"] == "sepoa"),
               key=lambda run: run["id"])
    runs.append(made["id"])
    values = live.api("GET", f"/api/runs/{made['id']}/config")["values"]
    assert (values["feedback.practice_pairs"], values["feedback.gold_rate"],
            values["feedback.gold_min_accuracy"], values["feedback.labels_per_query"]) == \
        (2, 0.2, 0.7, 3)

    # The invite form on a phone: every field and its button in reach, the run's quality
    # controls shown, the wait limit set there and checked by the server.
    page.context.close()
    page = phone(browser)
    page.goto(f"{live.url}/runs#token={OPERATOR_TOKEN}")
    form = "#new-invite"
    page.wait_for_selector(f"{form} [name=run_id] option[value='{made['id']}']", state="attached")
    for name in ("redirect_url", "consent_text", "pause_message", "wait_limit_s"):
        assert page.locator(f"{form} [name={name}]").is_visible(), name
    assert page.locator(f"{form} button[type=submit]").is_visible()
    assert page.evaluate("document.documentElement.scrollWidth <= innerWidth")
    page.select_option(f"{form} [name=run_id]", str(made["id"]))
    page.wait_for_function("document.querySelector('#invite-run-quality').dataset.practice "
                           "=== '2'")
    assert "3 answer(s) per pair" in page.inner_text("#invite-run-quality")
    page.fill(f"{form} [name=wait_limit_s]", "0")
    page.click(f"{form} button[type=submit]")
    page.wait_for_selector("#new-invite-errors:not([hidden])")
    assert "wait_limit_s" in page.inner_text("#new-invite-errors")
    page.fill(f"{form} [name=wait_limit_s]", "120")
    page.click(f"{form} button[type=submit]")
    page.wait_for_selector("#new-invite-result code")
    invite = max(live.api("GET", "/api/invites"), key=lambda invite: invite["id"])
    assert (invite["run_id"], invite["wait_limit_s"]) == (made["id"], 120)
    page.context.close()


def test_the_label_page_says_the_trainer_is_pretraining_with_an_estimate(
    live: LiveServer, browser: Any, runs: list[int]
) -> None:
    runs.append(run_id := live.new_human_run())
    labeller = live.new_labeller("waits")
    with live.sessions() as session:
        heartbeat(session, run_id=run_id, worker_id=f"web-test-worker-{run_id}", step=0,
                  progress={"pretraining_step": 12_000, "pretraining_steps": 200_000,
                            "pretraining_fps": 230.0})
    page = phone(browser)
    page.goto(f"{live.url}/label?run={run_id}#token={labeller.token}")
    page.wait_for_function("document.querySelector('#waiting-why').textContent.length > 0")
    assert page.inner_text("#waiting-why") == (
        "The trainer is first pretraining its skills, before it asks anything: about 14 min "
        "left.")
    screenshot(page, "label-waiting-phone.png")
    page.context.close()
