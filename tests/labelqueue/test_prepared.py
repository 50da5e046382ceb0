"""Prepared statements give what SQLAlchemy's own execution gives, on each database."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest
from queue_helpers import query_spec
from sqlalchemy import Engine, Integer, bindparam, func, insert, select, update
from sqlalchemy.exc import DataError, IntegrityError

from labelqueue import create_labeller, create_run, push_queries
from labelqueue.models import LABELLERS, QUERIES, RUNS, QueryStatus, RunStatus
from labelqueue.prepared import DriverConnection, Prepared
from labelqueue.transaction import driver_transaction

LEASED_UNTIL = datetime(2031, 5, 6, 7, 8, 9, 123456, tzinfo=UTC)
LEASED_ROW = (
    update(QUERIES)
    .where(QUERIES.c.id == bindparam("query", type_=Integer()))
    .values(status=QueryStatus.LEASED, lease_holder=bindparam("holder", type_=Integer()),
            lease_expires_at=bindparam("until", type_=QUERIES.c.lease_expires_at.type))
    .returning(*QUERIES.c)
)
JOINED = (
    select(QUERIES.c.id, QUERIES.c.status, QUERIES.c.gold, QUERIES.c.lease_expires_at,
           RUNS.c.status.label("run_status"), RUNS.c.config, QUERIES.c.first_segment_return)
    .join(RUNS, RUNS.c.id == QUERIES.c.run_id)
    .where(QUERIES.c.run_id == bindparam("run", type_=Integer()),
           QUERIES.c.status != QueryStatus.CANCELLED)
    .order_by(QUERIES.c.id)
    .limit(2)
)


@pytest.fixture
def stored(session, engine: Engine) -> dict[str, int]:
    run = create_run(session, name="r", task="dmc:cheetah_run", algo="pebble", budget=10,
                     config={"feedback.gold_rate": 0.25, "sac.betas": [0.5, 0.9]}, teacher="human")
    labeller, _ = create_labeller(session, name="alice")
    ids = push_queries(session, run_id=run.id, queries=[query_spec(i) for i in range(3)])
    return {"run": run.id, "labeller": labeller.id, "query": ids[0]}


def test_rows_and_their_types_match_sqlalchemy(engine: Engine, stored) -> None:
    params = {"query": stored["query"], "holder": stored["labeller"], "until": LEASED_UNTIL}
    with engine.connect() as connection:
        with connection.begin():
            driver = DriverConnection.under(connection)
            [leased] = Prepared(LEASED_ROW).rows(driver, params)
            ours = Prepared(JOINED).rows(driver, {"run": stored["run"]})
            theirs = connection.execute(JOINED, {"run": stored["run"]}).all()
    assert leased.status == QueryStatus.LEASED and leased.lease_holder == stored["labeller"]
    assert leased.lease_expires_at == LEASED_UNTIL and leased.lease_expires_at.tzinfo is not None
    assert len(ours) == 2
    assert [tuple(row) for row in ours] == [tuple(row) for row in theirs]
    assert [row._asdict() for row in ours] == [dict(row._mapping) for row in theirs]
    first = ours[0]
    assert type(first.status) is type(theirs[0].status)
    assert first.gold is False and isinstance(first.run_status, RunStatus)
    assert first.config == {"feedback.gold_rate": 0.25, "sac.betas": [0.5, 0.9]}


def test_count_says_how_many_rows_changed(engine: Engine, stored) -> None:
    pending = Prepared(
        update(QUERIES)
        .where(QUERIES.c.run_id == bindparam("run", type_=Integer()),
               QUERIES.c.status == QueryStatus.PENDING)
        .values(status=QueryStatus.CANCELLED)
    )
    with engine.connect() as connection:
        with connection.begin():
            driver = DriverConnection.under(connection)
            assert pending.count(driver, {"run": stored["run"]}) == 3
            assert pending.count(driver, {"run": stored["run"]}) == 0
        with connection.begin():  # committed with the transaction SQLAlchemy began
            left = connection.execute(
                select(func.count()).where(QUERIES.c.status == QueryStatus.PENDING)).scalar()
    assert left == 0


def test_driver_errors_come_back_as_sqlalchemys_and_roll_back(engine: Engine, stored) -> None:
    twin = Prepared(insert(LABELLERS).values(
        name=bindparam("name"), token_hash=bindparam("hash"), role="labeller", active=True,
        created_at=bindparam("at", type_=LABELLERS.c.created_at.type)))
    with engine.connect() as connection:
        with pytest.raises(IntegrityError), connection.begin():  # a name already taken
            twin.count(DriverConnection.under(connection),
                       {"name": "alice", "hash": "x" * 64, "at": datetime.now(UTC)})
        assert connection.execute(select(func.count()).select_from(LABELLERS)).scalar() == 1
        connection.rollback()
        if engine.dialect.name == "postgresql":  # a number the column cannot hold
            big = Prepared(select(bindparam("n", type_=Integer()).label("n")))
            with pytest.raises(DataError), connection.begin():
                big.rows(DriverConnection.under(connection), {"n": 2**40})


def test_a_missing_parameter_runs_nothing(engine: Engine, stored) -> None:
    with engine.connect() as connection, connection.begin():
        with pytest.raises(KeyError, match="until"):
            Prepared(LEASED_ROW).rows(DriverConnection.under(connection),
                                      {"query": stored["query"], "holder": 1})
        row = connection.execute(select(QUERIES.c.status)
                                 .where(QUERIES.c.id == stored["query"])).one()
    assert row.status == QueryStatus.PENDING


def test_statements_it_cannot_run_are_refused_when_first_compiled(engine: Engine) -> None:
    expanding = Prepared(select(QUERIES.c.id).where(
        QUERIES.c.id.in_(bindparam("ids", expanding=True))))
    unnamed = Prepared(select(func.count() + 1))
    # The labeller's created_at and active have defaults SQLAlchemy computes at execution.
    defaulted = Prepared(insert(LABELLERS).values(name="x", token_hash="y", role="labeller"))
    with engine.connect() as connection:
        driver = DriverConnection.under(connection)
        with pytest.raises(TypeError, match="expanding"):
            expanding.rows(driver, {"ids": [1]})
        with pytest.raises(TypeError, match="needs a name"):
            unnamed.rows(driver, {})
        with pytest.raises(TypeError, match="no column defaults.*created_at"):
            defaulted.count(driver, {})


def test_times_are_compared_in_sql_as_sqlalchemy_stores_them(engine: Engine, stored) -> None:
    """A time passed to a Prepared statement compares in SQL against one SQLAlchemy stored:
    same format, same zone (SQLite compares the text)."""
    later = Prepared(select(QUERIES.c.id).where(
        QUERIES.c.created_at < bindparam("at", type_=QUERIES.c.created_at.type)))
    with engine.connect() as connection, connection.begin():
        driver = DriverConnection.under(connection)
        now = datetime.now(UTC)
        assert len(later.rows(driver, {"at": now + timedelta(seconds=1)})) == 3
        assert later.rows(driver, {"at": now - timedelta(hours=1)}) == []
        naive = now.replace(tzinfo=None)  # a naive time is taken as UTC
        assert len(later.rows(driver, {"at": naive + timedelta(seconds=1)})) == 3


def test_a_driver_transaction_commits_at_the_end_and_rolls_back_on_error(sessions, stored) -> None:
    cancel = Prepared(update(QUERIES).where(QUERIES.c.id == bindparam("query", type_=Integer()))
                      .values(status=QueryStatus.CANCELLED))
    status = Prepared(select(QUERIES.c.status).where(
        QUERIES.c.id == bindparam("query", type_=Integer())))
    query = {"query": stored["query"]}
    with sessions() as session:
        with pytest.raises(RuntimeError), driver_transaction(session) as connection:
            assert cancel.count(connection, query) == 1
            raise RuntimeError("the operation fails after its update")
        with driver_transaction(session) as connection:
            assert status.first(connection, query).status == QueryStatus.PENDING
            cancel.count(connection, query)
        with driver_transaction(session) as connection:
            assert status.first(connection, query).status == QueryStatus.CANCELLED
        assert not session.in_transaction()


def test_a_none_value_is_converted_as_sqlalchemy_converts_it(engine: Engine, stored) -> None:
    """Its type's processor sees None too: a JSON column stores JSON null, not SQL NULL."""
    statement = (update(RUNS).where(RUNS.c.id == bindparam("run", type_=Integer()))
                 .values(config=bindparam("config", type_=RUNS.c.config.type)))
    stored_as = select(RUNS.c.config.is_(None).label("sql_null")).where(RUNS.c.id == stored["run"])
    with engine.connect() as connection:
        with connection.begin():
            connection.execute(statement, {"run": stored["run"], "config": None})
            theirs = connection.execute(stored_as).scalar()
            Prepared(statement).count(DriverConnection.under(connection),
                                      {"run": stored["run"], "config": None})
            ours = connection.execute(stored_as).scalar()
    assert ours == theirs
