"""Server settings, read from the environment (prefix `SEPOA_`) by pydantic-settings."""

from __future__ import annotations

import secrets
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path
from urllib.parse import urlsplit

from pydantic import Field, ValidationError, field_validator, model_validator
from pydantic_core import ErrorDetails
from pydantic_settings import BaseSettings, SettingsConfigDict

from labelqueue import LEASE_SECONDS, check_url, read_url_file, sqlite_url


class Settings(BaseSettings):
    """Everything the server reads from its environment; frozen once built."""

    model_config = SettingsConfigDict(env_prefix="SEPOA_", frozen=True)

    database_url: str = ""
    """the queue database (a `sqlite:///` or `postgresql+psycopg://` URL); unset (or empty),
    the one `database_url_file` holds when that is set, else the SQLite file
    `<data_dir>/queue.db`"""
    database_url_file: str | None = None
    """a file holding the database URL, read as every `sepoa` command reads it
    (`labelqueue.read_url_file`: mode 600, its first line that is no `#` comment), so that a
    password stays out of the environment"""
    data_dir: Path = Path("data")
    """where the SQLite file and clips live by default"""
    clips_dir: Path | None = None
    """the clips folder; `<data_dir>/clips` when unset"""
    lease_seconds: float = Field(default=LEASE_SECONDS, gt=0)
    """how long a labeller holds a query before another may take it"""
    operator_token: str | None = Field(default=None, min_length=16)
    """a bearer token that acts as an operator (bootstraps the first labellers); unset: none"""
    secret_key: str = Field(default_factory=lambda: secrets.token_urlsafe(32), min_length=16)
    """signs clip URLs; random per process unless set (set it when several servers share a DB)"""
    public_url: str | None = None
    """the address people reach this server at (`https://label.example.org`, or with a path
    prefix behind a reverse proxy): invite links and clip URLs are made with it. Unset: invite
    links use the address the operator's request came to, clip URLs are relative"""
    clip_url_seconds: float = Field(default=900.0, gt=0)
    """how long a signed clip URL stays valid"""
    auth_cache_seconds: float = Field(default=5.0, ge=0)
    """how long a checked labeller-role token is trusted without the database (0: check every
    request); a revoked labeller can still read for this long, but cannot lease or answer (an
    operator-role token is checked every request)"""
    body_limit_bytes: int = Field(default=64 * 1024, ge=1024)
    """the largest request body read; a larger one is refused with 413"""
    clip_upload_bytes: int = Field(default=16 * 1024 * 1024, ge=1024)
    """the largest clip (or frame array) an external run's client may upload"""
    clip_max_seconds: float = Field(default=60.0, gt=0)
    """the longest clip an external run's client may upload"""
    clip_max_frames: int = Field(default=1000, ge=1)
    """the most frames a clip an external run's client uploads may hold"""
    unused_upload_hours: float = Field(default=24.0, gt=0)
    """an external run's uploaded clip that no pair names is deleted this long after its last
    upload, or at the next sweeps once its run is stopped (`server.upload_sweep`)"""
    upload_sweep_seconds: float = Field(default=600.0, gt=0)
    """how often the server looks for unused uploads (deleting one takes two looks)"""
    join_per_s: float = Field(default=1.0, gt=0)
    """joins by one invite link a second, after a burst of `join_burst` (429 beyond)"""
    join_burst: int = Field(default=30, ge=1)
    lease_per_s: float = Field(default=2.0, gt=0)
    """pairs one labeller may ask for a second (next), after a burst of `lease_burst` (429
    beyond); the label page asks every 2 s while it waits"""
    lease_burst: int = Field(default=20, ge=1)
    opentelemetry: bool = False
    """FastAPI's native OpenTelemetry spans and metrics, through the global providers (off: it
    cost every request a look at them)"""
    threadpool_size: int = Field(default=8, ge=1)
    """threads serving requests: more only queue on the database's one write lock"""
    label_threads: int | None = Field(default=None, ge=1)
    """threads doing the label API's queue work (next, submit, withdraw); unset: one on SQLite,
    whose writes run one at a time anyway (more threads only hand its lock and the interpreter's
    to each other), `threadpool_size` on PostgreSQL"""

    label_inline: bool | None = None
    """the label API's queue work on the event loop itself when SQLite's write lock is free at
    once (a hand-off to the label thread otherwise); unset: on SQLite. The hand-off, and the two
    threads taking the interpreter's lock in turn, cost more CPU than the work"""

    @field_validator("public_url")
    @classmethod
    def _public_url(cls, value: str | None) -> str | None:
        if value is None or not value.strip():
            return None
        value = value.strip().rstrip("/")
        parts = urlsplit(value)
        if parts.scheme not in ("http", "https") or not parts.netloc or parts.query \
                or parts.fragment:
            raise ValueError("must be an absolute http:// or https:// URL without a query, "
                             f"e.g. https://label.example.org (got {value!r})")
        return value

    def public(self, path: str) -> str:
        """`path` (starting with /) under `public_url`; unchanged when it is unset."""
        return path if self.public_url is None else self.public_url + path

    @model_validator(mode="after")
    def _default_database_url(self) -> Settings:
        """`database_url` when it is not given: from `database_url_file` when that is, else
        the SQLite file in `data_dir` (as `labelqueue.database_url` and every `sepoa` command
        order them); ValueError naming the file and what is wrong with it (unreadable, readable
        by others, no URL in it)."""
        if not self.database_url:
            url = (read_url_file(self.database_url_file) if self.database_url_file
                   else sqlite_url(self.data_dir))
            # frozen: set through the object's dict, once, while validating.
            object.__setattr__(self, "database_url", url)
        return self

    @model_validator(mode="after")
    def _default_clips_dir(self) -> Settings:
        if self.clips_dir is None:
            # frozen: set through the object's dict, once, while validating.
            object.__setattr__(self, "clips_dir", self.data_dir / "clips")
        return self

    @property
    def label_thread_count(self) -> int:
        """`label_threads`, or its default for the database."""
        if self.label_threads is not None:
            return self.label_threads
        return 1 if self.database_url.startswith("sqlite") else self.threadpool_size

    @property
    def label_work_inline(self) -> bool:
        """`label_inline`, or its default for the database."""
        if self.label_inline is not None:
            return self.label_inline
        return self.database_url.startswith("sqlite")

    @property
    def clips_root(self) -> Path:
        """The clips folder, absolute."""
        assert self.clips_dir is not None
        return self.clips_dir.resolve()


@lru_cache
def get_settings() -> Settings:
    """The process's settings, read from the environment once."""
    return Settings()


def settings_or_exit() -> Settings:
    """`get_settings()`, or the process ended with one line saying what is wrong (a server
    that uvicorn starts would print a traceback), a database URL that cannot be used too."""
    try:
        settings = get_settings()
        check_url(settings.database_url)  # a database it cannot open, or one in memory
    except ValidationError as error:
        raise SystemExit(f"error: {described(error.errors())}") from None
    except ValueError as error:
        raise SystemExit(f"error: {error}") from None
    return settings


SECRET_SETTINGS = ("secret_key", "operator_token", "database_url")
"""settings whose value an error never shows"""


def described(errors: Sequence[ErrorDetails]) -> str:
    """Refused settings in one line: each variable at fault, with its value (a secret's not
    shown), and what is wrong; a refusal of no one variable (the URL file's) as it says."""
    return "; ".join(_variable(e["loc"], e["input"]) + f": {e['msg']}" if e["loc"]
                     else e["msg"].removeprefix("Value error, ") for e in errors)


def _variable(loc: tuple[int | str, ...], value: object) -> str:
    name = "_".join(map(str, loc))
    shown = " (its value not shown)" if name in SECRET_SETTINGS else f"={value!r}"
    return f"SEPOA_{name.upper()}{shown}"
