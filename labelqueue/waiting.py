"""Nobody waits unpaid: a participant who asked for pairs and got none for their invite's
`wait_limit_s` (default `WAIT_LIMIT_S`) finishes with their completion code, "nothing left to
label" (`crowdstudy.completion.Progress.why` "nothing_left").

The lease records it (`asked`): each time a participant asks for a pair and gets none, while no
pair is on their screen either (a page preloading behind one it shows, `ahead_of`, has a pair
to label: a lease of theirs, kept, or a practice pair), `invitees.asked_at` moves on, and
`waiting_since` is set unless they were already waiting and asked within `GAP_S` before (a
page left closed for a while starts over when it comes back); getting a pair clears
`waiting_since`. `finish_if_waited` then marks the study complete once
they have asked without a pair for the limit (`nothing_left_at`): only the server's own record
of their asking counts, never a time the browser reports.
"""

from __future__ import annotations

from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import Integer, and_, bindparam, case, select, update
from sqlalchemy.orm import Session

from labelqueue.models import INVITEES, Invite, Invitee, UTCDateTime, utcnow
from labelqueue.prepared import DriverConnection, Prepared
from labelqueue.transaction import transaction

WAIT_LIMIT_S = 300
"""an invite's default `wait_limit_s`: five minutes of asking with nothing to label"""
GAP_S = 90.0
"""a wait goes on while the participant asks at least this often (the label page asks every
2 s; a browser slows a hidden tab's timers to once a minute)"""

_LABELLER = bindparam("labeller", type_=Integer())
_NOW = bindparam("at", type_=UTCDateTime())
_GOT_ONE = Prepared(
    update(INVITEES)
    .where(INVITEES.c.labeller_id == _LABELLER, INVITEES.c.waiting_since.is_not(None))
    .values(waiting_since=None, asked_at=_NOW)
)
_GOT_NONE = Prepared(
    update(INVITEES)
    .where(INVITEES.c.labeller_id == _LABELLER)
    .values(
        asked_at=_NOW,
        waiting_since=case(
            (and_(INVITEES.c.waiting_since.is_not(None),
                  INVITEES.c.asked_at > bindparam("stale", type_=UTCDateTime())),
             INVITEES.c.waiting_since),
            else_=_NOW,
        ),
    )
)


def asked(connection: DriverConnection, params: dict[str, Any], *, got: bool) -> None:
    """Record, in the lease's transaction, that the labeller (`params`: the lease's `labeller`
    and `at`) asked for a pair and got one or not; a labeller who joined by no invite has no
    row, and nothing changes."""
    if got:
        _GOT_ONE.count(connection, params)
    else:
        _GOT_NONE.count(connection, params | {"stale": params["at"] - timedelta(seconds=GAP_S)})


def waited_enough(invitee: Invitee, limit_s: int | None, now: datetime) -> bool:
    """Whether the participant has asked without a pair for `limit_s` (None: the default),
    and asks still."""
    since, last = invitee.waiting_since, invitee.asked_at
    if since is None or last is None or (now - last).total_seconds() > GAP_S:
        return False
    return (last - since).total_seconds() >= (WAIT_LIMIT_S if limit_s is None else limit_s)


def finish_if_waited(session: Session, *, labeller_id: int, now: datetime | None = None) -> bool:
    """Mark the participant's study complete when they have waited their invite's limit with
    nothing to label; whether it is (now or before)."""
    now = now or utcnow()
    with transaction(session):
        row = session.execute(
            select(Invitee, Invite.wait_limit_s).join(Invite, Invite.id == Invitee.invite_id)
            .where(Invitee.labeller_id == labeller_id)
            .execution_options(populate_existing=True)
        ).one_or_none()
        if row is None:
            return False
        invitee, limit = row
        if invitee.nothing_left_at is None and waited_enough(invitee, limit, now):
            invitee.nothing_left_at = now
        done = invitee.nothing_left_at is not None
    return done
