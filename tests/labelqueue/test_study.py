"""A study around an invite: its state follows its runs, only decisive answers on its own run
count towards the target, each participant has their own completion code (checkable, not
guessable, not shared), and the study completes when the target is met, the run is over (a
spent budget included) or check pairs pause the participant. Also: why a run waits, and the
workers as last seen."""

from __future__ import annotations

from datetime import timedelta

import pytest
from queue_helpers import query_spec, running_run
from sqlalchemy import Engine, select, update
from sqlalchemy.orm import Session

from crowdstudy.completion import completion_redirect, labeller_progress, verify_code
from crowdstudy.invites import (
    InviteClosed,
    create_invite,
    invite_runs_open,
    invite_state,
    join_invite,
    list_invites,
    read_invite,
)
from crowdstudy.participants import participants, verify_codes
from labelqueue import (
    Invalid,
    Invitee,
    LabellerPause,
    OtherRun,
    Query,
    Run,
    RunStatus,
    TeacherKind,
    Worker,
    claim_run,
    create_labeller,
    create_run,
    heartbeat,
    lease_next_query,
    make_engine,
    push_queries,
    read_run,
    set_labeller_active,
    set_run_status,
    submit_label,
    without_waiting,
)
from labelqueue.models import utcnow
from labelqueue.waiting import finish_if_waited
from runviews.activity import labeller_waiting, list_workers, runs_activity


def week() -> object:
    return utcnow() + timedelta(days=7)


def answer(session: Session, labeller_id: int, run_id: int, choice: str) -> None:
    query = lease_next_query(session, labeller_id=labeller_id, run_id=run_id)
    assert query is not None
    submit_label(session, query_id=query.id, labeller_id=labeller_id, choice=choice,
                 left_is_first=True)


def test_only_decisive_answers_on_the_invites_run_count_and_codes_are_each_participants_own(
    session: Session,
) -> None:
    run = running_run(session, teacher=TeacherKind.HUMAN)
    other = create_run(session, name="o", task="dmc:cheetah_run", algo="pebble", budget=100)
    assert claim_run(session, worker_id="worker-b") is not None
    push_queries(session, run_id=run.id, queries=[query_spec(i) for i in range(6)])
    push_queries(session, run_id=other.id, queries=[query_spec(i) for i in range(3)])
    invite = create_invite(session, expires_at=week(), run_id=run.id, target_answers=2,
                           completion_code="PILOT")
    ann = join_invite(session, code=invite.code, participant="ann").labeller
    bob = join_invite(session, code=invite.code, participant="bob").labeller

    # Skips and can't-tells count for nothing; another run's pairs are not hers to answer.
    answer(session, ann.id, run.id, "skip")
    answer(session, ann.id, run.id, "cant_tell")
    with pytest.raises(OtherRun, match=f"for run {run.id}"):
        answer(session, ann.id, other.id, "left")
    progress = labeller_progress(session, labeller_id=ann.id)
    assert (progress.labels, progress.counted, progress.complete) == (2, 0, False)
    assert progress.completion_code is None
    answer(session, ann.id, run.id, "left")
    answer(session, ann.id, run.id, "equal")
    done = labeller_progress(session, labeller_id=ann.id)
    assert (done.counted, done.complete, done.why) == (2, True, "target")
    assert done.completion_code is not None and done.completion_code.startswith("PILOT-")

    # Bob's code is another; before he finishes he has none, and nobody can derive it.
    assert labeller_progress(session, labeller_id=bob.id).completion_code is None
    answer(session, bob.id, run.id, "right")
    answer(session, bob.id, run.id, "left")
    bobs = labeller_progress(session, labeller_id=bob.id).completion_code
    assert bobs is not None and bobs != done.completion_code

    checked = verify_code(session, done.completion_code.lower().replace("-", " - "))
    assert checked is not None
    assert (checked.labeller_id, checked.participant, checked.counted, checked.why) == (
        ann.id, "ann", 2, "target")
    # The prefix may be left out; a code off by one character, or the study code with another
    # participant's part, is nobody's.
    assert verify_code(session, done.completion_code.removeprefix("PILOT-")) is not None
    # Typed in other groups, with spaces or none: one code all the same.
    flat = done.completion_code.replace("-", "")
    for typed in (done.completion_code.replace("-", " "), flat, f"{flat[:6]} {flat[6:]}"):
        found = verify_code(session, typed)
        assert found is not None and found.labeller_id == ann.id, typed
    assert verify_code(session, "ÉÉÉÉ-ÉÉÉÉ-ÉÉÉÉ") is None
    forged = done.completion_code[:-1] + ("0" if done.completion_code[-1] != "0" else "1")
    assert verify_code(session, forged) is None
    assert verify_code(session, "PILOT") is None
    assert verify_code(session, "OTHER-" + bobs.removeprefix("PILOT-")) is None


def test_the_study_closes_with_its_run_and_completes_for_those_who_joined(
    session: Session,
) -> None:
    run = running_run(session, teacher=TeacherKind.HUMAN)
    invite = create_invite(session, expires_at=week(), run_id=run.id, target_answers=50,
                           redirect_url="https://example.org/done?cc=ABC")
    joined = join_invite(session, code=invite.code, participant="P9").labeller
    assert invite_runs_open(session, [invite]) == {invite.id: True}
    assert labeller_progress(session, labeller_id=joined.id).complete is False

    set_run_status(session, run_id=run.id, status=RunStatus.STOPPING)
    [stored] = list_invites(session)
    assert invite_state(stored, runs_open=invite_runs_open(session, [stored])[stored.id]) \
        == "closed"
    with pytest.raises(InviteClosed) as refused:
        join_invite(session, code=invite.code, participant="late")
    assert refused.value.reason == "closed" and "ended" in str(refused.value)

    progress = labeller_progress(session, labeller_id=joined.id)
    assert (progress.complete, progress.why, progress.counted) == (True, "runs_over", 0)
    assert progress.completion_code is not None
    assert progress.redirect_url == "https://example.org/done?cc=ABC&participant=P9"

    # A requeued run opens its invite again.
    set_run_status(session, run_id=run.id, status=RunStatus.STOPPED)
    set_run_status(session, run_id=run.id, status=RunStatus.QUEUED)
    assert invite_runs_open(session, [stored]) == {invite.id: True}


def test_a_spent_budget_or_a_pause_completes_the_study_with_a_code_or_the_operators_message(
    session: Session,
) -> None:
    run = running_run(session, teacher=TeacherKind.HUMAN)
    coded = create_invite(session, expires_at=week(), run_id=run.id)
    told = create_invite(session, expires_at=week(), run_id=run.id,
                         pause_message="Please return the study on Prolific.")
    one = join_invite(session, code=coded.code).labeller
    two = join_invite(session, code=told.code).labeller
    three = join_invite(session, code=coded.code).labeller  # never paused
    for labeller in (one, two):
        session.add(LabellerPause(run_id=run.id, labeller_id=labeller.id, gold_answers=4,
                                  gold_correct=1))
    session.commit()
    paused = labeller_progress(session, labeller_id=one.id)
    assert (paused.why, paused.pause_message) == ("paused", None)
    assert paused.completion_code is not None
    message = labeller_progress(session, labeller_id=two.id)
    assert (message.why, message.completion_code) == ("paused", None)
    assert message.pause_message == "Please return the study on Prolific."

    with session.begin():
        session.execute(update(Run).where(Run.id == run.id).values(labels_used=100))
    assert labeller_progress(session, labeller_id=one.id).why == "paused"  # found first, kept
    assert labeller_progress(session, labeller_id=three.id).why == "runs_over"


def test_consent_is_required_when_the_invite_has_a_text(session: Session) -> None:
    run = running_run(session, teacher=TeacherKind.HUMAN)
    invite = create_invite(session, expires_at=week(), run_id=run.id,
                           consent_text="Your answers are kept for research.")
    with pytest.raises(ValueError, match="consent"):
        join_invite(session, code=invite.code)
    assert join_invite(session, code=invite.code, consent=True).labeller.id > 0
    # A consent text of white space is refused, not taken for none (which asks no consent).
    for field in ("consent_text", "pause_message", "note"):
        with pytest.raises(Invalid, match=f"{field} is blank"):
            create_invite(session, expires_at=week(), **{field: " \n\t "})
    with pytest.raises(ValueError, match="redirect_url"):
        create_invite(session, expires_at=week(), redirect_url="javascript:alert(1)")


def test_redirects_fill_in_the_code_and_the_participant() -> None:
    url = "https://x.test/end?pid={participant}&code={code}"
    assert completion_redirect(url, code="A-B", participant="w 1") == \
        "https://x.test/end?pid=w%201&code=A-B"
    assert completion_redirect("https://x.test/end", code="A", participant=None) == \
        "https://x.test/end"


def test_a_run_says_what_it_waits_for(session: Session) -> None:
    run = running_run(session, teacher=TeacherKind.HUMAN)
    queued = create_run(session, name="q", task="dmc:cheetah_run", algo="pebble", budget=10)
    [activity, waiting] = runs_activity(session, [run, queued])
    assert activity.phase == "starting"
    assert waiting.phase == "queued" and "all busy" in waiting.text

    push_queries(session, run_id=run.id, queries=[query_spec(i) for i in range(10)])
    invite = create_invite(session, expires_at=week(), run_id=run.id)
    one = join_invite(session, code=invite.code).labeller
    session.add(LabellerPause(run_id=run.id, labeller_id=one.id, gold_answers=4,
                              gold_correct=1))
    session.commit()
    fresh = session.get(Run, run.id)
    session.commit()
    assert fresh is not None
    [activity] = runs_activity(session, [fresh])
    assert activity.phase == "labelling"
    assert activity.text == "waiting for 10 answers from 0 active labellers (1 paused by " \
                            "check pairs)"

    heartbeat(session, run_id=run.id, worker_id="worker-a", step=0,
              progress={"pretraining_step": 1000, "pretraining_steps": 11_000,
                        "pretraining_fps": 100.0})
    other = create_run(session, name="p", task="dmc:walker_run", algo="sepoa", budget=10)
    set_run_status(session, run_id=queued.id, status=RunStatus.STOPPED)
    assert claim_run(session, worker_id="worker-c") is not None
    heartbeat(session, run_id=other.id, worker_id="worker-c", step=0,
              progress={"pretraining_step": 1000, "pretraining_steps": 11_000,
                        "pretraining_fps": 100.0})
    stored = session.get(Run, other.id)
    session.commit()
    assert stored is not None
    [pre] = runs_activity(session, [stored])
    assert pre.phase == "pretraining" and pre.eta_s == pytest.approx(100.0)
    assert "about 2 min left" in pre.text
    assert labeller_waiting(session, run_id=other.id).text.startswith(
        "The trainer is first pretraining its skills")


def test_workers_are_listed_with_their_host_and_dead_ones_as_dead(session: Session) -> None:
    running_run(session, teacher=TeacherKind.HUMAN, worker_id="worker-a")
    assert claim_run(session, worker_id="worker-idle") is None
    with session.begin():
        session.add(Worker(id="worker-gone", host="elsewhere", first_seen_at=utcnow(),
                           last_seen_at=utcnow() - timedelta(minutes=10)))
    states = {w.id: w for w in list_workers(session)}
    assert states["worker-a"].state == "training" and states["worker-a"].run_id is not None
    assert states["worker-a"].host
    assert states["worker-idle"].state == "idle"
    assert states["worker-gone"].state == "dead" and states["worker-gone"].silent_s > 500


def test_a_labeller_is_active_only_while_leasing_or_answering(session: Session) -> None:
    run = running_run(session, teacher=TeacherKind.HUMAN)
    push_queries(session, run_id=run.id, queries=[
        query_spec(i, needs_labels=2) for i in range(3)])
    ann, _ = create_labeller(session, name="ann")
    bob, _ = create_labeller(session, name="bob")
    for who in (ann, bob):
        query = lease_next_query(session, labeller_id=who.id, run_id=run.id)
        assert query is not None
        submit_label(session, query_id=query.id, labeller_id=who.id, choice="left",
                     left_is_first=True)
    lease_next_query(session, labeller_id=bob.id, run_id=run.id)
    [activity] = runs_activity(session, [read_run(session, run_id=run.id)])
    assert activity.labellers_active == 2
    # Three minutes on: ann answered nothing since; bob's page still renews the lease it took
    # then, but nobody answers there. Neither is active, and the run says so.
    later = utcnow() + timedelta(minutes=3)
    with session.begin():
        session.execute(update(Query).where(Query.lease_holder == bob.id)
                        .values(lease_expires_at=later + timedelta(minutes=1)))
    heartbeat(session, run_id=run.id, worker_id="worker-a", step=1)
    [activity] = runs_activity(session, [read_run(session, run_id=run.id)], now=later)
    assert activity.labellers_active == 0


def spend(session: Session, run_id: int, used: int) -> None:
    with session.begin():
        session.execute(update(Run).where(Run.id == run_id).values(labels_used=used))


def test_a_spent_budget_closes_the_study_to_newcomers_and_to_those_coming_back(
    session: Session,
) -> None:
    run = create_run(session, name="k", task="dmc:cheetah_run", algo="pebble", budget=10,
                     teacher=TeacherKind.HUMAN, config={"feedback.labels_per_query": 2})
    assert claim_run(session, worker_id="worker-a") is not None
    invite = create_invite(session, expires_at=week(), run_id=run.id, target_answers=5)
    everyone = create_invite(session, expires_at=week())
    ann = join_invite(session, code=invite.code, participant="ann").labeller
    spend(session, run.id, 8)  # two answers left: one more query
    assert invite_runs_open(session, [invite, everyone]) == {invite.id: True, everyone.id: True}

    spend(session, run.id, 9)  # one answer left, and a query takes two: spent
    assert invite_runs_open(session, [invite, everyone]) == {invite.id: False,
                                                             everyone.id: False}
    [stored, _] = list_invites(session)
    assert invite_state(stored, runs_open=False) == "closed"
    for code, who in ((invite.code, "late"), (invite.code, "ann"), (everyone.code, "zed")):
        with pytest.raises(InviteClosed) as refused:
            join_invite(session, code=code, participant=who)
        assert refused.value.reason == "closed" and "ended" in str(refused.value)
    assert labeller_progress(session, labeller_id=ann.id).why == "runs_over"

    # Another run taught by people, with budget left, opens the all-runs invite again.
    create_run(session, name="more", task="dmc:cheetah_run", algo="pebble", budget=10,
               teacher=TeacherKind.HUMAN)
    assert invite_runs_open(session, [invite, everyone]) == {invite.id: False,
                                                             everyone.id: True}


def test_an_all_runs_study_ends_when_every_budget_is_spent_and_pauses_on_every_open_run(
    session: Session,
) -> None:
    first = running_run(session, teacher=TeacherKind.HUMAN)
    second = create_run(session, name="b", task="dmc:cheetah_run", algo="pebble", budget=100,
                        teacher=TeacherKind.HUMAN)
    assert claim_run(session, worker_id="worker-b") is not None
    invite = create_invite(session, expires_at=week())
    pat = join_invite(session, code=invite.code, participant="pat").labeller

    # Paused on one run of two: the other still has pairs for them.
    session.add(LabellerPause(run_id=first.id, labeller_id=pat.id, gold_answers=4,
                              gold_correct=1))
    session.commit()
    [row] = participants(session, invite_id=invite.id)
    assert (row.paused, row.why) == (False, None)

    # The other run's budget spent: the only run left to them has paused them.
    spend(session, second.id, 100)
    [row] = participants(session, invite_id=invite.id)
    assert (row.paused, row.why, row.code_valid) == (True, "paused", True)

    # Both budgets spent: the study is over, with their code; it ended for them at the pause.
    spend(session, first.id, 100)
    progress = labeller_progress(session, labeller_id=pat.id)
    assert (progress.complete, progress.why) == (True, "paused")
    assert progress.completion_code == row.completion_code


def test_a_one_run_participant_is_served_their_run_only_and_never_waits_on_another(
    session: Session,
) -> None:
    mine = create_run(session, name="mine", task="dmc:cheetah_run", algo="pebble", budget=100,
                      teacher=TeacherKind.HUMAN, config={"feedback.practice_pairs": 1})
    assert claim_run(session, worker_id="worker-a") is not None
    other = create_run(session, name="other", task="dmc:cheetah_run", algo="pebble",
                       budget=100, teacher=TeacherKind.HUMAN,
                       config={"feedback.practice_pairs": 1})
    assert claim_run(session, worker_id="worker-b") is not None
    practice = query_spec(50, gold=True, first_segment_return=9.0, second_segment_return=1.0)
    push_queries(session, run_id=mine.id, queries=[practice, query_spec(0), query_spec(1)])
    [other_practice, _] = push_queries(session, run_id=other.id,
                                       queries=[practice, query_spec(0)])
    invite = create_invite(session, expires_at=week(), run_id=mine.id, wait_limit_s=1)
    ann = join_invite(session, code=invite.code, participant="ann").labeller

    with pytest.raises(OtherRun, match=f"joined this study for run {mine.id}"):
        lease_next_query(session, labeller_id=ann.id, run_id=other.id, for_people=True)
    with pytest.raises(OtherRun):  # nor the other run's practice pair, leased to nobody
        submit_label(session, query_id=other_practice, labeller_id=ann.id, choice="left",
                     left_is_first=True)
    # Asking for a stopped run is no wait for pairs; asking for no run is asking for hers.
    set_run_status(session, run_id=other.id, status=RunStatus.STOPPING)
    with pytest.raises(OtherRun):
        lease_next_query(session, labeller_id=ann.id, run_id=other.id, for_people=True)
    first = lease_next_query(session, labeller_id=ann.id, for_people=True)
    assert first is not None and first.run_id == mine.id
    [invitee] = session.scalars(select(Invitee)).all()
    session.commit()
    assert invitee.waiting_since is None
    assert read_run(session, run_id=other.id).labels_used == 0


def test_a_code_withheld_by_the_pause_message_is_not_earned(session: Session) -> None:
    run = running_run(session, teacher=TeacherKind.HUMAN)
    told = create_invite(session, expires_at=week(), run_id=run.id,
                         pause_message="Please return the study on Prolific.")
    coded = create_invite(session, expires_at=week(), run_id=run.id)
    returned = join_invite(session, code=told.code, participant="P1").labeller
    kept = join_invite(session, code=coded.code, participant="P2").labeller
    for who in (returned, kept):
        session.add(LabellerPause(run_id=run.id, labeller_id=who.id, gold_answers=4,
                                  gold_correct=1))
    session.commit()
    for invite, earned in ((told, False), (coded, True)):
        [row] = participants(session, invite_id=invite.id)
        assert (row.why, row.code_valid) == ("paused", earned)
        [check] = verify_codes(session, [row.completion_code])
        assert (check.valid, check.why) == (earned, "paused")
    assert labeller_progress(session, labeller_id=returned.id).earned is False


def test_a_pair_on_screen_is_no_wait_with_nothing_to_label(session: Session) -> None:
    run = create_run(session, name="p", task="dmc:cheetah_run", algo="pebble", budget=100,
                     teacher=TeacherKind.HUMAN, config={"feedback.practice_pairs": 1})
    assert claim_run(session, worker_id="worker-a") is not None
    push_queries(session, run_id=run.id, queries=[query_spec(0), query_spec(
        50, gold=True, first_segment_return=9.0, second_segment_return=1.0)])
    invite = create_invite(session, expires_at=week(), run_id=run.id, wait_limit_s=1,
                           entry_pass=1)
    later = utcnow() + timedelta(seconds=30)

    def finished_after_preloading(participant: str, answer_practice: bool) -> bool:
        who = join_invite(session, code=invite.code, participant=participant).labeller
        shown = lease_next_query(session, labeller_id=who.id, for_people=True)
        assert shown is not None and shown.practice
        if answer_practice:  # right: then the one real pair, leased and on screen
            submit_label(session, query_id=shown.id, labeller_id=who.id, choice="left",
                         left_is_first=True)
            shown = lease_next_query(session, labeller_id=who.id, for_people=True)
            assert shown is not None and not shown.practice
        # The page preloads behind the pair it shows, and finds nothing more.
        assert lease_next_query(session, labeller_id=who.id, ahead_of=shown.id,
                                for_people=True) is None
        with session.begin():
            session.execute(update(Invitee).where(Invitee.labeller_id == who.id)
                            .values(asked_at=later))
        return finish_if_waited(session, labeller_id=who.id, now=later)

    assert not finished_after_preloading("on-practice", answer_practice=False)
    assert not finished_after_preloading("on-a-pair", answer_practice=True)


def test_a_deactivated_participants_code_is_not_earned(session: Session) -> None:
    run = running_run(session, teacher=TeacherKind.HUMAN)
    push_queries(session, run_id=run.id, queries=[query_spec(i) for i in range(2)])
    invite = create_invite(session, expires_at=week(), run_id=run.id, target_answers=1)
    cheat = join_invite(session, code=invite.code, participant="cheat").labeller
    answer(session, cheat.id, run.id, "left")
    done = labeller_progress(session, labeller_id=cheat.id)
    assert done.earned and done.completion_code is not None
    set_labeller_active(session, labeller_id=cheat.id, active=False)  # the operator rejects

    [check] = verify_codes(session, [done.completion_code])
    assert (check.valid, check.why) == (False, "target")
    [row] = participants(session, invite_id=invite.id)
    assert (row.why, row.active, row.code_valid) == ("target", False, False)


def test_an_all_runs_study_made_before_its_runs_waits_for_them(session: Session) -> None:
    invite = create_invite(session, expires_at=week())
    early = join_invite(session, code=invite.code, participant="early").labeller
    progress = labeller_progress(session, labeller_id=early.id)
    assert (progress.complete, progress.why, progress.completion_code) == (False, None, None)


def test_reading_invites_takes_no_write_lock(
    engine: Engine, url: str, session: Session
) -> None:
    if engine.dialect.name != "sqlite":
        pytest.skip("SQLite's write lock")
    invite = create_invite(session, expires_at=week())
    other = make_engine(url)  # as another process writing: SQLite's lock only
    try:
        with other.connect() as holder, holder.begin(), without_waiting():
            # Opening a link (GET /join/<code>) and listing the invites wait for no writer.
            found = read_invite(session, code=invite.code)
            assert found is not None and found.id == invite.id
            assert [i.id for i in list_invites(session)] == [invite.id]
    finally:
        other.dispose()
