"""Gold pairs: every labeller may answer each once, they never end and never cost budget, a
labeller gets them at the run's rate, and one who answers them badly is paused on the run."""

from __future__ import annotations

from typing import Any

import pytest
from queue_helpers import query_spec
from sqlalchemy.orm import Session

from labelqueue import (
    GOLD_NEEDS_LABELS,
    Paused,
    Query,
    QueryStatus,
    Run,
    TeacherKind,
    claim_run,
    create_labeller,
    create_run,
    gold_answer,
    labels_for_queries,
    lease_next_query,
    lift_pause,
    paused_labellers,
    push_queries,
    read_run,
    submit_label,
    withdraw_label,
)
from labelqueue.gold import SCHEDULE_KEY
from labelqueue.models import ServerKey, utcnow
from runvocab.answers import Answer, click_of_answer

# query_spec's returns: first 1.5, second 2.5, so a gold pair's answer is the second segment.
RIGHT, WRONG = Answer.SECOND, Answer.FIRST


def gold_run(session: Session, *, worker_id: str = "worker-a", **config: Any) -> Run:
    """A running human-taught run with these `feedback.*` settings."""
    run = create_run(
        session, name="r", task="dmc:cheetah_run", algo="pebble", budget=1000,
        teacher=TeacherKind.HUMAN, config={f"feedback.{k}": v for k, v in config.items()},
    )
    claimed = claim_run(session, worker_id=worker_id)
    assert claimed is not None and claimed.id == run.id
    return claimed


def push(session: Session, run: Run, *, plain: int, gold: int,
         **plain_fields: Any) -> tuple[list[int], list[int]]:
    """`plain` ordinary queries and `gold` gold pairs spread evenly among them, as a worker puts
    them (at places of their own in the round); their ids, in order."""
    places = {(i + 1) * (plain + gold) // (gold + 1) for i in range(gold)}
    specs = [query_spec(i, gold=True) if i in places else query_spec(i, **plain_fields)
             for i in range(plain + gold)]
    ids = push_queries(session, run_id=run.id, queries=specs)
    return ([i for i, spec in zip(ids, specs, strict=True) if not spec.get("gold")],
            [i for i, spec in zip(ids, specs, strict=True) if spec.get("gold")])


def answer_next(
    session: Session, labeller_id: int, run_id: int | None, gold_ids: list[int],
    gold_answer: Answer = RIGHT, **lease: Any,
) -> Query | None:
    """Lease the next query and answer it (a gold pair with `gold_answer`, others "first")."""
    query = lease_next_query(session, labeller_id=labeller_id, run_id=run_id, **lease)
    if query is None:
        return None
    answer = gold_answer if query.id in gold_ids else Answer.FIRST
    _, created = submit_label(
        session, query_id=query.id, labeller_id=labeller_id,
        choice=click_of_answer(answer, left_is_first=True), left_is_first=True,
    )
    assert created
    return query


def fresh(session: Session, query_id: int) -> Query:
    query = session.get(Query, query_id, populate_existing=True)
    assert query is not None
    session.commit()
    return query


def test_the_gold_answer_is_the_segment_with_the_larger_true_return() -> None:
    assert gold_answer(1.5, 2.5) is Answer.SECOND
    assert gold_answer(-1.0, -3.0) is Answer.FIRST


def test_a_gold_pair_is_answered_by_everyone_once_and_costs_no_budget(session: Session) -> None:
    run = gold_run(session, gold_rate=0.5)
    # Every ordinary query asks everyone, so each person walks the same stream.
    plain, [gold] = push(session, run, plain=3, gold=1, needs_labels=6)
    assert fresh(session, gold).needs_labels == GOLD_NEEDS_LABELS and fresh(session, gold).gold
    people = [create_labeller(session, name=f"p{i}")[0] for i in range(6)]
    plain_answers = 0
    for person in people:
        served = []
        while (query := answer_next(session, person.id, run.id, [gold])) is not None:
            served.append(query.id)
            if query.id == gold:
                break
        # In its place among the ordinary queries (the third), due after one answer at half.
        assert served == [plain[0], plain[1], gold], person.name
        plain_answers += len(served) - 1
        # Never twice to one labeller: the next lease is an ordinary query or nothing.
        again = lease_next_query(session, labeller_id=person.id, run_id=run.id)
        assert again is None or again.id != gold
    query = fresh(session, gold)
    assert query.status is QueryStatus.PENDING and query.label_count == len(people)
    assert len(labels_for_queries(session, query_ids=[gold])) == len(people)
    assert read_run(session, run_id=run.id).labels_used == plain_answers


def test_gold_pairs_are_never_served_to_the_scripted_teacher_nor_at_rate_zero(
    session: Session,
) -> None:
    run = gold_run(session, gold_rate=0.5)
    plain, gold = push(session, run, plain=3, gold=3)
    teacher, _ = create_labeller(session, name="teacher")
    served = []
    while (query := answer_next(session, teacher.id, run.id, gold, gold=False)) is not None:
        served.append(query.id)
    assert served == plain  # then nothing, though gold pairs are open

    other = gold_run(session, worker_id="worker-b")  # gold_rate left at its default, 0
    plain, gold = push(session, other, plain=3, gold=3)
    ann, _ = create_labeller(session, name="ann")
    served = []
    while (query := answer_next(session, ann.id, other.id, gold)) is not None:
        served.append(query.id)
    assert served == plain


def test_ordinary_queries_are_served_when_no_gold_pair_is_open(session: Session) -> None:
    run = gold_run(session, gold_rate=0.5)
    plain, _ = push(session, run, plain=5, gold=0)
    ann, _ = create_labeller(session, name="ann")
    served = [q.id for q in iter(lambda: answer_next(session, ann.id, run.id, []), None)]
    assert served == plain
    assert read_run(session, run_id=run.id).labels_used == 5


@pytest.mark.parametrize("run_id_given", [True, False])
def test_a_labeller_gets_gold_pairs_at_the_runs_rate(session: Session, run_id_given: bool) -> None:
    run = gold_run(session, gold_rate=0.2)
    # Enough of both for two people, gold pairs at least as dense in the stream as the rate.
    plain, gold = push(session, run, plain=100, gold=40)
    counts = []
    for name in ("ann", "bob"):
        person, _ = create_labeller(session, name=name)
        got = 0
        for n in range(1, 51):
            query = answer_next(session, person.id, run.id if run_id_given else None, gold)
            assert query is not None
            got += query.id in gold
            # Spread over the stream, never bunched: within one and a half of the rate's share.
            assert abs(got - 0.2 * n) <= 1.5, (name, n, got)
        counts.append(got)
        answered = {label.query_id for label in labels_for_queries(session, query_ids=gold)
                    if label.labeller_id == person.id}
        assert len(answered) == got  # each a different gold pair
    assert all(9 <= got <= 11 for got in counts), counts


def test_the_gold_schedule_cannot_be_worked_out_from_a_labellers_own_ids(
    session: Session, tmp_path: Any
) -> None:
    """The offsets that decide when a labeller's next check is due come from a key the server
    keeps in its database: the public formula (a hash of labeller, run and answer count) does
    not give them, and another database's key gives others."""
    import hashlib

    from labelqueue import make_engine, migrate, server_key, session_factory
    from labelqueue.gold import SCHEDULE_KEY, _offset

    def public(labeller: int, answers: int) -> float:
        digest = hashlib.sha256(f"gold:{labeller}:1:{answers}".encode()).digest()
        return int.from_bytes(digest[:8], "big") / 2.0**64

    key = server_key(session, SCHEDULE_KEY)
    assert server_key(session, SCHEDULE_KEY) == key and len(key) == 32  # one, kept
    other_url = f"sqlite:///{tmp_path / 'other.db'}"
    migrate(other_url)
    engine = make_engine(other_url)
    with session_factory(engine)() as other:
        other_key = server_key(other, SCHEDULE_KEY)
    engine.dispose()
    offsets = [_offset(key, 7, 1, n) for n in range(200)]
    assert all(0 <= x < 1 for x in offsets) and 0.4 < sum(offsets) / 200 < 0.6
    # Predicting "due" (offset below the rate's remainder) by the public formula is a coin flip.
    rate = 0.5
    agree = sum((o < rate) == (public(7, n) < rate) for n, o in enumerate(offsets))
    assert 70 <= agree <= 130, agree
    assert offsets != [_offset(other_key, 7, 1, n) for n in range(200)]


def pause_settings(**overrides: Any) -> dict[str, Any]:
    return {"gold_rate": 0.5, "gold_min_accuracy": 0.5, "gold_min_answers": 4} | overrides


def answer_gold(session: Session, labeller_id: int, run: Run, gold: list[int],
                answers: list[Answer]) -> None:
    """Answer ordinary queries and gold pairs until the gold pairs got `answers`, in order."""
    todo = list(answers)
    while todo:
        query = lease_next_query(session, labeller_id=labeller_id, run_id=run.id)
        assert query is not None
        answer = todo.pop(0) if query.id in gold else Answer.FIRST
        submit_label(session, query_id=query.id, labeller_id=labeller_id,
                     choice=click_of_answer(answer, left_is_first=True), left_is_first=True)


def test_a_labeller_below_the_gold_accuracy_is_paused_until_an_operator_lifts_it(
    session: Session,
) -> None:
    run = gold_run(session, **pause_settings())
    plain, gold = push(session, run, plain=40, gold=10)
    ann, _ = create_labeller(session, name="ann")
    bob, _ = create_labeller(session, name="bob")

    # Three wrong of three: fewer than gold_min_answers, so not yet.
    answer_gold(session, ann.id, run, gold, [WRONG, WRONG, WRONG])
    assert paused_labellers(session, run_id=run.id) == []
    answer_gold(session, ann.id, run, gold, [RIGHT])  # 1 of 4 right, below half
    [pause] = paused_labellers(session, run_id=run.id)
    assert (pause.labeller_id, pause.gold_answers, pause.gold_correct) == (ann.id, 4, 1)

    stored = len(labels_for_queries(session, query_ids=plain + gold))
    with pytest.raises(Paused, match="1 of your 4"):
        lease_next_query(session, labeller_id=ann.id, run_id=run.id)
    with pytest.raises(Paused, match="50%"):
        lease_next_query(session, labeller_id=ann.id)  # any human-taught run: only this one
    # Others go on; the paused labeller's answers stay.
    assert lease_next_query(session, labeller_id=bob.id, run_id=run.id) is not None
    assert len(labels_for_queries(session, query_ids=plain + gold)) == stored

    assert lift_pause(session, run_id=run.id, labeller_id=ann.id)
    assert not lift_pause(session, run_id=run.id, labeller_id=ann.id)  # nothing left to lift
    assert paused_labellers(session, run_id=run.id) == []
    assert lease_next_query(session, labeller_id=ann.id, run_id=run.id) is not None


def test_the_pause_threshold_is_strictly_below_and_skips_do_not_count(session: Session) -> None:
    run = gold_run(session, **pause_settings())
    plain, gold = push(session, run, plain=40, gold=10)
    ann, _ = create_labeller(session, name="ann")
    # Two skips are no gold answers; then 2 of 4 right is exactly half: not below it.
    answer_gold(session, ann.id, run, gold,
                [Answer.SKIP, WRONG, Answer.SKIP, RIGHT, WRONG, RIGHT])
    assert paused_labellers(session, run_id=run.id) == []
    answer_gold(session, ann.id, run, gold, [WRONG])  # 2 of 5
    [pause] = paused_labellers(session, run_id=run.id)
    assert (pause.gold_answers, pause.gold_correct) == (5, 2)


def test_a_lifted_pause_comes_back_with_the_next_bad_gold_answer(session: Session) -> None:
    run = gold_run(session, **pause_settings())
    plain, gold = push(session, run, plain=40, gold=10)
    ann, _ = create_labeller(session, name="ann")
    answer_gold(session, ann.id, run, gold, [WRONG] * 4)
    assert lift_pause(session, run_id=run.id, labeller_id=ann.id)
    answer_gold(session, ann.id, run, gold, [WRONG])  # the record is kept: 0 of 5
    [pause] = paused_labellers(session, run_id=run.id)
    assert (pause.gold_answers, pause.gold_correct) == (5, 0)


def test_no_pause_without_a_minimum_accuracy(session: Session) -> None:
    run = gold_run(session, **pause_settings(gold_min_accuracy=0.0))
    plain, gold = push(session, run, plain=40, gold=10)
    ann, _ = create_labeller(session, name="ann")
    answer_gold(session, ann.id, run, gold, [WRONG] * 6)
    assert paused_labellers(session, run_id=run.id) == []
    assert lease_next_query(session, labeller_id=ann.id, run_id=run.id) is not None


def test_a_pause_on_one_run_leaves_the_labeller_the_other_runs(session: Session) -> None:
    run = gold_run(session, **pause_settings())
    plain, gold = push(session, run, plain=20, gold=5)
    other = gold_run(session, worker_id="worker-b")
    [other_query] = push_queries(session, run_id=other.id, queries=[query_spec(0)])
    ann, _ = create_labeller(session, name="ann")
    answer_gold(session, ann.id, run, gold, [WRONG] * 4)
    # The oldest open query overall is the first run's, but ann is paused there.
    leased = lease_next_query(session, labeller_id=ann.id)
    assert leased is not None and leased.id == other_query


def test_taking_back_a_gold_answer_leaves_the_budget_as_it_was(session: Session) -> None:
    run = gold_run(session, gold_rate=0.5)
    plain, [gold] = push(session, run, plain=5, gold=1)
    ann, _ = create_labeller(session, name="ann")
    served = []
    while not served or served[-1] != gold:
        query = answer_next(session, ann.id, run.id, [gold])
        assert query is not None
        served.append(query.id)
    used = len(served) - 1  # the ordinary answers only
    assert read_run(session, run_id=run.id).labels_used == used
    withdraw_label(session, query_id=gold, labeller_id=ann.id)
    # The gold answer never cost budget, so taking it back gives none back.
    assert read_run(session, run_id=run.id).labels_used == used


def test_newcomers_first_checks_are_drawn_at_random_among_the_runs_gold(
        session: Session) -> None:
    # A fixed schedule key, so that the draws (random to labellers) are the same each time.
    session.add(ServerKey(name=SCHEDULE_KEY, value="5e" * 32, created_at=utcnow()))
    session.commit()
    run = gold_run(session, gold_rate=0.3)
    # An early round, its ordinary pairs all answered; its gold pairs stay open to newcomers.
    plain, golds = push(session, run, plain=10, gold=8)
    veteran, _ = create_labeller(session, name="veteran")
    while any(q.status != "labelled" for q in (
            session.get(Query, i, populate_existing=True) for i in plain)):
        assert answer_next(session, veteran.id, run.id, golds) is not None
    session.commit()
    later = [query_spec(i, round=1, gold=i % 10 == 5) for i in range(200)]
    ids = push_queries(session, run_id=run.id, queries=later)
    golds += [i for i, spec in zip(ids, later, strict=True) if spec["gold"]]
    newcomers = [create_labeller(session, name=f"new{i}")[0].id for i in range(16)]
    first_check: dict[int, int] = {}
    for _ in range(30):  # a crowd: each newcomer answers in turn, until their first check
        for who in newcomers:
            if who not in first_check:
                query = answer_next(session, who, run.id, golds)
                assert query is not None
                if query.gold:
                    first_check[who] = query.id
    firsts = list(first_check.values())
    # Not the run's oldest for all: newcomers' first checks are spread over its gold pairs.
    assert len(firsts) == 16 and len(set(firsts)) >= 5
    assert max(firsts.count(f) for f in set(firsts)) <= len(firsts) // 2


def last_gold_answered(session: Session, gold: list[int]) -> int:
    return labels_for_queries(session, query_ids=gold)[-1].query_id


def test_taking_back_the_gold_answer_that_paused_a_labeller_lifts_the_pause(
    session: Session,
) -> None:
    run = gold_run(session, **pause_settings())
    plain, gold = push(session, run, plain=40, gold=10)
    ann, _ = create_labeller(session, name="ann")
    answer_gold(session, ann.id, run, gold, [RIGHT, RIGHT, WRONG, WRONG])  # 2 of 4: not below
    answer_gold(session, ann.id, run, gold, [WRONG])  # a slip: 2 of 5
    assert len(paused_labellers(session, run_id=run.id)) == 1
    slip = last_gold_answered(session, gold)

    withdraw_label(session, query_id=slip, labeller_id=ann.id)
    assert paused_labellers(session, run_id=run.id) == []  # 2 of 4 again
    submit_label(session, query_id=slip, labeller_id=ann.id,
                 choice=click_of_answer(RIGHT, left_is_first=True), left_is_first=True)
    assert paused_labellers(session, run_id=run.id) == []  # 3 of 5
    assert lease_next_query(session, labeller_id=ann.id, run_id=run.id) is not None


def test_taking_back_a_gold_answer_keeps_a_pause_the_rest_of_the_record_earns(
    session: Session,
) -> None:
    run = gold_run(session, **pause_settings())
    plain, gold = push(session, run, plain=40, gold=10)
    ann, _ = create_labeller(session, name="ann")
    answer_gold(session, ann.id, run, gold, [WRONG] * 4)
    assert lift_pause(session, run_id=run.id, labeller_id=ann.id)
    answer_gold(session, ann.id, run, gold, [WRONG])  # paused again: 0 of 5
    withdraw_label(session, query_id=last_gold_answered(session, gold), labeller_id=ann.id)
    [pause] = paused_labellers(session, run_id=run.id)  # 0 of 4 is below all the same
    assert (pause.gold_answers, pause.gold_correct) == (4, 0)


def test_the_lease_after_an_undo_whose_pause_stands_says_paused(session: Session) -> None:
    """The undo leases the gold pair back to the labeller; while the pause stands, the next
    lease says Paused instead of serving it, and the pair goes back to the others."""
    run = gold_run(session, **pause_settings())
    plain, gold = push(session, run, plain=40, gold=10)
    ann, _ = create_labeller(session, name="ann")
    answer_gold(session, ann.id, run, gold, [WRONG] * 4)  # paused: 0 of 4
    assert lift_pause(session, run_id=run.id, labeller_id=ann.id)
    answer_gold(session, ann.id, run, gold, [WRONG])  # paused again: 0 of 5
    slip = last_gold_answered(session, gold)
    withdrawn = withdraw_label(session, query_id=slip, labeller_id=ann.id)
    assert withdrawn.query.lease_holder == ann.id
    assert len(paused_labellers(session, run_id=run.id)) == 1  # 0 of 4 stands
    with pytest.raises(Paused, match="0 of your 4"):
        lease_next_query(session, labeller_id=ann.id, run_id=run.id)
    with pytest.raises(Paused):
        lease_next_query(session, labeller_id=ann.id)  # any human-taught run: only this one
    assert fresh(session, slip).lease_holder is None
