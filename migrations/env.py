"""Alembic environment for the queue database.

The URL, first found wins: `migrate(url)`'s attribute, `alembic -x url=...`, then the
environment's as the server reads it: $SEPOA_DATABASE_URL, the file $SEPOA_DATABASE_URL_FILE
names (`labelqueue.database_url`), else `queue.db` in $SEPOA_DATA_DIR (default `data`).
"""

import os
from logging.config import fileConfig

from alembic import context

from labelqueue.db_url import database_url as environment_url
from labelqueue.db_url import sqlite_url
from labelqueue.engine import make_engine
from labelqueue.models import Base, UTCDateTime

config = context.config
# Only the alembic command line configures logging; `migrate()` leaves the host's logging alone.
if config.config_file_name is not None:
    fileConfig(config.config_file_name, disable_existing_loggers=False)

target_metadata = Base.metadata


def database_url() -> str:
    return (
        config.attributes.get("url")
        or context.get_x_argument(as_dictionary=True).get("url")
        or environment_url(None, None)
        or sqlite_url(os.environ.get("SEPOA_DATA_DIR", "data"))
    )


def render_item(kind: str, item: object, _context: object) -> str | bool:
    # Autogenerate writes the models' UTCDateTime as the column type it stores.
    if kind == "type" and isinstance(item, UTCDateTime):
        return "sa.DateTime(timezone=True)"
    return False


def run_migrations_offline() -> None:
    url = database_url()
    context.configure(
        url=url,
        target_metadata=target_metadata,
        literal_binds=True,
        render_as_batch=url.startswith("sqlite"),
        render_item=render_item,
    )
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online() -> None:
    engine = make_engine(database_url(), foreign_keys=False)
    try:
        with engine.connect() as connection:
            context.configure(
                connection=connection,
                target_metadata=target_metadata,
                # SQLite alters most things only by copying the table; batch mode does that.
                render_as_batch=connection.dialect.name == "sqlite",
                # make_engine opens every SQLite transaction itself, so DDL is transactional too.
                transactional_ddl=True,
                render_item=render_item,
            )
            with context.begin_transaction():
                context.run_migrations()
    finally:
        engine.dispose()


if context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
