"""Where the queue database is: its URL (SQLite by default, or PostgreSQL), checked at the door,
read from a file of mode 600 or the environment, and shown with its password masked."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

from sqlalchemy.engine import make_url
from sqlalchemy.exc import ArgumentError, NoSuchModuleError


def sqlite_url(data_dir: str | Path) -> str:
    """The embedded default: the SQLite file `queue.db` in the data folder."""
    return f"sqlite:///{Path(data_dir) / 'queue.db'}"


DEFAULT_URL = sqlite_url("data")
VALID_URLS = "sqlite:///PATH or postgresql+psycopg://USER:PASSWORD@HOST/DATABASE"


def check_url(url: str) -> str:
    """`url` if SQLAlchemy can open databases of its kind with a driver that is installed, and
    it is not SQLite in memory (each connection's own); ValueError saying what is valid."""
    try:
        parsed = make_url(url)
        dialect = parsed.get_dialect()
    except (ArgumentError, NoSuchModuleError, ValueError):
        raise ValueError(
            f"{mask_url(url)!r} is not a database URL this app can open; use {VALID_URLS}"
        ) from None
    if parsed.get_backend_name() not in ("sqlite", "postgresql"):
        raise ValueError(
            f"{parsed.get_backend_name()} databases are not supported; use {VALID_URLS}"
        )
    if parsed.get_backend_name() == "sqlite" and (
            parsed.database in (None, "", ":memory:") or parsed.query.get("mode") == "memory"):
        raise ValueError(f"{mask_url(url)!r} is a database in memory, which the server, the "
                         f"workers and the next start cannot share; use {VALID_URLS}")
    try:  # the dialect loads its driver only when connecting: a missing one is found here
        dialect.import_dbapi()
    except ImportError:
        hint = (" (pip install -e '.[postgres]')" if parsed.get_driver_name() == "psycopg"
                else "")
        raise ValueError(
            f"{mask_url(url)!r} needs the {parsed.get_driver_name()} driver, which is not "
            f"installed; use {VALID_URLS}{hint}"
        ) from None
    folder = Path(parsed.database or "").parent  # where a SQLite file would be made
    file = next((p for p in (folder, *folder.parents) if p.exists() and not p.is_dir()), None)
    if parsed.get_backend_name() == "sqlite" and file is not None:
        raise ValueError(f"{mask_url(url)!r}: {file} is a file, not a folder to hold it")
    return url


SECRET_QUERY_KEYS = ("password", "sslpassword")
"""query parameters of a database URL that hold a secret (libpq reads a password there too)"""


def mask_url(url: str) -> str:
    """`url` with its password (and any password query parameter) shown as `***`: the form every
    log line, hint and error message uses, so no secret reaches a log, a terminal or a file."""
    try:
        parsed = make_url(url)
    except (ArgumentError, ValueError):
        return url.split("@")[-1] if "@" in url else url
    hidden = {key: "***" for key in parsed.query if key in SECRET_QUERY_KEYS}
    if hidden:
        parsed = parsed.update_query_dict(hidden)
    return parsed.render_as_string(hide_password=True).replace("%2A%2A%2A", "***")


def url_has_secret(url: str) -> bool:
    """Whether `url` carries a password (in its user part or its query)."""
    try:
        parsed = make_url(url)
    except (ArgumentError, ValueError):
        return "@" in url
    return parsed.password is not None or any(key in parsed.query for key in SECRET_QUERY_KEYS)


def read_url_file(path: str | Path) -> str:
    """The database URL kept in the file `path` (its first line that is neither empty nor a
    `#` comment). Like libpq with a password file, a file that other users may read is refused.
    ValueError naming the file and the problem."""
    try:
        mode = Path(path).stat().st_mode
        lines = Path(path).read_text().splitlines()
    except (OSError, UnicodeDecodeError) as err:
        why = "not UTF-8 text" if isinstance(err, UnicodeDecodeError) else err.strerror or err
        raise ValueError(f"database URL file {path}: {why}; give a text file of the URL") from None
    if mode & 0o077:
        raise ValueError(f"database URL file {path} may be read by other users (mode "
                         f"{mode & 0o777:o}); chmod 600 {path}")
    for line in lines:
        if line.strip() and not line.lstrip().startswith("#"):
            return line.strip()
    raise ValueError(f"database URL file {path} holds no URL")


def database_url(url: str | None, url_file: str | None,
                 environ: Mapping[str, str] | None = None) -> str | None:
    """The queue's URL from a command's `--database-url` or `--database-url-file` (not both),
    else from the environment: SEPOA_DATABASE_URL, else the file named by
    SEPOA_DATABASE_URL_FILE. None when none is given. ValueError for both flags, or a file that
    cannot be used (`read_url_file`)."""
    environ = os.environ if environ is None else environ
    if url and url_file:
        raise ValueError("give --database-url or --database-url-file, not both")
    if url_file:
        return read_url_file(url_file)
    if url:
        return url
    if environ.get("SEPOA_DATABASE_URL"):
        return environ["SEPOA_DATABASE_URL"]
    if environ.get("SEPOA_DATABASE_URL_FILE"):
        return read_url_file(environ["SEPOA_DATABASE_URL_FILE"])
    return None
