"""The operator's pages in a real headless Chromium: the new-run form shows the API's 422
errors and creates runs; a run's page draws its curves, pauses it and downloads its labels;
the labellers panel revokes, restores and re-keys a labeller."""

from __future__ import annotations

import json
from datetime import timedelta
from pathlib import Path
from typing import Any

import httpx
from sqlalchemy import func, select
from web_helpers import OPERATOR_TOKEN, LiveServer

from labelqueue import (
    Run,
    RunStatus,
    Worker,
    create_labeller,
    heartbeat,
    lease_next_query,
    read_run,
    submit_label,
    write_metrics,
)
from labelqueue.models import utcnow


def test_the_new_run_form_explains_refusals_and_creates_runs(live: LiveServer, page: Any) -> None:
    page.goto(f"{live.url}/runs#token={OPERATOR_TOKEN}")
    page.wait_for_selector("#runs-body tr")

    page.fill("#new-run [name=task]", "cheetah")
    page.fill("#new-run [name=budget]", "-1")
    page.click("#new-run [type=submit]")
    page.wait_for_selector("#new-run-errors:not([hidden])")
    errors = page.inner_text("#new-run-errors")
    assert "task: unknown task 'cheetah' (did you mean 'dmc:cheetah_run'?)" in errors
    assert "budget: Input should be greater than or equal to 0" in errors

    # A whole-run refusal points at the config field and says what is valid.
    page.fill("#new-run [name=task]", "dmc:walker_run")
    page.fill("#new-run [name=budget]", "200")
    page.fill("#new-run [name=config]", '{"feedback.per_rund": 10}')
    page.click("#new-run [type=submit]")
    page.wait_for_selector("#new-run-errors:has-text('per_rund')")
    errors = page.inner_text("#new-run-errors")
    assert ("config.feedback.per_rund: unknown config field 'feedback.per_rund' (did you mean "
            "'feedback.per_round'?)") in errors
    page.fill("#new-run [name=config]", "")

    page.fill("#new-run [name=task]", "dmc:walker_run")
    page.fill("#new-run [name=budget]", "200")
    page.select_option("#new-run [name=teacher]", "scripted")
    page.fill("#new-run [name=eps]", "0.3")
    page.fill("#new-run [name=name]", "walker-from-the-form")
    page.click("#new-run [type=submit]")
    page.wait_for_selector("#runs-body a:text('walker-from-the-form')")
    assert page.is_hidden("#new-run-errors")
    created = next(r for r in live.api("GET", "/api/runs") if r["name"] == "walker-from-the-form")
    assert (created["task"], created["budget"], created["teacher"]) == (
        "dmc:walker_run",
        200,
        "scripted",
    )
    assert created["teacher_params"] == {"eps": 0.3}
    # Out of the queue again: other tests' workers claim the oldest queued run.
    live.api("POST", f"/api/runs/{created['id']}/stop")


def test_a_run_page_draws_curves_pauses_the_run_and_exports_its_labels(
    live: LiveServer, page: Any, tmp_path: Path
) -> None:
    run_id = live.new_human_run()
    live.push_rendered_queries(run_id, 1)
    with live.sessions() as session:
        for step in (1000, 2000, 3000):
            write_metrics(
                session,
                run_id=run_id,
                stream="episodes",
                step=step,
                values={"return": step / 10, "labels_used": step // 1000},
            )
        write_metrics(session, run_id=run_id, stream="eval", step=3000, values={"return": 250.0})
        for round_ in (1, 2):
            write_metrics(
                session,
                run_id=run_id,
                stream="rounds",
                step=1000 * round_,
                values={
                    "round": round_,
                    "distinguishable_ratio": 0.5,
                    "model_agreement": 0.6,
                    "shadow_agreement": None,
                    "reward_corr": 0.2 * round_,
                },
            )
        teacher, _ = create_labeller(session, name=f"scripted-{run_id}")
        query = lease_next_query(session, labeller_id=teacher.id, run_id=run_id)
        assert query is not None
        submit_label(
            session,
            query_id=query.id,
            labeller_id=teacher.id,
            choice="right",
            left_is_first=True,
            source="scripted",
        )

    page.goto(f"{live.url}/runs/{run_id}#token={OPERATOR_TOKEN}")
    page.wait_for_selector("#chart-return svg polyline")
    assert page.locator("#chart-return circle").count() == 4  # 3 episodes + 1 evaluation
    assert page.locator("#chart-agreement circle").count() == 2  # the null series is left out
    assert page.locator("#chart-reward-corr circle").count() == 2
    assert "Learned reward vs true reward" in page.inner_text("#chart-reward-corr")
    assert "1 label (1 scripted)" in page.inner_text("#chart-throughput")
    assert page.locator("#chart-throughput rect").count() == 1
    # The report's figure of this run beside its peers, fetched with the operator's token.
    page.wait_for_function(
        "() => { const i = document.getElementById('peers-img');"
        " return !i.hidden && i.complete && i.naturalWidth > 300; }")
    # The teacher-calibration figure of the run's answers (docs/QUALITY.md), the same way.
    page.wait_for_function(
        "() => { const i = document.getElementById('calibration-img');"
        " return !i.hidden && i.complete && i.naturalWidth > 300; }")

    page.click("#controls button:text('Pause')")
    page.wait_for_selector("#run-status:text('paused')")
    with live.sessions() as session:
        assert read_run(session, run_id=run_id).status is RunStatus.PAUSED

    with page.expect_download() as download_info:
        page.click("[data-export=jsonl]")
    download = download_info.value
    assert download.suggested_filename.startswith(f"labels-run{run_id}")
    saved = tmp_path / "labels.jsonl"
    download.save_as(saved)
    rows = [json.loads(line) for line in saved.read_text().splitlines()]
    assert [(row["run_id"], row["choice"]) for row in rows] == [(run_id, "right")]


def test_the_runs_page_revokes_restores_and_rekeys_a_labeller(live: LiveServer, page: Any) -> None:
    created = live.api("POST", "/api/labellers", json={"name": "page-revokes-me"})
    old = {"Authorization": f"Bearer {created['token']}"}
    page.on("dialog", lambda dialog: dialog.accept())  # the confirmations
    page.goto(f"{live.url}/runs#token={OPERATOR_TOKEN}")
    row = "#labellers-body tr[data-labeller='page-revokes-me']"
    page.wait_for_selector(row)

    page.click(f"{row} button:text('Revoke')")
    page.wait_for_selector(f"{row} .badge:text('revoked')")
    assert httpx.get(f"{live.url}/api/label/count", headers=old).status_code == 401

    page.click(f"{row} button:text('Activate')")
    page.wait_for_selector(f"{row} .badge:text('active')")
    assert httpx.get(f"{live.url}/api/label/count", headers=old).status_code == 200

    page.click(f"{row} button:text('New token')")
    page.wait_for_selector("#new-token:not([hidden]) code")
    new = page.inner_text("#new-token code")
    assert new != created["token"] and "page-revokes-me" in page.inner_text("#new-token")
    assert httpx.get(f"{live.url}/api/label/count", headers=old).status_code == 401
    fresh = {"Authorization": f"Bearer {new}"}
    assert httpx.get(f"{live.url}/api/label/count", headers=fresh).status_code == 200


def test_the_pages_show_a_teacher_error_rate_set_by_a_config_override(
    live: LiveServer, page: Any
) -> None:
    run_id = live.new_human_run(teacher="scripted", config={"teacher.eps": 0.3})
    try:
        page.goto(f"{live.url}/runs#token={OPERATOR_TOKEN}")
        row = page.locator(f"#runs-body tr:has(a[href='/runs/{run_id}'])").first
        row.wait_for()
        assert "scripted ε=0.3" in row.inner_text()
        page.goto(f"{live.url}/runs/{run_id}#token={OPERATOR_TOKEN}")
        page.wait_for_selector("#run-facts dd")
        assert "scripted (ε=0.3)" in page.inner_text("#run-facts")
    finally:
        live.stop_run(run_id)


def test_a_run_page_for_an_id_no_run_can_have_says_so_once(live: LiveServer, page: Any) -> None:
    asked: list[str] = []
    page.on("request", lambda request: asked.append(request.url) if "/api/" in request.url
            else None)
    page.clock.install()  # the page's timers run when the test says
    with page.expect_response(lambda response: "/api/quality/agreement" in response.url) as card:
        page.goto(f"{live.url}/runs/-5#token={OPERATOR_TOKEN}")
    assert card.value.status == 422
    page.wait_for_selector("#notice:not([hidden])")
    page.wait_for_selector("#loading", state="hidden")
    notice = page.inner_text("#notice")
    assert "greater than or equal to 1" in notice and "Could not refresh" not in notice
    first = sorted(asked)
    page.clock.run_for(95_000)  # past every refresh period of the page (5 s, 30 s)
    page.wait_for_timeout(500)
    assert sorted(asked) == first, "asked again"  # every refresh stopped


def test_a_run_page_asks_only_for_new_curve_points_and_sees_a_resume_rewrite_them(
        live: LiveServer, page: Any) -> None:
    run_id = live.new_human_run()
    worker = f"web-test-worker-{run_id}"

    def episode(session: Any, step: int, value: float) -> None:
        write_metrics(session, run_id=run_id, stream="episodes", step=step,
                      values={"return": value, "labels_used": 0})

    with live.sessions() as session:
        heartbeat(session, run_id=run_id, worker_id=worker, step=2000)
        episode(session, 1000, 100.0)
        episode(session, 2000, 200.0)
    asked: list[str] = []
    page.on("request", lambda request: asked.append(request.url) if "/metrics?" in request.url
            else None)
    page.goto(f"{live.url}/runs/{run_id}#token={OPERATOR_TOKEN}")
    dots = "#chart-return circle title"
    page.wait_for_function(f"document.querySelectorAll('{dots}').length === 2")
    with live.sessions() as session:
        heartbeat(session, run_id=run_id, worker_id=worker, step=3000)
        episode(session, 3000, 300.0)
    page.wait_for_function(f"document.querySelectorAll('{dots}').length === 3", timeout=15_000)
    # A worker resumes the run from its checkpoint at step 1500 and writes steps 2000 and 3000
    # again: the page shows the new values, not the ones it had.
    with live.sessions() as session:
        heartbeat(session, run_id=run_id, worker_id=worker, step=1500)
        episode(session, 2000, 222.0)
        episode(session, 3000, 333.0)
    page.wait_for_function(
        f"[...document.querySelectorAll('{dots}')].map(t => t.textContent).join(' ')"
        ".includes(': 222') && [...document.querySelectorAll('" + dots + "')]"
        ".map(t => t.textContent).join(' ').includes(': 333')", timeout=20_000)
    titles = page.eval_on_selector_all(dots, "ts => ts.map(t => t.textContent)")
    assert len(titles) == 3 and not any(": 200" in t or ": 300" in t for t in titles), titles
    # Episodes past the first refresh: only those after a step the page has (the empty streams
    # are asked whole: there is nothing of them to send again).
    episodes = [url for url in asked if "stream=episodes" in url]
    assert "after_step" not in episodes[0] and len(episodes) > 2
    assert all("after_step=" in url for url in episodes[1:]), episodes
    live.stop_run(run_id)


def test_the_runs_page_shows_the_newest_runs_and_the_workers_heard_from_lately(
        live: LiveServer, page: Any) -> None:
    with live.sessions() as session, session.begin():
        have = session.scalar(select(func.count()).select_from(Run)) or 0
        session.add_all(Run(name=f"old-{i}", task="dmc:cheetah_run", algo="pebble",
                            preset="tiny", seed=i, config={}, teacher="human",
                            teacher_params={}, budget=10, status="finished", progress={})
                        for i in range(max(0, 105 - have)))
        session.merge(Worker(id="restarted-long-ago", host="old-host",
                             first_seen_at=utcnow() - timedelta(days=3),
                             last_seen_at=utcnow() - timedelta(days=2)))
    total = len(live.api("GET", "/api/runs"))
    page.goto(f"{live.url}/runs#token={OPERATOR_TOKEN}")
    page.wait_for_selector("#runs-body tr a")
    assert page.locator("#runs-body tr").count() == 100  # the newest 100 of them
    newest = max(run["id"] for run in live.api("GET", "/api/runs?limit=1"))
    assert page.inner_text("#runs-body tr:first-child td:first-child") == str(newest)
    page.click("#runs-more")
    page.wait_for_function(f"document.querySelectorAll('#runs-body tr').length === {total}")
    assert page.locator("#runs-more").is_hidden()  # no older ones left
    page.wait_for_selector("#workers-body tr")
    assert page.locator("#workers-body tr[data-worker='restarted-long-ago']").count() == 0


def test_an_operator_who_gives_themselves_a_new_token_stays_signed_in_with_it(
        live: LiveServer, page: Any) -> None:
    me = live.api("POST", "/api/labellers", json={"name": "operator-self", "role": "operator"})
    page.on("dialog", lambda dialog: dialog.accept())
    page.goto(f"{live.url}/runs#token={me['token']}")
    row = "#labellers-body tr[data-labeller='operator-self']"
    page.wait_for_selector(row)
    page.wait_for_selector("#updated:text('updated')")
    page.click(f"{row} button:text('New token')")
    page.wait_for_selector("#new-token:not([hidden]) code")
    new = page.inner_text("#new-token code")
    assert new != me["token"]
    # The runs poll (every 5 s) goes on with the new token: still signed in, the token shown.
    before = page.inner_text("#updated")
    page.wait_for_function(f"document.getElementById('updated').textContent !== {before!r}",
                           timeout=15_000)
    assert page.locator("#app").is_visible() and page.locator("#signin").is_hidden()
    assert page.inner_text("#new-token code") == new
    assert "this page now signs in with it" in page.inner_text("#new-token")
    assert page.evaluate("localStorage.getItem('sepoa.operator-token')") == new
    old = {"Authorization": f"Bearer {me['token']}"}
    assert httpx.get(f"{live.url}/api/runs?limit=1", headers=old).status_code == 401
    page.reload()  # a later visit signs in with it too
    page.wait_for_selector(row)
    assert page.locator("#signin").is_hidden()


def test_the_invites_and_labellers_panels_refresh_and_link_each_links_participants(
        live: LiveServer, page: Any) -> None:
    run_id = live.new_human_run()
    invite = live.api("POST", "/api/invites", json={"run_id": run_id, "note": "refreshed"})
    page.clock.install()
    page.goto(f"{live.url}/runs#token={OPERATOR_TOKEN}")
    row = f"#invites-body tr[data-invite='{invite['id']}']"
    page.wait_for_selector(row)
    link = page.locator(f"{row} a.participants-link")
    assert link.get_attribute("href") == f"/invites/{invite['id']}/participants"
    assert page.inner_text(f"{row} td:nth-child(4)") == "0"
    assert page.locator("#labellers-body tr[data-labeller='late-comer']").count() == 0

    httpx.post(f"{live.url}/api/join/{invite['code']}", json={"participant": "P-REFRESH"})
    live.api("POST", "/api/labellers", json={"name": "late-comer"})
    live.stop_run(run_id)  # its link closes: nobody can join any more
    page.clock.run_for(31_000)
    page.wait_for_selector(f"{row} td:nth-child(4):text-is('1')")
    page.wait_for_selector(f"{row} .badge:text-is('closed')")
    page.wait_for_selector("#labellers-body tr[data-labeller='late-comer']")
    page.click(f"{row} a.participants-link")
    page.wait_for_url(f"**/invites/{invite['id']}/participants")
    page.wait_for_selector("#participants-body :text('P-REFRESH')")
