"""Flagged pairs, on each database: a flag comes with a skip and a note, is refused on any other
answer, is never trained on as a preference, and is counted per run; a flag taken back (undo)
no longer counts."""

from __future__ import annotations

import pytest
from queue_helpers import query_spec, running_run
from sqlalchemy.orm import Session

from labelqueue import (
    TeacherKind,
    consume_labels,
    create_labeller,
    lease_next_query,
    push_queries,
    submit_label,
    withdraw_label,
)
from runviews.flags import flag_summary
from runvocab.answers import DECISIVE, FLAG_NOTE_MAX, Flag


def test_a_flag_is_stored_with_its_skip_and_counted(session: Session) -> None:
    run = running_run(session, teacher=TeacherKind.HUMAN)
    ids = push_queries(session, run_id=run.id, queries=[query_spec(i) for i in range(3)])
    alice, _ = create_labeller(session, name="alice")
    bob, _ = create_labeller(session, name="bob")

    q = lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    assert q is not None
    label, created = submit_label(session, query_id=q.id, labeller_id=alice.id, choice="skip",
                                  left_is_first=True, flag="not_visible",
                                  flag_note="  the cheetah is off the left edge  ")
    assert created and label.flag is Flag.NOT_VISIBLE
    assert label.flag_note == "the cheetah is off the left edge"  # stripped
    q2 = lease_next_query(session, labeller_id=bob.id, run_id=run.id)
    assert q2 is not None
    submit_label(session, query_id=q2.id, labeller_id=bob.id, choice="skip", left_is_first=False,
                 flag=Flag.CLIP_BROKEN, flag_note="   ")  # a blank note is no note
    q3 = lease_next_query(session, labeller_id=bob.id, run_id=run.id)
    assert q3 is not None
    submit_label(session, query_id=q3.id, labeller_id=bob.id, choice="left", left_is_first=True)

    summary = flag_summary(session, run_id=run.id)
    assert summary.total == 2 and summary.queries == 2
    assert summary.by_flag == {"clip_broken": 1, "not_visible": 1, "other": 0}
    newest, older = summary.latest
    assert (newest.labeller_name, newest.flag, newest.note) == ("bob", "clip_broken", None)
    assert (older.query_id, older.note) == (q.id, "the cheetah is off the left edge")
    assert set(ids) == {q.id, q2.id, q3.id}

    # The trainer gets the flagged answers as skips: nothing it trains on.
    taken = {lab.query_id: lab for lab in consume_labels(session, run_id=run.id)}
    assert taken[q.id].answer not in DECISIVE and taken[q2.id].answer not in DECISIVE
    assert taken[q3.id].answer in DECISIVE and taken[q3.id].flag is None


def test_a_flag_on_an_answer_or_a_bad_note_is_refused(session: Session) -> None:
    run = running_run(session, teacher=TeacherKind.HUMAN)
    push_queries(session, run_id=run.id, queries=[query_spec(0)])
    alice, _ = create_labeller(session, name="alice")
    q = lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    assert q is not None
    for kwargs, words in (
        ({"choice": "left", "flag": "other"}, "flagged pair is skipped"),
        ({"choice": "cant_tell", "flag": "other"}, "flagged pair is skipped"),
        ({"choice": "skip", "flag": "ugly"}, "unknown flag 'ugly'"),
        ({"choice": "skip", "flag_note": "no flag"}, "needs a flag"),
        ({"choice": "skip", "flag": "other", "flag_note": "x" * (FLAG_NOTE_MAX + 1)},
         "at most 500"),
    ):
        with pytest.raises(ValueError, match=words):
            submit_label(session, query_id=q.id, labeller_id=alice.id, left_is_first=True,
                         **kwargs)
    # Nothing was stored by the refusals: the lease still stands and a proper flag is taken.
    label, created = submit_label(session, query_id=q.id, labeller_id=alice.id, choice="skip",
                                  left_is_first=True, flag="other", flag_note="two cheetahs?")
    assert created and label.flag is Flag.OTHER


def test_a_flag_taken_back_no_longer_counts(session: Session) -> None:
    run = running_run(session, teacher=TeacherKind.HUMAN)
    push_queries(session, run_id=run.id, queries=[query_spec(0)])
    alice, _ = create_labeller(session, name="alice")
    q = lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    assert q is not None
    submit_label(session, query_id=q.id, labeller_id=alice.id, choice="skip", left_is_first=True,
                 flag="clip_broken")
    assert flag_summary(session, run_id=run.id).total == 1
    withdraw_label(session, query_id=q.id, labeller_id=alice.id)
    assert flag_summary(session, run_id=run.id).total == 0
