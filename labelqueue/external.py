"""External runs: runs no worker trains, whose pairs a client pushes over REST.

An external run (`algo` "external") is created running, with no worker: a client holding a
token scoped to the run (`issue_run_token`; `revoke_run_token` ends one at once) pushes pairs
of clips (`push_pairs`) and reads the answers people give them (`answers_after`). Everything
else is the queue's as for any run: the pairs are queries, leased and answered through the same
operations, with k answers each (`feedback.labels_per_query`), gold and practice pairs, invites
and the quality pages. A worker never claims one (`labelqueue.runs.claim_run`).

How its answers count: an answer to an ordinary pair spends one of the run's budget (skips
and can't-tells too), counts toward a study's target and code when decisive, and is given to
the client; an answer to a gold pair costs no budget, counts toward a study's target like any
other (it looks like one) and is given to the client marked gold; a practice answer costs
nothing, counts toward nothing and is not given to the client. A push is refused once its
pairs would ask for more answers than the budget has left.

A pushed pair carries an idempotency key, unique in its run: pushing the same content under
the same key again returns the stored query; other content under a used key is refused. Its
hidden metadata (the client's own ids, true returns for the calibration report, a gold pair's
known answer) is stored beside the query and never sent to a labeller.
"""

from __future__ import annotations

import dataclasses
import hashlib
import hmac
import json
import math
import secrets
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import func, insert, select
from sqlalchemy.orm import Session

from labelqueue.errors import Conflict, Invalid, NotFound
from labelqueue.instructions import checked_instruction, record_instruction
from labelqueue.models import (
    EXTERNAL_PAIRS,
    QUERIES,
    ExternalPair,
    Label,
    Labeller,
    Query,
    QueryStatus,
    Run,
    RunStatus,
    RunToken,
    TeacherKind,
    Withdrawal,
    utcnow,
)
from labelqueue.practice import reserve
from labelqueue.queries import _query_fields
from labelqueue.runs import EXTERNAL as EXTERNAL
from labelqueue.transaction import detach, get_row, reading, transaction
from runvocab.answers import DECISIVE, Answer, aggregate
from runvocab.clip_format import ClipInfo
from runvocab.config import FeedbackConfig

KEY_MAX = 200
"""the longest idempotency key"""
META_MAX_BYTES = 4096
"""the most a pair's hidden metadata may hold, as JSON"""
TOKEN_PREFIX = "run."
FEED_LIMIT = 500
"""the most events one read of the answers feed returns"""


def is_external(run: Run) -> bool:
    return run.algo == EXTERNAL


def create_external_run(
    session: Session, *, name: str, task: str, budget: int, labels_per_query: int = 1,
    gold_rate: float = 0.0, gold_min_accuracy: float = 0.0, gold_min_answers: int = 10,
    practice_pairs: int = 0, instruction: str | None = None,
) -> Run:
    """A running external run: `task` in free text (its instruction is the task's own unless
    given), `labels_per_query` answers per pair, gold and practice as for any run. Invalid
    naming the field for a value out of range; nothing is stored then."""
    checks = {"budget": budget >= 1, "labels_per_query": 1 <= labels_per_query <= 50,
              "gold_rate": 0.0 <= gold_rate <= 0.5,
              "gold_min_accuracy": 0.0 <= gold_min_accuracy <= 1.0,
              "gold_min_answers": gold_min_answers >= 1,
              "practice_pairs": 0 <= practice_pairs <= 20,
              "task": 1 <= len(task.strip()) <= 100}
    for field, fine in checks.items():
        if not fine:
            raise Invalid(f"{field}: out of range")
    feedback = dataclasses.replace(
        FeedbackConfig(), budget=budget, labels_per_query=labels_per_query, gold_rate=gold_rate,
        gold_min_accuracy=gold_min_accuracy, gold_min_answers=gold_min_answers,
        practice_pairs=practice_pairs)
    stored_instruction = checked_instruction(instruction)
    now = utcnow()
    with transaction(session):
        run = Run(name=name, task=task.strip(), algo=EXTERNAL, preset=EXTERNAL, seed=0,
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
    token_id, dot, _ = token.removeprefix(TOKEN_PREFIX).partition(".")
    if not dot or not token_id.isdigit() or len(token_id) > 18:
        return None
    with reading(session):
        row = session.get(RunToken, int(token_id), populate_existing=True)
        found = None if row is None else (row.run_id, row.token_hash, row.revoked_at)
    if found is None or found[2] is not None:
        return None
    digest = hashlib.sha256(token.encode()).hexdigest()
    return found[0] if hmac.compare_digest(found[1], digest) else None


@dataclass(frozen=True)
class PairSpec:
    """One pair as a client pushes it: two uploaded clips and what it knows of them."""

    key: str
    """the idempotency key, unique in the run"""
    first_clip: str
    """the id of an uploaded clip (`clip_key` finds its file)"""
    second_clip: str
    gold: Answer | None = None
    """a gold pair's known answer (first or second); none: an ordinary pair"""
    returns: tuple[float, float] | None = None
    """the two segments' true returns (hidden; for the calibration report and accuracy)"""
    trajectory_returns: tuple[float, float] | None = None
    """their whole trajectories' returns (hidden); none: the segments' own"""
    meta: Mapping[str, Any] | None = None
    """the client's own hidden metadata, returned with the pair's answers"""

    def digest(self) -> str:
        content = {"first_clip": self.first_clip, "second_clip": self.second_clip,
                   "gold": None if self.gold is None else Answer(self.gold).value,
                   "returns": self.returns, "trajectory_returns": self.trajectory_returns,
                   "meta": self.meta}
        text = json.dumps(content, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()


@dataclass(frozen=True)
class Pushed:
    """A pushed pair's query, and whether this push stored it (false: its key was stored)."""

    key: str
    query_id: int
    created: bool


def clip_key(run_id: int, clip_id: str, container: str) -> str:
    """A client's uploaded clip's storage key, relative to the clips folder."""
    return f"external/{run_id}/{clip_id}.{container}"


@dataclass(frozen=True)
class ClipUse:
    """An external run's status, and the uploaded clips its pairs name (their ids)."""

    status: RunStatus
    clip_ids: frozenset[str]

    @property
    def over(self) -> bool:
        """The run takes no pairs now (stopped, finished or failed; a requeue runs it again)."""
        return self.status not in (RunStatus.QUEUED, RunStatus.RUNNING, RunStatus.PAUSED)


def clip_use(session: Session) -> dict[int, ClipUse]:
    """Per external run: its status and the ids of the uploaded clips its pairs name."""
    with reading(session):
        statuses = dict(session.execute(select(Run.id, Run.status).where(Run.algo == EXTERNAL))
                        .tuples().all())
        named = session.execute(
            select(QUERIES.c.run_id, QUERIES.c.first_clip, QUERIES.c.second_clip)
            .where(QUERIES.c.run_id.in_(list(statuses)), QUERIES.c.rule == EXTERNAL)).all()
    ids: dict[int, set[str]] = {run_id: set() for run_id in statuses}
    for run_id, *keys in named:
        ids[run_id].update(key.rpartition("/")[2].partition(".")[0] for key in keys if key)
    return {run_id: ClipUse(RunStatus(status), frozenset(ids[run_id]))
            for run_id, status in statuses.items()}


def _check_pair(index: int, pair: PairSpec, clips: Mapping[str, ClipInfo]) -> None:
    where = f"pairs[{index}] ({pair.key!r})"
    if not 1 <= len(pair.key) <= KEY_MAX:
        raise Invalid(f"{where}: key must be 1-{KEY_MAX} characters")
    for side, clip in (("first_clip", pair.first_clip), ("second_clip", pair.second_clip)):
        if clip not in clips:
            raise Invalid(f"{where}: {side} {clip!r} is no clip uploaded to this run")
    first, second = clips[pair.first_clip], clips[pair.second_clip]
    if (first.width, first.height, first.frames) != (second.width, second.height, second.frames):
        raise Invalid(
            f"{where}: the two clips differ in shape: {first.width}x{first.height}, "
            f"{first.frames} frames against {second.width}x{second.height}, {second.frames} "
            "frames (the label page plays them side by side on one clock)")
    for name in ("returns", "trajectory_returns"):
        values = getattr(pair, name)
        if values is not None and not all(math.isfinite(v) for v in values):
            raise Invalid(f"{where}: {name} must be finite numbers")
    if pair.trajectory_returns is not None and pair.returns is None:
        raise Invalid(f"{where}: trajectory_returns needs returns")
    if pair.gold is not None:
        if pair.gold not in (Answer.FIRST, Answer.SECOND):
            raise Invalid(f"{where}: a gold pair's answer is first or second, not "
                             f"{pair.gold!r}")
        if pair.returns is not None:
            by_returns = (Answer.FIRST if pair.returns[0] > pair.returns[1] else
                          Answer.SECOND if pair.returns[1] > pair.returns[0] else None)
            if by_returns != pair.gold:
                raise Invalid(f"{where}: the gold answer {pair.gold.value} contradicts the "
                                 f"returns {list(pair.returns)}")
    if pair.meta is not None and len(json.dumps(pair.meta)) > META_MAX_BYTES:
        raise Invalid(f"{where}: meta is larger than {META_MAX_BYTES} bytes as JSON")


def push_pairs(session: Session, *, run_id: int, pairs: Sequence[PairSpec],
               clips: Mapping[str, ClipInfo]) -> list[Pushed]:
    """Store the pairs as queries of the external run, all or none; one `Pushed` per pair, in
    order. `clips`: what the uploaded clips the pairs name hold (`runvocab.clip_format.ClipInfo`).

    Invalid naming the pair for a missing clip, two clips of different shapes, a gold
    answer that is neither first nor second or contradicts the returns, or a key used twice in
    the push; Conflict for a key stored with other content, a run that is no external run or
    takes no answers, or pairs beyond the budget. Nothing is stored on any refusal.
    """
    keys = Counter(pair.key for pair in pairs)
    for index, pair in enumerate(pairs):
        _check_pair(index, pair, clips)
        if keys[pair.key] > 1:
            raise Invalid(f"pairs[{index}]: key {pair.key!r} is used twice in this push")
    digests = [pair.digest() for pair in pairs]
    with transaction(session):
        run = get_row(session, Run, run_id)
        if not is_external(run):
            raise Conflict(f"run {run_id} is trained by a worker: pairs are pushed to an "
                           "external run only")
        if run.status not in (RunStatus.RUNNING, RunStatus.PAUSED):
            raise Conflict(f"run {run_id} is {run.status.value}: it takes no more pairs")
        stored = {row.key: row for row in session.execute(
            select(EXTERNAL_PAIRS.c.key, EXTERNAL_PAIRS.c.digest, EXTERNAL_PAIRS.c.query_id)
            .where(EXTERNAL_PAIRS.c.run_id == run_id,
                   EXTERNAL_PAIRS.c.key.in_(list(keys))))}
        for pair, digest in zip(pairs, digests, strict=True):
            row = stored.get(pair.key)
            if row is not None and row.digest != digest:
                raise Conflict(f"key {pair.key!r} was pushed before with other content (query "
                               f"{row.query_id}): a new pair needs a new key")
        new = [(pair, digest) for pair, digest in zip(pairs, digests, strict=True)
               if pair.key not in stored]
        k = int(run.resolved_config["feedback"]["labels_per_query"]) if run.resolved_config \
            else 1
        _check_budget(session, run=run, new_answers=k * sum(p.gold is None for p, _ in new))
        position = int(session.scalar(select(func.coalesce(func.max(QUERIES.c.position), -1))
                                      .where(QUERIES.c.run_id == run_id)) or 0) + 1
        now = utcnow()
        specs = [_query_spec(run_id, pair, clips, position + i, k, now)
                 for i, (pair, _) in enumerate(new)]
        if specs:
            reserve(session, run_id=run_id, specs=specs)
            ids = session.execute(insert(QUERIES).returning(
                QUERIES.c.id, sort_by_parameter_order=True), specs).scalars().all()
            session.execute(insert(EXTERNAL_PAIRS), [
                {"query_id": query_id, "run_id": run_id, "key": pair.key, "digest": digest,
                 "meta": None if pair.meta is None else dict(pair.meta),
                 "gold_answer": pair.gold if pair.gold is not None and pair.returns is None
                 else None}
                for query_id, (pair, digest) in zip(ids, new, strict=True)])
        created = {pair.key: query_id for query_id, (pair, _) in
                   zip(ids if specs else [], new, strict=True)}
    return [Pushed(pair.key, created[pair.key], True) if pair.key in created
            else Pushed(pair.key, stored[pair.key].query_id, False) for pair in pairs]


def _check_budget(session: Session, *, run: Run, new_answers: int) -> None:
    """Conflict when the run's ordinary pairs would ask for more answers than its budget."""
    if new_answers == 0:
        return
    asked = session.scalar(
        select(func.coalesce(func.sum(QUERIES.c.needs_labels), 0)).where(
            QUERIES.c.run_id == run.id, QUERIES.c.gold.is_(False),
            QUERIES.c.status != QueryStatus.CANCELLED)) or 0
    if asked + new_answers > run.budget:
        raise Conflict(f"run {run.id}'s budget is {run.budget} answers, {asked} of them asked "
                       f"for already: these pairs ask for {new_answers} more")


def _query_spec(run_id: int, pair: PairSpec, clips: Mapping[str, ClipInfo], position: int,
                k: int, now: datetime) -> dict[str, Any]:
    first, second = clips[pair.first_clip], clips[pair.second_clip]
    truth: dict[str, Any] = {}
    if pair.returns is not None:
        trajectory = pair.trajectory_returns or pair.returns
        truth = {"first_segment_return": pair.returns[0],
                 "second_segment_return": pair.returns[1],
                 "first_trajectory_return": trajectory[0],
                 "second_trajectory_return": trajectory[1]}
    # An external pair is its own two "trajectories": the clips, whole, from their start.
    fields = _query_fields({
        "round": 0, "position": position, "segment_length": first.frames,
        "first_trajectory": 2 * position, "first_start": 0,
        "second_trajectory": 2 * position + 1, "second_start": 0,
        "first_clip": clip_key(run_id, pair.first_clip, first.container),
        "second_clip": clip_key(run_id, pair.second_clip, second.container),
        "rule": EXTERNAL, "gold": pair.gold is not None, "needs_labels": k, **truth})
    return fields | {"run_id": run_id, "status": QueryStatus.PENDING, "created_at": now,
                     "practice": False}


def known_answer(session: Session, *, query_id: int) -> Answer | None:
    """A gold pair's answer as its external client gave it (none for any other pair)."""
    with reading(session):
        row = session.get(ExternalPair, query_id, populate_existing=True)
        return None if row is None or row.gold_answer is None else Answer(row.gold_answer)


@dataclass(frozen=True)
class Cursor:
    """Where a reader of the answers feed is: after this label id and this withdrawal id."""

    label: int = 0
    withdrawal: int = 0

    def __str__(self) -> str:
        return f"{self.label}.{self.withdrawal}"

    @classmethod
    def parse(cls, text: str) -> Cursor:
        """Invalid for text that is no cursor the feed gave."""
        label, dot, withdrawal = text.partition(".")
        if not (label.isdigit() and withdrawal.isdigit() and dot) or len(text) > 40:
            raise Invalid(f"cursor {text!r} is not one the answers feed gave (like '0.0')")
        return cls(int(label), int(withdrawal))


def tally(answers: Sequence[Answer]) -> tuple[Answer, bool]:
    """The aggregate of a pair's answers (`runvocab.answers.aggregate`: the majority, can't-tell
    when most cannot tell), and whether two decisive answers tie for the most (then can't-tell
    too)."""
    counts = Counter(a for a in answers if a in DECISIVE).most_common()
    tie = len(counts) > 1 and counts[0][1] == counts[1][1]
    return aggregate(answers), tie


@dataclass(frozen=True)
class Feed:
    events: list[dict[str, Any]]
    cursor: Cursor
    open_pairs: int
    """ordinary pairs still short of their k answers"""
    status: str


def answers_after(session: Session, *, run_id: int, cursor: Cursor,
                  limit: int = FEED_LIMIT) -> Feed:
    """The external run's answers and withdrawals after `cursor`, oldest first, each with its
    pair's key and hidden metadata, the pair's standing answers by labeller, their aggregate
    and whether it ties. A label taken back before it was read is never given; one read and
    then taken back comes again as a withdrawal. Practice answers are not given.

    The cursor is exact, with nothing held back: a run's labels (and its withdrawals) commit
    in the order of their ids, since each draws its id holding the run's row lock
    (`labelqueue.labels`, `labelqueue.undo`; SQLite's one writer anyway), so a read that sees
    one sees every one before it. Invalid for a cursor ahead of the run's answers; NotFound
    for an unknown run."""
    with reading(session):
        status = get_row(session, Run, run_id).status.value
        open_pairs = session.scalar(select(func.count()).select_from(QUERIES).where(
            QUERIES.c.run_id == run_id, QUERIES.c.gold.is_(False),
            QUERIES.c.status.in_((QueryStatus.PENDING, QueryStatus.LEASED)))) or 0
        last_label = session.scalar(select(func.coalesce(func.max(Label.id), 0))
                                    .where(Label.run_id == run_id)) or 0
        last_withdrawal = session.scalar(select(func.coalesce(func.max(Withdrawal.id), 0))
                                         .where(Withdrawal.run_id == run_id)) or 0
        if cursor.label > last_label or cursor.withdrawal > last_withdrawal:
            raise Invalid(f"cursor {cursor} is ahead of run {run_id}'s answers (its newest "
                             f"is {last_label}.{last_withdrawal})")
        labels = session.execute(
            select(Label, Labeller.name).join(Labeller, Labeller.id == Label.labeller_id)
            .where(Label.run_id == run_id, Label.id > cursor.label,
                   Label.practice.is_(False))
            .order_by(Label.id).limit(limit)).all()
        label_to = labels[-1][0].id if len(labels) == limit else max(
            [cursor.label, *(label.id for label, _ in labels)])
        withdrawals = session.execute(
            select(Withdrawal, Label, Labeller.name)
            .join(Label, Label.id == Withdrawal.label_id)
            .join(Labeller, Labeller.id == Label.labeller_id)
            .where(Withdrawal.run_id == run_id, Withdrawal.id > cursor.withdrawal,
                   Label.practice.is_(False))
            .order_by(Withdrawal.id).limit(limit)).all()
        withdrawal_to = max([cursor.withdrawal, *(w.id for w, _, _ in withdrawals)])
        touched = {label.query_id for label, _ in labels} | {
            label.query_id for _, label, _ in withdrawals}
        state = _pair_states(session, touched)
    events: list[dict[str, Any]] = []
    given = set()
    for label, name in labels:
        if label.withdrawn_at is not None:
            continue  # taken back before anyone read it
        given.add(label.id)
        events.append({"kind": "answer", "label_id": label.id, "labeller_id": label.labeller_id,
                       "labeller": name, "answer": label.answer.value,
                       "at": label.answered_at.isoformat(),
                       "flag": None if label.flag is None else label.flag.value,
                       **state[label.query_id]})
    for withdrawal, label, name in withdrawals:
        if label.id > cursor.label and label.id not in given:
            continue  # its answer was never given (read as taken back): nor is its withdrawal
        events.append({"kind": "withdrawal", "label_id": label.id,
                       "labeller_id": label.labeller_id, "labeller": name,
                       "answer": label.answer.value, "at": withdrawal.withdrawn_at.isoformat(),
                       "flag": None, **state[label.query_id]})
    events.sort(key=lambda event: event["at"])
    return Feed(events=events, cursor=Cursor(label_to, withdrawal_to), open_pairs=open_pairs,
                status=status)


def _pair_states(session: Session, query_ids: set[int]) -> dict[int, dict[str, Any]]:
    """Per query: its key, meta, gold, k, and its standing answers with their tally."""
    if not query_ids:
        return {}
    pairs = session.execute(
        select(Query.id, Query.needs_labels, Query.gold, ExternalPair.key, ExternalPair.meta)
        .outerjoin(ExternalPair, ExternalPair.query_id == Query.id)
        .where(Query.id.in_(query_ids))).all()
    standing = session.execute(
        select(Label.query_id, Label.labeller_id, Labeller.name, Label.answer)
        .join(Labeller, Labeller.id == Label.labeller_id)
        .where(Label.query_id.in_(query_ids), Label.withdrawn_at.is_(None),
               Label.practice.is_(False))
        .order_by(Label.id)).all()
    answers: dict[int, list[Any]] = {}
    for row in standing:
        answers.setdefault(row.query_id, []).append(row)
    out = {}
    for pair in pairs:
        given = answers.get(pair.id, [])
        agreed, tie = tally([Answer(row.answer) for row in given])
        out[pair.id] = {
            "query_id": pair.id, "key": pair.key, "meta": pair.meta, "gold": pair.gold,
            "k": None if pair.gold else pair.needs_labels,
            "answers": [{"labeller_id": row.labeller_id, "labeller": row.name,
                         "answer": Answer(row.answer).value} for row in given],
            "aggregate": agreed.value if given else None, "tie": tie,
            "complete": not pair.gold and len(given) >= pair.needs_labels}
    return out
