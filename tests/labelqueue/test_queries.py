"""Queries are pushed by the worker and leased to one labeller at a time."""

from __future__ import annotations

from datetime import timedelta

import numpy as np
import pytest
from queue_helpers import query_spec, running_run
from sqlalchemy import Engine, func, select, update
from sqlalchemy.orm import Session

from labelqueue import (
    Conflict,
    Label,
    LeaseError,
    Query,
    QueryStatus,
    Run,
    TeacherKind,
    cancel_queries,
    create_labeller,
    lease_next_query,
    push_queries,
    set_clips,
    set_run_status,
    submit_label,
)
from labelqueue import queries as queries_module
from labelqueue.models import utcnow
from runvocab.answers import Answer
from runvocab.query_fields import QUERY_FIELDS


def expire_lease(session: Session, query_id: int) -> None:
    session.execute(
        update(Query)
        .where(Query.id == query_id)
        .values(lease_expires_at=utcnow() - timedelta(seconds=1))
    )
    session.commit()


def counts(session: Session) -> tuple[int, int, int]:
    """(labels, labels_used summed over runs, label_count summed over queries)."""
    result = (
        session.scalar(select(func.count()).select_from(Label)) or 0,
        session.scalar(select(func.sum(Run.labels_used))) or 0,
        session.scalar(select(func.sum(Query.label_count))) or 0,
    )
    session.commit()
    return result


def test_push_stores_provenance_and_hidden_truth(session: Session) -> None:
    run = running_run(session)
    spec = query_spec(0, first_skill=np.array([0.5, -1.0]), model_p=float("nan"), score=None,
                      shadow_choice="second", distinguishable=np.bool_(True))
    spec["first_trajectory"] = np.int64(7)  # the trainer's NumPy scalars are welcome
    spec["first_segment_return"] = np.float32(1.5)
    ids = push_queries(session, run_id=run.id, queries=[spec, query_spec(1)])
    assert len(ids) == 2 and ids[0] < ids[1]

    query = session.get(Query, ids[0])
    assert query is not None
    assert (query.run_id, query.round, query.position) == (run.id, 0, 0)
    assert (query.first_trajectory, query.first_start, query.segment_length) == (7, 10, 50)
    assert query.first_skill == [0.5, -1.0] and query.second_skill is None
    assert query.first_segment_return == 1.5 and query.second_trajectory_return == 120.0
    assert query.model_p is None and query.score is None  # NaN is stored as null
    assert query.first_clip == "r0/q0-a.mp4"
    assert query.status is QueryStatus.PENDING and query.needs_labels == 1
    assert query.shadow_choice == "second" and query.distinguishable is True
    with pytest.raises(ValueError, match="maybe"):
        push_queries(session, run_id=run.id, queries=[query_spec(2, shadow_choice="maybe")])


def test_pushing_a_round_again_returns_the_stored_ids(session: Session) -> None:
    run = running_run(session)
    specs = [query_spec(i) for i in range(3)]
    ids = push_queries(session, run_id=run.id, queries=specs)
    # A worker resumed from an older checkpoint re-selects and re-pushes the same round.
    assert push_queries(session, run_id=run.id, queries=specs) == ids
    assert session.scalar(select(func.count()).select_from(Query)) == 3
    session.commit()

    different = query_spec(1, first_start=11)
    with pytest.raises(Conflict, match="different pair"):
        push_queries(session, run_id=run.id, queries=[query_spec(3), different])
    assert session.scalar(select(func.count()).select_from(Query)) == 3  # query 3 not stored


def test_bad_query_fields_and_clip_keys_are_refused(session: Session) -> None:
    run = running_run(session)
    with pytest.raises(ValueError, match="missing"):
        push_queries(session, run_id=run.id, queries=[{"round": 0}])
    with pytest.raises(ValueError, match="unknown"):
        push_queries(session, run_id=run.id, queries=[query_spec(0, colour="red")])
    for key in ["/etc/passwd", "../x.mp4", "a/../../x.mp4", "C:\\x.mp4", "", "."]:
        with pytest.raises(ValueError, match="clip key"):
            push_queries(session, run_id=run.id, queries=[query_spec(0, first_clip=key)])
    [query_id] = push_queries(session, run_id=run.id, queries=[query_spec(0, first_clip=None)])
    with pytest.raises(ValueError, match="clip key"):
        set_clips(session, query_id=query_id, first_clip="/abs.mp4", second_clip="b.mp4")
    query = set_clips(session, query_id=query_id, first_clip="r0/a.mp4", second_clip="r0/b.mp4")
    assert (query.first_clip, query.second_clip) == ("r0/a.mp4", "r0/b.mp4")


def test_a_push_stores_each_declared_field_and_the_defaults_of_those_left_out(
    session: Session,
) -> None:
    run = running_run(session)
    required = {field.name for field in QUERY_FIELDS if not field.optional}
    spec = {name: value for name, value in query_spec(0).items() if name in required}
    # NumPy scalars, as the trainer's may be, are stored as plain numbers.
    spec |= {"first_trajectory": np.int64(4), "first_segment_return": np.float32(0.5)}
    full = query_spec(1, first_skill=[np.float32(0.25)], shadow_choice="first",
                      distinguishable=np.bool_(True), score=float("nan"), needs_labels=2)
    bare_id, full_id = push_queries(session, run_id=run.id, queries=[spec, full])
    bare, stored = session.get(Query, bare_id), session.get(Query, full_id)
    assert bare is not None and stored is not None
    for field in QUERY_FIELDS:
        value = getattr(bare, field.name)
        if field.name in spec:
            assert value == spec[field.name], field.name
        else:
            assert field.optional and value == field.default, field.name
    assert (stored.first_skill, stored.shadow_choice, stored.distinguishable) == (
        [0.25], Answer.FIRST, True)
    assert (stored.score, stored.needs_labels, stored.gold) == (None, 2, False)
    for name in sorted(required):
        with pytest.raises(ValueError, match=f"query field {name} may not be null"):
            push_queries(session, run_id=run.id, queries=[query_spec(2) | {name: None}])
    with pytest.raises(ValueError, match="may not be null"):
        push_queries(session, run_id=run.id, queries=[query_spec(2, gold=None)])


def test_lease_takes_the_oldest_and_a_reload_returns_the_same_query(session: Session) -> None:
    run = running_run(session)
    ids = push_queries(session, run_id=run.id, queries=[query_spec(i) for i in range(3)])
    alice, _ = create_labeller(session, name="alice")
    bob, _ = create_labeller(session, name="bob")

    first = lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    assert first is not None and first.id == ids[0]
    assert first.status is QueryStatus.LEASED and first.lease_holder == alice.id
    again = lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    assert again is not None and again.id == ids[0]
    assert again.lease_expires_at >= first.lease_expires_at  # type: ignore[operator]

    second = lease_next_query(session, labeller_id=bob.id, run_id=run.id)
    assert second is not None and second.id == ids[1]


def test_a_labeller_may_lease_one_query_ahead_to_preload_it(session: Session) -> None:
    run = running_run(session)
    ids = push_queries(session, run_id=run.id, queries=[query_spec(i) for i in range(3)])
    alice, _ = create_labeller(session, name="alice")
    bob, _ = create_labeller(session, name="bob")

    current = lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    assert current is not None and current.id == ids[0]
    ahead = lease_next_query(session, labeller_id=alice.id, run_id=run.id, ahead_of=ids[0])
    assert ahead is not None and ahead.id == ids[1]
    # Asking again (a retried preload) returns the same pair; both leases are alice's.
    again = lease_next_query(session, labeller_id=alice.id, run_id=run.id, ahead_of=ids[0])
    assert again is not None and again.id == ids[1]
    other = lease_next_query(session, labeller_id=bob.id, run_id=run.id)
    assert other is not None and other.id == ids[2]

    submit_label(session, query_id=ids[0], labeller_id=alice.id, choice="left",
                 left_is_first=True)
    submit_label(session, query_id=ids[1], labeller_id=alice.id, choice="right",
                 left_is_first=True)
    assert lease_next_query(session, labeller_id=alice.id, run_id=run.id, ahead_of=ids[1]) is None


def test_no_labeller_sees_a_query_twice(session: Session) -> None:
    run = running_run(session)
    [query_id] = push_queries(session, run_id=run.id, queries=[query_spec(0, needs_labels=2)])
    alice, _ = create_labeller(session, name="alice")
    bob, _ = create_labeller(session, name="bob")
    carol, _ = create_labeller(session, name="carol")

    leased = lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    assert leased is not None and leased.id == query_id
    submit_label(
        session, query_id=query_id, labeller_id=alice.id, choice="left", left_is_first=True
    )
    assert session.get(Query, query_id).status is QueryStatus.PENDING  # type: ignore[union-attr]
    session.commit()

    assert lease_next_query(session, labeller_id=alice.id, run_id=run.id) is None
    leased = lease_next_query(session, labeller_id=bob.id, run_id=run.id)
    assert leased is not None and leased.id == query_id
    submit_label(session, query_id=query_id, labeller_id=bob.id, choice="right", left_is_first=True)

    assert session.get(Query, query_id).status is QueryStatus.LABELLED  # type: ignore[union-attr]
    session.commit()
    for labeller in (alice, bob, carol):  # it has all the labels it wants
        assert lease_next_query(session, labeller_id=labeller.id, run_id=run.id) is None


def test_an_expired_lease_passes_on_and_the_late_submit_is_refused(session: Session) -> None:
    run = running_run(session)
    [query_id] = push_queries(session, run_id=run.id, queries=[query_spec(0)])
    slow, _ = create_labeller(session, name="slow")
    quick, _ = create_labeller(session, name="quick")
    lease_next_query(session, labeller_id=slow.id, run_id=run.id)
    assert lease_next_query(session, labeller_id=quick.id, run_id=run.id) is None

    expire_lease(session, query_id)
    taken = lease_next_query(session, labeller_id=quick.id, run_id=run.id)
    assert taken is not None and taken.id == query_id and taken.lease_holder == quick.id

    before = counts(session)
    with pytest.raises(LeaseError, match="leased to another labeller"):
        submit_label(
            session, query_id=query_id, labeller_id=slow.id, choice="left", left_is_first=True
        )
    assert counts(session) == before == (0, 0, 0)
    _, created = submit_label(
        session, query_id=query_id, labeller_id=quick.id, choice="left", left_is_first=True
    )
    assert created and counts(session) == (1, 1, 1)


def test_an_expired_lease_nobody_took_is_still_refused(session: Session) -> None:
    run = running_run(session)
    [query_id] = push_queries(session, run_id=run.id, queries=[query_spec(0)])
    alice, _ = create_labeller(session, name="alice")
    lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    expire_lease(session, query_id)
    with pytest.raises(LeaseError, match="expired"):
        submit_label(
            session, query_id=query_id, labeller_id=alice.id, choice="left", left_is_first=True
        )
    assert counts(session) == (0, 0, 0)
    # Asking again gives her a fresh lease on it.
    again = lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    assert again is not None and again.id == query_id


def test_submitting_for_another_labellers_lease_changes_nothing(session: Session) -> None:
    run = running_run(session)
    ids = push_queries(session, run_id=run.id, queries=[query_spec(0), query_spec(1)])
    holder, _ = create_labeller(session, name="holder")
    intruder, _ = create_labeller(session, name="intruder")
    lease_next_query(session, labeller_id=holder.id, run_id=run.id)

    before = counts(session)
    with pytest.raises(LeaseError, match="leased to another labeller"):
        submit_label(
            session, query_id=ids[0], labeller_id=intruder.id, choice="left", left_is_first=True
        )
    with pytest.raises(LeaseError, match="holds no lease"):  # never leased
        submit_label(
            session, query_id=ids[1], labeller_id=intruder.id, choice="left", left_is_first=True
        )
    assert counts(session) == before
    query = session.get(Query, ids[0], populate_existing=True)
    assert query is not None and query.lease_holder == holder.id
    assert query.status is QueryStatus.LEASED


def test_human_runs_serve_rendered_queries_and_scripted_runs_only_by_name(
    session: Session,
) -> None:
    scripted = running_run(session, teacher=TeacherKind.SCRIPTED, worker_id="w1")
    human = running_run(session, teacher=TeacherKind.HUMAN, worker_id="w2")
    [scripted_q] = push_queries(
        session, run_id=scripted.id, queries=[query_spec(0, first_clip=None, second_clip=None)]
    )
    [unrendered] = push_queries(
        session, run_id=human.id, queries=[query_spec(0, first_clip=None, second_clip=None)]
    )
    [rendered] = push_queries(session, run_id=human.id, queries=[query_spec(1)])
    alice, _ = create_labeller(session, name="alice")
    teacher, _ = create_labeller(session, name="scripted-teacher")

    got = lease_next_query(session, labeller_id=alice.id)
    assert got is not None and got.id == rendered
    got = lease_next_query(session, labeller_id=teacher.id, run_id=scripted.id)
    assert got is not None and got.id == scripted_q

    set_clips(session, query_id=unrendered, first_clip="a.mp4", second_clip="b.mp4")
    bob, _ = create_labeller(session, name="bob")
    got = lease_next_query(session, labeller_id=bob.id)
    assert got is not None and got.id == unrendered


def test_paused_runs_are_labellable_and_stopping_ones_are_not(session: Session) -> None:
    run = running_run(session)
    ids = push_queries(session, run_id=run.id, queries=[query_spec(0), query_spec(1)])
    alice, _ = create_labeller(session, name="alice")
    set_run_status(session, run_id=run.id, status="paused")
    got = lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    assert got is not None and got.id == ids[0]

    set_run_status(session, run_id=run.id, status="stopping")
    assert lease_next_query(session, labeller_id=alice.id, run_id=run.id) is None


def test_asking_for_another_run_releases_the_held_lease(session: Session) -> None:
    run_a = running_run(session, worker_id="w1")
    run_b = running_run(session, worker_id="w2")
    [qa] = push_queries(session, run_id=run_a.id, queries=[query_spec(0)])
    [qb] = push_queries(session, run_id=run_b.id, queries=[query_spec(0)])
    alice, _ = create_labeller(session, name="alice")
    bob, _ = create_labeller(session, name="bob")

    assert lease_next_query(session, labeller_id=alice.id, run_id=run_a.id).id == qa  # type: ignore[union-attr]
    assert lease_next_query(session, labeller_id=alice.id, run_id=run_b.id).id == qb  # type: ignore[union-attr]
    # Alice let go of qa, so bob gets it at once.
    assert lease_next_query(session, labeller_id=bob.id, run_id=run_a.id).id == qa  # type: ignore[union-attr]


def test_cancelled_queries_are_not_served_and_their_leases_end(session: Session) -> None:
    run = running_run(session)
    ids = push_queries(session, run_id=run.id, queries=[query_spec(i) for i in range(3)])
    alice, _ = create_labeller(session, name="alice")
    lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    assert cancel_queries(session, run_id=run.id, query_ids=ids[:2]) == 2
    with pytest.raises(LeaseError, match="cancelled"):
        submit_label(
            session, query_id=ids[0], labeller_id=alice.id, choice="left", left_is_first=True
        )
    got = lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    assert got is not None and got.id == ids[2]
    assert cancel_queries(session, run_id=run.id) == 1
    assert lease_next_query(session, labeller_id=alice.id, run_id=run.id) is None


@pytest.mark.parametrize("name", ["_TAKE_OF_ANY_HUMAN_RUN", "_TAKE_OF_RUN",
                                  "_GOLD_OF_ANY_HUMAN_RUN", "_GOLD_OF_RUN"])
def test_the_lease_reads_by_index_not_every_label_or_query(engine: Engine, name: str) -> None:
    """A lease's cost must not grow with the labels stored: SQLite's plan for each of its
    looks searches an index for the labeller's answers and for the run's open queries (gold
    pairs apart from the others), and scans no table."""
    if engine.dialect.name != "sqlite":
        pytest.skip("SQLite's query plan")
    statement = getattr(queries_module, name).statement
    sql = str(statement.compile(dialect=engine.dialect))
    with engine.connect() as connection:
        plan = [row[-1] for row in connection.exec_driver_sql(
            "EXPLAIN QUERY PLAN " + sql, tuple([None] * sql.count("?"))
        )]
    assert not [step for step in plan if step.startswith("SCAN")], plan
    assert any("labels USING INDEX uq_labels_query_id_labeller_id_standing" in step
               for step in plan), plan
    assert any("candidate USING INDEX ix_queries_run_id_gold_status" in step
               for step in plan), plan
