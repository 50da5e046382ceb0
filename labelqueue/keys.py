"""Secrets the server keeps in the queue database (`server_keys`), made on first use.

Kept in the database, not in a process's settings, so that every server process, every host
sharing the database and the command line (`sepoa invite verify`) use the same key, and a
restart changes nothing: a participant's completion code stays valid. Whoever can read the
database can read them, as they can read every label.
"""

from __future__ import annotations

import secrets

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from labelqueue.models import ServerKey, utcnow
from labelqueue.transaction import transaction

COMPLETION = "completion-codes"
"""the key that completion codes are derived with (`crowdstudy.completion.participant_code`)"""

_cache: dict[tuple[str, str], bytes] = {}


def server_key(session: Session, name: str = COMPLETION) -> bytes:
    """The key `name`, made (32 random bytes) the first time any process asks for it."""
    bind = session.get_bind()
    url = str(bind.engine.url)
    cached = _cache.get((url, name))
    if cached is not None:
        return cached
    for _ in range(2):
        with transaction(session):
            value = session.scalar(select(ServerKey.value).where(ServerKey.name == name))
        if value is not None:
            break
        try:
            with transaction(session):
                session.add(ServerKey(name=name, value=secrets.token_hex(32), created_at=utcnow()))
        except IntegrityError:  # another process made it just now: read theirs
            session.rollback()
    assert value is not None
    key = bytes.fromhex(value)
    _cache[(url, name)] = key
    return key
