"""What the queue operations raise when a request cannot be honoured.

Every error is a `QueueError`, so a caller can map the whole family to a client error in one
place; the subclasses say why.
"""

from sqlalchemy.exc import DBAPIError


class QueueError(Exception):
    """A queue operation refused; nothing was changed."""


class NotFound(QueueError):
    """The run, query or labeller named does not exist."""


class LeaseError(QueueError):
    """The labeller does not hold a valid lease on the query."""


class Conflict(QueueError):
    """The request contradicts the stored state (another worker's run, a different query)."""


class InvalidTransition(Conflict):
    """The run's status does not allow the change asked for."""


class Revoked(QueueError):
    """The labeller has been deactivated: it may neither lease nor answer."""


class StaleToken(Revoked):
    """The bearer token the request came with is no longer the labeller's: a new one replaced
    it (`rotate_token`), from whichever process."""


class OtherRun(QueueError):
    """The labeller joined by an invite for one run and asked for, or answered, another: they
    label their invite's run only."""

    @classmethod
    def asking(cls, own: int, asked: int | None) -> "OtherRun":
        """The refusal of a one-run invitee (of run `own`) asking for run `asked`."""
        return cls(f"you joined this study for run {own}: pairs of run {asked} are not yours "
                   f"to label (ask for run {own}, or for no run)")


class Invalid(QueueError, ValueError):
    """A value given to the operation is not valid; the message names it and what is valid. (A
    ValueError too, so that callers outside the server may catch it as one.)"""


class RunClosed(Conflict):
    """The run takes no answers in its status (only running and paused runs do)."""


def database_reason(err: DBAPIError) -> str:
    """The first line of what the database said (the driver's own message, not SQLAlchemy's
    wrapping of it): short enough for a one-line error."""
    return str(err.orig or err).strip().splitlines()[0]
