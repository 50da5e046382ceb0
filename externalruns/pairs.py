"""Pairs an external client pushes (`push_pairs`): checked against the clips it uploaded and
the run's budget, stored as the run's queries with their hidden metadata beside them, under an
idempotency key unique in the run; withdrawn while nobody has answered them (`withdraw_pair`);
and which uploaded clips a run's pairs use (`clip_use`), or used only in withdrawn pairs
(`withdrawn_clips`)."""

from __future__ import annotations

import hashlib
import json
import math
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import func, insert, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from externalruns.runs import is_external
from labelqueue.errors import Conflict, Invalid, NotFound
from labelqueue.models import (
    EXTERNAL_PAIRS,
    QUERIES,
    ExternalPair,
    QueryStatus,
    Run,
    RunStatus,
    utcnow,
)
from labelqueue.practice import reserve
from labelqueue.queries import checked_query_fields
from labelqueue.runs import EXTERNAL
from labelqueue.transaction import changed, reading, transaction
from runvocab.answers import Answer
from runvocab.clip_format import ClipInfo

KEY_MAX = 200
"""the longest idempotency key"""
META_MAX_BYTES = 4096
"""the most a pair's hidden metadata may hold, as JSON"""
SECONDS_APART = 0.05
"""how much the two clips of a pair may differ in length (the label page plays them on one
clock, in seconds)"""

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


_SHOWN = QUERIES.c.status != QueryStatus.CANCELLED
"""a pair that is not withdrawn (only a withdrawal cancels an external run's query)"""


def clip_use(session: Session) -> dict[int, ClipUse]:
    """Per external run: its status and the ids of the uploaded clips its pairs name (its
    withdrawn pairs name none)."""
    with reading(session):
        statuses = dict(session.execute(select(Run.id, Run.status).where(Run.algo == EXTERNAL))
                        .tuples().all())
        named = session.execute(
            select(QUERIES.c.run_id, QUERIES.c.first_clip, QUERIES.c.second_clip)
            .where(QUERIES.c.run_id.in_(list(statuses)), QUERIES.c.rule == EXTERNAL,
                   _SHOWN)).all()
    ids: dict[int, set[str]] = {run_id: set() for run_id in statuses}
    for run_id, *keys in named:
        ids[run_id].update(key.rpartition("/")[2].partition(".")[0] for key in keys if key)
    return {run_id: ClipUse(RunStatus(status), frozenset(ids[run_id]))
            for run_id, status in statuses.items()}


def withdrawn_clips(session: Session, *, run_id: int, query_id: int) -> list[str]:
    """The storage keys of the clips of the run's withdrawn pair `query_id` that no pair of
    the run still shows (none while the pair is not withdrawn)."""
    with reading(session):
        pair = session.execute(
            select(QUERIES.c.first_clip, QUERIES.c.second_clip).where(
                QUERIES.c.id == query_id, QUERIES.c.run_id == run_id,
                QUERIES.c.rule == EXTERNAL, QUERIES.c.status == QueryStatus.CANCELLED)).first()
        keys = {key for key in pair or () if key}
        shown = session.execute(
            select(QUERIES.c.first_clip, QUERIES.c.second_clip).where(
                QUERIES.c.run_id == run_id, _SHOWN,
                or_(QUERIES.c.first_clip.in_(keys), QUERIES.c.second_clip.in_(keys)))).all()
    return sorted(keys - {key for row in shown for key in row})


def _check_uploaded(index: int, pair: PairSpec, clips: Mapping[str, ClipInfo]) -> None:
    """Invalid for a new pair naming a clip not uploaded (a stored pair's clips may be gone:
    a withdrawal deletes them, and its key answers a push all the same)."""
    for side, clip in (("first_clip", pair.first_clip), ("second_clip", pair.second_clip)):
        if clip not in clips:
            raise Invalid(f"pairs[{index}] ({pair.key!r}): {side} {clip!r} is no clip "
                          "uploaded to this run")


def _check_pair(index: int, pair: PairSpec, clips: Mapping[str, ClipInfo]) -> None:
    where = f"pairs[{index}] ({pair.key!r})"
    if not 1 <= len(pair.key) <= KEY_MAX:
        raise Invalid(f"{where}: key must be 1-{KEY_MAX} characters")
    # A missing clip is refused once the pair is known to be new (`_check_uploaded`).
    first, second = clips.get(pair.first_clip), clips.get(pair.second_clip)
    if first is not None and second is not None:
        if (first.width, first.height, first.frames) != (second.width, second.height,
                                                         second.frames):
            raise Invalid(
                f"{where}: the two clips differ in shape: {first.width}x{first.height}, "
                f"{first.frames} frames against {second.width}x{second.height}, "
                f"{second.frames} frames (the label page plays them side by side on one clock)")
        if abs(first.seconds - second.seconds) > SECONDS_APART:
            raise Invalid(
                f"{where}: the two clips last {first.seconds:.2f} s and {second.seconds:.2f} s "
                f"(another frame rate); the label page plays them side by side on one clock, "
                f"so they must last as long, within {SECONDS_APART} s")
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
    if pair.meta is not None and len(json.dumps(pair.meta, ensure_ascii=False).encode(
            errors="surrogatepass")) > META_MAX_BYTES:
        raise Invalid(f"{where}: meta is larger than {META_MAX_BYTES} bytes as JSON")


def push_pairs(session: Session, *, run_id: int, pairs: Sequence[PairSpec],
               clips: Mapping[str, ClipInfo]) -> list[Pushed]:
    """Store the pairs as queries of the external run, all or none; one `Pushed` per pair, in
    order. `clips`: what the uploaded clips the pairs name hold (`runvocab.clip_format.ClipInfo`).

    Invalid naming the pair for a new pair's missing clip (a stored pair pushed again is
    answered though a withdrawal deleted its clips), two clips of different shapes or lengths
    in seconds, a gold
    answer that is neither first nor second or contradicts the returns, or a key used twice in
    the push; Conflict for a key stored with other content, a run that is no external run or
    takes no answers, or pairs beyond the budget. Nothing is stored on any refusal. Pushes to
    one run take turns on its row lock, so two at once (a retry racing its first try) store
    each key once.
    """
    keys = Counter(pair.key for pair in pairs)
    for index, pair in enumerate(pairs):
        _check_pair(index, pair, clips)
        if keys[pair.key] > 1:
            raise Invalid(f"pairs[{index}]: key {pair.key!r} is used twice in this push")
    digests = [pair.digest() for pair in pairs]
    try:
        return _store(session, run_id=run_id, pairs=pairs, digests=digests, clips=clips)
    except IntegrityError as error:  # the run's lock makes this rare: a safety net
        raise Conflict(f"another push to run {run_id} stored some of these keys at the same "
                       "time: push again (a stored key is not stored twice)") from error


def _store(session: Session, *, run_id: int, pairs: Sequence[PairSpec], digests: list[str],
           clips: Mapping[str, ClipInfo]) -> list[Pushed]:
    with transaction(session):
        # Pushes to one run take turns on its row (PostgreSQL; SQLite writes one at a time):
        # each reads the stored keys, the budget and the last position after the one before.
        run = session.scalars(select(Run).where(Run.id == run_id).with_for_update()
                              .execution_options(populate_existing=True)).first()
        if run is None:
            raise NotFound(f"run {run_id} does not exist")
        if not is_external(run):
            raise Conflict(f"run {run_id} is trained by a worker: pairs are pushed to an "
                           "external run only")
        if run.status not in (RunStatus.RUNNING, RunStatus.PAUSED):
            raise Conflict(f"run {run_id} is {run.status.value}: it takes no more pairs")
        stored = {row.key: row for row in session.execute(
            select(EXTERNAL_PAIRS.c.key, EXTERNAL_PAIRS.c.digest, EXTERNAL_PAIRS.c.query_id)
            .where(EXTERNAL_PAIRS.c.run_id == run_id,
                   EXTERNAL_PAIRS.c.key.in_([pair.key for pair in pairs])))}
        for pair, digest in zip(pairs, digests, strict=True):
            row = stored.get(pair.key)
            if row is not None and row.digest != digest:
                raise Conflict(f"key {pair.key!r} was pushed before with other content (query "
                               f"{row.query_id}): a new pair needs a new key")
        new = []
        for index, (pair, digest) in enumerate(zip(pairs, digests, strict=True)):
            if pair.key not in stored:
                _check_uploaded(index, pair, clips)
                new.append((pair, digest))
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
    fields = checked_query_fields({
        "round": 0, "position": position, "segment_length": first.frames,
        "first_trajectory": 2 * position, "first_start": 0,
        "second_trajectory": 2 * position + 1, "second_start": 0,
        "first_clip": clip_key(run_id, pair.first_clip, first.container),
        "second_clip": clip_key(run_id, pair.second_clip, second.container),
        "rule": EXTERNAL, "gold": pair.gold is not None, "needs_labels": k, **truth})
    return fields | {"run_id": run_id, "status": QueryStatus.PENDING, "created_at": now,
                     "practice": False}


def withdraw_pair(session: Session, *, run_id: int, query_id: int) -> str:
    """Withdraw one of the external run's pushed pairs that has no answer: its query is
    cancelled, as a closed round's are (`labelqueue.queries.cancel_queries`), so it is leased
    no more, a labeller who has it on screen is refused the answer (LeaseError), and the answers
    it asked of the budget are free again (`_check_budget`). Its key stays used, and its clips
    are no longer in use (`clip_use`, `withdrawn_clips`). Withdrawing a withdrawn pair changes
    nothing. The pair's key.

    NotFound for a query that is no pair the run's client pushed; Conflict for a pair with a
    standing answer (one of its k is enough: the answers stand, and the feed gave them), or
    one of the run's practice pairs (every newcomer is shown them). Decided by one conditional
    update of the query's row, which a submit takes too: an answer and a withdrawal at once
    never both succeed."""
    with transaction(session):
        changed(session, update(QUERIES).where(
            QUERIES.c.id == query_id, QUERIES.c.run_id == run_id,
            QUERIES.c.status.in_((QueryStatus.PENDING, QueryStatus.LEASED)),
            QUERIES.c.label_count == 0, QUERIES.c.practice.is_(False),
            select(EXTERNAL_PAIRS.c.query_id).where(
                EXTERNAL_PAIRS.c.query_id == QUERIES.c.id).exists(),
        ).values(status=QueryStatus.CANCELLED, lease_holder=None, lease_expires_at=None,
                 leased_at=None))
        row = session.execute(
            select(EXTERNAL_PAIRS.c.key, QUERIES.c.status, QUERIES.c.label_count,
                   QUERIES.c.needs_labels, QUERIES.c.gold, QUERIES.c.practice)
            .join(QUERIES, QUERIES.c.id == EXTERNAL_PAIRS.c.query_id)
            .where(EXTERNAL_PAIRS.c.query_id == query_id, EXTERNAL_PAIRS.c.run_id == run_id)
        ).first()
        if row is None:
            raise NotFound(f"run {run_id} has no pair of query id {query_id}")
        where = f"pair {row.key!r} (query {query_id})"
        if row.status == QueryStatus.CANCELLED:
            return str(row.key)
        if row.practice:
            raise Conflict(f"{where} is one of the run's practice pairs, shown to every "
                           "newcomer: it cannot be withdrawn")
        of = "" if row.gold else f" of the {row.needs_labels} it asks for"
        raise Conflict(f"{where} has {row.label_count} answer(s){of}: a pair with an answer "
                       "cannot be withdrawn (its answers stand, and the feed gives them)")


def known_answer(session: Session, *, query_id: int) -> Answer | None:
    """A gold pair's answer as its external client gave it (none for any other pair)."""
    with reading(session):
        row = session.get(ExternalPair, query_id, populate_existing=True)
        return None if row is None or row.gold_answer is None else Answer(row.gold_answer)
