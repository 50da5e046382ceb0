"""An external run's row and its tokens: `create_external_run` makes one running, with no
worker; `issue_run_token` gives its client a bearer token scoped to it, `revoke_run_token` ends
one at once, and `run_of_token` reads which run a token is for."""

from __future__ import annotations

import dataclasses
import hashlib
import hmac
import re
import secrets

from sqlalchemy import select
from sqlalchemy.orm import Session

from labelqueue.errors import Conflict, Invalid, NotFound
from labelqueue.instructions import checked_instruction, record_instruction
from labelqueue.models import (
    Run,
    RunStatus,
    RunToken,
    TeacherKind,
    utcnow,
)
from labelqueue.runs import EXTERNAL as EXTERNAL
from labelqueue.transaction import detach, get_row, reading, transaction
from runvocab.config import FeedbackConfig
from runvocab.text import filled

TOKEN_PREFIX = "run."
ID_MAX = 2**31 - 1
"""the largest id an INTEGER column holds on PostgreSQL"""
_ID = re.compile(r"[0-9]{1,10}")


def stored_id(text: str) -> int | None:
    """The id `text` writes in ASCII digits, or None for text that is none (str.isdigit
    takes '²', which int() does not) or too large for an id column."""
    if _ID.fullmatch(text) is None or int(text) > ID_MAX:
        return None
    return int(text)


def is_external(run: Run) -> bool:
    return run.algo == EXTERNAL


def create_external_run(
    session: Session, *, name: str, task: str, budget: int, labels_per_query: int = 1,
    gold_rate: float = 0.0, gold_min_accuracy: float = 0.0, gold_min_answers: int = 10,
    practice_pairs: int = 0, instruction: str | None = None,
) -> Run:
    """A running external run: `task` in free text (its instruction is the task's own unless
    given), `labels_per_query` answers per pair, gold and practice as for any run. Invalid
    naming the field for a value out of range, or a blank task or name; nothing is stored
    then."""
    checks = {"budget": budget >= 1, "labels_per_query": 1 <= labels_per_query <= 50,
              "gold_rate": 0.0 <= gold_rate <= 0.5,
              "gold_min_accuracy": 0.0 <= gold_min_accuracy <= 1.0,
              "gold_min_answers": gold_min_answers >= 1,
              "practice_pairs": 0 <= practice_pairs <= 20,
              "task": len(task) <= 100, "name": len(name) <= 200}
    for field, fine in checks.items():
        if not fine:
            raise Invalid(f"{field}: out of range")
    try:
        task, name = filled(task, "task"), filled(name, "name")
    except ValueError as err:
        raise Invalid(str(err)) from None
    feedback = dataclasses.replace(
        FeedbackConfig(), budget=budget, labels_per_query=labels_per_query, gold_rate=gold_rate,
        gold_min_accuracy=gold_min_accuracy, gold_min_answers=gold_min_answers,
        practice_pairs=practice_pairs)
    stored_instruction = checked_instruction(instruction)
    now = utcnow()
    with transaction(session):
        run = Run(name=name, task=task, algo=EXTERNAL, preset=EXTERNAL, seed=0,
                  budget=budget, teacher=TeacherKind.HUMAN, teacher_params={}, config={},
                  resolved_config={"feedback": dataclasses.asdict(feedback)},
                  status=RunStatus.RUNNING, started_at=now, instruction=stored_instruction)
        session.add(run)
        session.flush()
        record_instruction(session, run)
        detach(session, run)
    return run


def issue_run_token(session: Session, *, run_id: int) -> str:
    """A new bearer token scoped to the external run (shown once; only its hash is kept):
    it pushes the run's pairs and reads its answers. Conflict for a run a worker trains."""
    with transaction(session):
        run = get_row(session, Run, run_id)
        if not is_external(run):
            raise Conflict(f"run {run_id} is trained by a worker: only an external run takes "
                           "a run token")
        row = RunToken(run_id=run_id, token_hash="")
        session.add(row)
        session.flush()
        token = f"{TOKEN_PREFIX}{row.id}.{secrets.token_urlsafe(32)}"
        row.token_hash = hashlib.sha256(token.encode()).hexdigest()
    return token


def run_tokens(session: Session, *, run_id: int) -> list[RunToken]:
    """The external run's tokens, oldest first, revoked ones too (a row keeps the token's hash
    only: its secret is shown once). NotFound for an unknown run."""
    with reading(session):
        get_row(session, Run, run_id)
        rows = list(session.scalars(select(RunToken).where(RunToken.run_id == run_id)
                                    .order_by(RunToken.id)))
        session.expunge_all()
    return rows


def revoke_run_token(session: Session, *, run_id: int, token_id: int) -> RunToken:
    """Revoke one of the run's tokens: from the next request on, it reaches nothing (each
    request reads its token's row, `run_of_token`; no server caches one). Revoking a revoked
    token changes nothing. NotFound for a token that is not this run's."""
    with transaction(session):
        row = session.get(RunToken, token_id, populate_existing=True)
        if row is None or row.run_id != run_id:
            raise NotFound(f"run {run_id} has no token {token_id}")
        if row.revoked_at is None:
            row.revoked_at = utcnow()
        detach(session, row)
    return row


def run_of_token(session: Session, *, token: str) -> int | None:
    """The run a run token is scoped to, or None for a token that is no live run token."""
    if not token.startswith(TOKEN_PREFIX):
        return None
    text, dot, _ = token.removeprefix(TOKEN_PREFIX).partition(".")
    token_id = stored_id(text)
    if not dot or token_id is None:
        return None
    with reading(session):
        row = session.get(RunToken, token_id, populate_existing=True)
        found = None if row is None else (row.run_id, row.token_hash, row.revoked_at)
    if found is None or found[2] is not None:
        return None
    digest = hashlib.sha256(token.encode()).hexdigest()
    return found[0] if hmac.compare_digest(found[1], digest) else None
