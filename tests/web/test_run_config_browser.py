"""The run page shows what the run trains with, in a real headless Chromium: every field of its
stored configuration, the fields the run sets itself marked, and a teacher switch shown there."""

from __future__ import annotations

from typing import Any

from web_helpers import OPERATOR_TOKEN, LiveServer

from labelqueue import finish_run


def test_the_run_page_shows_the_configuration_with_the_runs_own_fields_marked(
        live: LiveServer, page: Any) -> None:
    run_id = live.new_human_run(config={"sac.lr": 0.002}, teacher_params={"eps": 0.1})
    page.goto(f"{live.url}/runs/{run_id}#token={OPERATOR_TOKEN}")
    page.wait_for_selector("#config-rows tr", state="attached")  # in a closed <details>
    assert page.text_content("#config-summary") == "set by this run: sac.lr, teacher.eps"
    page.click("#config-card summary")
    rows = page.eval_on_selector_all("#config-rows tr", """rows => rows.map(row => [
        row.cells[0].textContent, row.cells[1].textContent, row.querySelector("mark") !== null])""")
    shown = {path: (value, marked) for path, value, marked in rows}
    assert shown["sac.lr"] == ("0.002", True)
    assert shown["sac.hidden_dim"] == ("32", False)  # the tiny preset's
    assert shown["feedback.selection"] == ("skill", False)  # S-EPOA's
    assert shown["teacher.eps"] == ("0.1", True)
    assert len(shown) == len(live.api("GET", f"/api/runs/{run_id}/config")["values"])

    page.fill("#teacher-form input[name=eps]", "0.3")
    page.click("#teacher-form button[type=submit]")
    page.wait_for_function("""() => [...document.querySelectorAll("#config-rows tr")]
        .some(row => row.cells[0].textContent === "teacher.eps"
                     && row.cells[1].textContent === "0.3")""")
    live.api("POST", f"/api/runs/{run_id}/stop")


def test_the_teacher_form_shows_the_eps_a_config_set_and_changes_it(
        live: LiveServer, page: Any) -> None:
    run_id = live.new_human_run(teacher="scripted", config={"teacher.eps": 0.3})
    page.goto(f"{live.url}/runs/{run_id}#token={OPERATOR_TOKEN}")
    page.wait_for_selector("#run-facts dd")
    eps = page.locator("#teacher-form input[name=eps]")
    assert eps.input_value() == "0.3"  # set by the config, not by teacher_params
    eps.fill("0.1")
    page.click("#teacher-form button[type=submit]")
    page.wait_for_function("""() => [...document.querySelectorAll("#config-rows tr")]
        .some(row => row.cells[0].textContent === "teacher.eps"
                     && row.cells[1].textContent === "0.1")""")
    page.wait_for_selector("#run-facts dd:text('scripted (ε=0.1)')")
    assert eps.input_value() == "0.1"
    live.stop_run(run_id)


def test_a_finished_runs_page_offers_no_teacher_switch(live: LiveServer, page: Any) -> None:
    run_id = live.new_human_run(teacher="scripted", teacher_params={"eps": 0.2})
    with live.sessions() as session:
        finish_run(session, run_id=run_id, worker_id=f"web-test-worker-{run_id}")
    page.goto(f"{live.url}/runs/{run_id}#token={OPERATOR_TOKEN}")
    page.wait_for_selector("#run-status:text('finished')")
    assert page.locator("#teacher-form").is_hidden()
    assert page.inner_text("#teacher-closed") == ("This run is finished: it keeps the teacher "
                                                  "it trained with, scripted (ε=0.2).")
