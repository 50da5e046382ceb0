"""Core statements run on the driver's own connection (`DriverConnection`).

A `Prepared` statement is compiled once per dialect. Each execution then converts the caller's
values with the column types' own bind processors, hands the SQL to the driver, and converts the
rows with the types' result processors: what SQLAlchemy's execution does, without its
per-execution machinery (cache key, execution context, parameter and result objects), which on
the label API's hot path costs many times the driver's own work, on SQLite and PostgreSQL alike
(benchmarks/README.md has the figures).

Only plain statements are taken, checked when first compiled: every parameter is either a
literal of the statement or one the caller must give (no expanding IN lists, no values rendered
at execution time). The driver's errors reach callers as SQLAlchemy's own (`DataError`,
`IntegrityError`, ...). Transactions are `labelqueue.transaction.driver_transaction`'s.

Tracing sees these statements as it sees SQLAlchemy's: an engine's `before_cursor_execute` and
`after_cursor_execute` listeners are called with each one (given the SQLAlchemy `Connection`
the driver's connection was taken through), and `echo` or the `sqlalchemy.engine` logger at
INFO logs its SQL and values. An engine with neither pays nothing for it.
"""

from __future__ import annotations

import logging
from collections import namedtuple
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from sqlalchemy import Connection, Dialect, Engine, PoolProxiedConnection, Select
from sqlalchemy.exc import DBAPIError
from sqlalchemy.sql.dml import UpdateBase

Statement = Select[Any] | UpdateBase


@dataclass(frozen=True)
class _Plan:
    """A statement as one dialect runs it."""

    sql: str
    slots: tuple[tuple[str, bool, Any], ...]
    """each parameter in the driver's order: its name, whether the caller gives it, and then
    its converter (or None), else the statement's own value, already converted"""
    positional: bool
    """the driver takes the values as a tuple, in `slots`' order (else a dict by name)"""
    row: type[tuple[Any, ...]] | None
    """the result's row type (a named tuple); None for a statement that returns no rows"""

    def driver_values(self, params: Mapping[str, Any]) -> Any:
        values = []
        for name, given, fixed in self.slots:
            if given:
                value = params[name]  # converted even when None, as SQLAlchemy does
                values.append(value if fixed is None else fixed(value))
            else:
                values.append(fixed)
        if self.positional:
            return tuple(values)
        return {name: value for (name, _, _), value in zip(self.slots, values, strict=True)}


def _plan(statement: Statement, dialect: Dialect) -> _Plan:
    compiled = statement.compile(dialect=dialect)
    if getattr(compiled, "literal_execute_params", None) or getattr(
        compiled, "post_compile_params", None
    ):
        raise TypeError("a Prepared statement takes no values rendered at execution time "
                        "(expanding IN lists, literal_execute)")
    computed = [column.name for kind in ("insert_prefetch", "update_prefetch")
                for column in getattr(compiled, kind, ())]
    if computed:  # SQLAlchemy's execution would compute their defaults
        raise TypeError(f"a Prepared statement computes no column defaults: give {computed}")
    slot: dict[str, tuple[str, bool, Any]] = {}
    for bind, name in compiled.bind_names.items():
        if bind.expanding:
            raise TypeError(f"a Prepared statement takes no expanding parameter ({name})")
        convert = bind.type.dialect_impl(dialect).bind_processor(dialect)
        if bind.required:
            slot[name] = (name, True, convert)
        else:
            value = bind.effective_value
            slot[name] = (name, False, value if convert is None else convert(value))
    names = [str(name) for name in statement.exported_columns.keys()]
    if len(set(names)) != len(names) or not all(
        name.isidentifier() and not name.startswith("_") for name in names
    ):
        raise TypeError(f"every column of a Prepared statement needs a name of its own (got "
                        f"{names}): label them")
    row = namedtuple("Row", names) if names else None
    order = compiled.positiontup if compiled.positional and compiled.positiontup else slot
    return _Plan(compiled.string, tuple(slot[name] for name in order), compiled.positional, row)


def traced(engine: Engine) -> bool:
    """Whether anything watches the engine's statements: cursor-execute listeners, or its
    logger at INFO (`echo`)."""
    hooks = engine.dispatch  # the engine's event listeners, as its connections inherit them
    return bool(hooks.before_cursor_execute or hooks.after_cursor_execute) or \
        engine.logger.isEnabledFor(logging.INFO)


class DriverConnection:
    """A driver's connection in a transaction, as `Prepared` statements run on it: from the
    engine's pool (`pooled`, invalidated when an error says the database went away), or the one
    under a SQLAlchemy `Connection` (whose own error handling then applies). With `tracer`, the
    SQLAlchemy `Connection` it was taken through, each statement is shown to the engine's
    cursor-execute listeners and logger as SQLAlchemy's own statements are."""

    def __init__(self, dbapi: Any, dialect: Dialect, pooled: PoolProxiedConnection | None = None,
                 tracer: Connection | None = None):
        self.dbapi = dbapi
        self.dialect = dialect
        self.pooled = pooled
        self.tracer = tracer

    @classmethod
    def under(cls, connection: Connection) -> DriverConnection:
        return cls(connection.connection.dbapi_connection, connection.dialect, tracer=connection)

    def before(self, cursor: Any, sql: str, params: Any) -> None:
        assert self.tracer is not None
        for hook in self.tracer.dispatch.before_cursor_execute:
            hook(self.tracer, cursor, sql, params, None, False)
        logger = self.tracer.engine.logger
        if logger.isEnabledFor(logging.INFO):
            logger.info(sql)
            logger.info("[prepared] %r", params)

    def after(self, cursor: Any, sql: str, params: Any) -> None:
        assert self.tracer is not None
        for hook in self.tracer.dispatch.after_cursor_execute:
            hook(self.tracer, cursor, sql, params, None, False)

    def wrapped(self, error: Exception, sql: str, params: Any) -> DBAPIError:
        """A driver's error as SQLAlchemy raises it; a lost connection leaves the pool."""
        dbapi_error = self.dialect.loaded_dbapi.Error
        lost = self.dialect.is_disconnect(error, self.dbapi, None)  # type: ignore[arg-type]
        if lost and self.pooled is not None:
            self.pooled.invalidate(error)
        wrapped = DBAPIError.instance(
            sql, params, error, dbapi_error, dialect=self.dialect, connection_invalidated=lost
        )
        assert isinstance(wrapped, DBAPIError)
        return wrapped


class Prepared:
    """A Core statement (select, or insert/update/delete with or without RETURNING) that runs on
    a `DriverConnection`, in the transaction it holds.

    Rows come back as named tuples (`row.status`, `row._asdict()`), their values converted as
    SQLAlchemy converts them. A missing parameter raises KeyError before anything runs."""

    def __init__(self, statement: Statement):
        self.statement = statement
        self._plans: dict[tuple[str, str], _Plan] = {}
        self._readers: dict[tuple[str, str], list[tuple[int, Callable[[Any], Any]]]] = {}

    def _plan_for(self, dialect: Dialect) -> _Plan:
        key = (dialect.name, dialect.driver)
        plan = self._plans.get(key)
        if plan is None:
            plan = self._plans[key] = _plan(self.statement, dialect)
        return plan

    def _readers_for(
        self, dialect: Dialect, description: Sequence[Any]
    ) -> list[tuple[int, Callable[[Any], Any]]]:
        """The columns whose values are converted, with their converters, from the driver's
        first description of the result (as SQLAlchemy caches them per compiled statement)."""
        key = (dialect.name, dialect.driver)
        readers = self._readers.get(key)
        if readers is None:
            types = [column.type for column in self.statement.exported_columns]
            converters = [
                type_.dialect_impl(dialect).result_processor(dialect, column[1])
                for type_, column in zip(types, description, strict=True)
            ]
            readers = self._readers[key] = [
                (i, read) for i, read in enumerate(converters) if read is not None
            ]
        return readers

    def _run(self, connection: DriverConnection, params: Mapping[str, Any]) -> tuple[Any, _Plan]:
        dialect = connection.dialect
        plan = self._plan_for(dialect)
        driver_params = plan.driver_values(params)
        cursor = connection.dbapi.cursor()
        if connection.tracer is not None:
            connection.before(cursor, plan.sql, driver_params)
        try:
            cursor.execute(plan.sql, driver_params)
        except dialect.loaded_dbapi.Error as error:
            cursor.close()
            raise connection.wrapped(error, plan.sql, driver_params) from error
        if connection.tracer is not None:
            connection.after(cursor, plan.sql, driver_params)
        return cursor, plan

    def rows(self, connection: DriverConnection, params: Mapping[str, Any]) -> list[Any]:
        """Every row the statement returns."""
        cursor, plan = self._run(connection, params)
        try:
            assert plan.row is not None, "the statement returns no rows"
            readers = self._readers_for(connection.dialect, cursor.description)
            make = plan.row._make  # type: ignore[attr-defined]
            rows = []
            for raw in cursor.fetchall():
                values = list(raw)
                for i, read in readers:
                    values[i] = read(values[i])
                rows.append(make(values))
            return rows
        finally:
            cursor.close()

    def first(self, connection: DriverConnection, params: Mapping[str, Any]) -> Any | None:
        """The first row the statement returns, or None."""
        rows = self.rows(connection, params)
        return rows[0] if rows else None

    def count(self, connection: DriverConnection, params: Mapping[str, Any]) -> int:
        """Run a statement that returns no rows; how many rows it changed."""
        cursor, _ = self._run(connection, params)
        try:
            return int(cursor.rowcount)
        finally:
            cursor.close()
