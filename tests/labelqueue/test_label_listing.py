"""The label browser's queries, on each database: correctness against the true returns (equal
when they are exactly equal; can't-tell and skip are neither), flag, gold, labeller and run
filters, answers taken back only when asked, paging by id, one label with its truth."""

from __future__ import annotations

import pytest
from queue_helpers import query_spec, running_run
from sqlalchemy import update
from sqlalchemy.orm import Session

from labelqueue import (
    NotFound,
    TeacherKind,
    create_labeller,
    lease_next_query,
    push_queries,
    submit_label,
    withdraw_label,
)
from labelqueue.models import Query
from runviews.label_browser import browse_labels, label_detail


def test_filters_paging_and_detail(session: Session) -> None:
    run = running_run(session, teacher=TeacherKind.HUMAN)
    # Returns: first 1.5 < second 2.5 (so "second" is right), except the third: equal.
    specs = [query_spec(i) for i in range(5)]
    specs[2] |= {"first_segment_return": 2.0, "second_segment_return": 2.0,
                 "shadow_choice": "equal"}
    ids = push_queries(session, run_id=run.id, queries=specs)
    ann, _ = create_labeller(session, name="ann")
    ben, _ = create_labeller(session, name="ben")

    def answer(who: int, click: str, **flag: str) -> int:
        query = lease_next_query(session, labeller_id=who, run_id=run.id)
        assert query is not None
        label, _ = submit_label(session, query_id=query.id, labeller_id=who, choice=click,
                                left_is_first=True, **flag)
        return label.id

    right = answer(ann.id, "right")  # second: correct
    wrong = answer(ann.id, "left")  # first: incorrect
    equal = answer(ann.id, "equal")  # the equal pair: correct
    flagged = answer(ben.id, "skip", flag="clip_broken")
    taken_back = answer(ben.id, "cant_tell")
    withdraw_label(session, query_id=ids[4], labeller_id=ben.id)
    session.execute(update(Query).where(Query.id == ids[0]).values(gold=True))
    session.commit()

    def listed(**filters: object) -> list[int]:
        return [label.label_id for label in browse_labels(session, **filters).labels]

    assert listed(run_id=run.id) == [flagged, equal, wrong, right]  # newest first
    assert listed(run_id=run.id, correct=True) == [equal, right]
    assert listed(run_id=run.id, correct=False) == [wrong]
    assert listed(flagged=True) == [flagged] and flagged not in listed(flagged=False)
    assert listed(gold=True) == [right]
    assert listed(labeller_id=ben.id) == [flagged]
    assert listed(labeller_id=ben.id, withdrawn=True) == [taken_back, flagged]

    first = browse_labels(session, run_id=run.id, limit=3)
    assert [x.label_id for x in first.labels] == [flagged, equal, wrong]
    assert first.matching == 4 and first.next_before == wrong
    rest = browse_labels(session, run_id=run.id, limit=3, before=first.next_before)
    assert [x.label_id for x in rest.labels] == [right] and rest.next_before is None

    detail = label_detail(session, label_id=equal)
    assert (detail.first_segment_return, detail.second_segment_return) == (2.0, 2.0)
    assert detail.true_answer == "equal" and detail.label.correct is True
    assert detail.label.shadow_choice == "equal" and detail.label.labeller_name == "ann"
    assert label_detail(session, label_id=flagged).label.correct is None

    with pytest.raises(NotFound, match="run 999"):
        browse_labels(session, run_id=999)
    with pytest.raises(NotFound, match="label 999"):
        label_detail(session, label_id=999)
    with pytest.raises(ValueError, match="limit"):
        browse_labels(session, limit=0)
