"""The bodies of external runs (`externalruns`): a run no worker trains, the clips and
pairs its client pushes, and the answers it reads back."""

from __future__ import annotations

import math
import re
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, Field

from server.schemas import INT32_MAX, Body, FilledText, InstructionText, Out, SmallJson


def _finite(values: tuple[float, float] | None) -> tuple[float, float] | None:
    if values is not None and not all(math.isfinite(v) for v in values):
        raise ValueError("returns must be finite numbers")
    return values


NO_NUL = r"^[^\x00]*$"
"""text without NUL characters: PostgreSQL stores none in text, JSON included"""


def _no_nul(text: str) -> str:
    if "\x00" in text:
        raise ValueError("the key holds a NUL character (\\u0000), which no text can store")
    return text


SURROGATE = re.compile("[\ud800-\udfff]")
"""a lone surrogate, as JSON's "\\ud800" escape makes one: no character, so no UTF-8 has it
(stored in meta, it would fail every read of its pair's answers)"""


def _unstorable_text(text: str) -> str | None:
    """What in `text` no database stores, in words; None for text without it."""
    if "\x00" in text:
        return "a NUL character (\\u0000), which no text can store"
    if SURROGATE.search(text):
        return "a lone surrogate (\\ud800-\\udfff), which is no character UTF-8 can store"
    return None


def _storable(value: Any, where: str = "meta") -> None:
    """ValueError naming the place of a number that is not finite (JSON has no NaN or
    Infinity: it was stored as null on SQLite, refused as out of range on PostgreSQL), or of
    a NUL character or a lone surrogate in a key or a string."""
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"{where} is {value}: numbers in meta must be finite")
    if isinstance(value, str) and (problem := _unstorable_text(value)):
        raise ValueError(f"{where} holds {problem}")
    if isinstance(value, dict):
        for key, item in value.items():
            if problem := _unstorable_text(key):
                raise ValueError(f"a key of {where} holds {problem}")
            _storable(item, f"{where}.{key}")
    elif isinstance(value, list):
        for index, item in enumerate(value):
            _storable(item, f"{where}[{index}]")


def _storable_meta(meta: dict[str, Any]) -> dict[str, Any]:
    _storable(meta)
    return meta


Returns = Annotated[tuple[float, float] | None, AfterValidator(_finite)]
PairKey = Annotated[str, Field(min_length=1, max_length=200,
                               json_schema_extra={"pattern": NO_NUL}),
                    AfterValidator(_no_nul)]
"""a pair's idempotency key: 1-200 characters, no NUL"""
Meta = Annotated[SmallJson, AfterValidator(_storable_meta), Field(
    description="the client's own ids, hidden from labellers: at most 4096 bytes as JSON, "
                "finite numbers only, no NUL character (\\u0000) or lone surrogate "
                "(\\ud800-\\udfff) in a key or a string")]
ClipId = Annotated[str, Field(pattern=r"^[0-9a-f]{32}$",
                              description="an id `POST /api/runs/{id}/clips` gave")]


class ExternalRunCreate(Body):
    """A run no worker trains: a client holding its run token pushes its pairs."""

    task: FilledText = Field(min_length=1, max_length=100, examples=["gym:HalfCheetah-v5"])
    """what is being trained, in free text (the instruction's default names it)"""
    name: FilledText | None = Field(default=None, min_length=1, max_length=200)
    """defaults to `external: <task>`"""
    instruction: InstructionText | None = None
    """what labellers are told "better" means; null: a generic one from the task's name"""
    budget: int = Field(ge=1, le=INT32_MAX)
    """answers to ordinary pairs the run may take in all (gold and practice ones are free)"""
    labels_per_query: int = Field(default=1, ge=1, le=50)
    """k: distinct labellers' answers per pair, aggregated by majority"""
    gold_rate: float = Field(default=0.0, ge=0.0, le=0.5)
    """the share of each labeller's answers given to the gold pairs the client pushes"""
    gold_min_accuracy: float = Field(default=0.0, ge=0.0, le=1.0)
    """pause a labeller whose accuracy on gold pairs falls below this (0: never)"""
    gold_min_answers: int = Field(default=10, ge=1, le=10_000)
    practice_pairs: int = Field(default=0, ge=0, le=20)
    """a practice round of this many of the client's first gold pairs for each newcomer"""


class RunTokenOut(Out):
    run_id: int
    token: str
    """shown once: it pushes the run's pairs and reads its answers, and nothing else"""


class RunTokenInfo(Out):
    """One of an external run's tokens, without its secret (shown once, when it was made)."""

    id: int
    """the number after `run.` in the token, as in `run.3.Xq...`"""
    run_id: int
    created_at: datetime
    revoked_at: datetime | None
    """when an operator revoked it: it reaches nothing since; null for a live token"""


class ClipOut(Out):
    """An uploaded clip, as the decoder read it."""

    clip_id: str
    container: Literal["mp4", "webm"]
    codec: str
    width: int
    height: int
    frames: int
    seconds: float


class PairIn(Body):
    """One pair of uploaded clips to compare."""

    key: PairKey
    """the idempotency key, unique in the run: a pair pushed again under it is not stored
    twice; other content under a used key is a 409"""
    first_clip: ClipId
    second_clip: ClipId
    gold: Literal["first", "second"] | None = None
    """a gold pair's known answer; null: an ordinary pair"""
    returns: Returns = None
    """hidden: the two segments' true returns, for accuracy and the calibration report"""
    trajectory_returns: Returns = None
    """hidden: their whole episodes' returns; null: `returns`"""
    meta: Meta | None = None
    """hidden: the client's own ids, given back with the pair's answers"""


class PairsIn(Body):
    pairs: list[PairIn] = Field(min_length=1, max_length=500)


class PushedOut(Out):
    key: str
    query_id: int
    created: bool
    """false: the key was stored before (a retried push), and this is its query"""


class PushOut(Out):
    pairs: list[PushedOut]


class GivenAnswer(Out):
    labeller_id: int
    labeller: str
    answer: str


class PairState(Out):
    """One of the run's pairs as it stands: its standing answers and their tally."""

    query_id: int
    key: str | None
    meta: dict[str, Any] | None
    gold: bool
    k: int | None
    """answers the pair takes (null for a gold pair: everyone's)"""
    answers: list[GivenAnswer]
    """the pair's standing answers, one per labeller"""
    aggregate: str | None
    """their majority (`runvocab.answers.aggregate`): cant_tell when most cannot tell or two
    decisive answers tie; skip when every one is a skip; null with no answer standing"""
    tie: bool
    """two decisive answers tie for the most"""
    complete: bool
    """the pair has its k answers (skips count: the queue asks no more); never for a gold
    pair, which takes the answer of everyone it is shown to"""
    withdrawn: bool
    """its client withdrew it before anyone answered it: it is shown to nobody again and gets
    no answer"""


class AnswerEvent(PairState):
    """An answer to one of the run's pairs, or an answer taken back, with the pair as it
    stands now."""

    kind: Literal["answer", "withdrawal"]
    label_id: int
    labeller_id: int
    labeller: str
    answer: str
    """first, second, equal, cant_tell or skip (for a withdrawal: the answer taken back)"""
    at: datetime
    flag: str | None


class PairStatesOut(Out):
    pairs: list[PairState]
    """the pairs found, in the order of the keys asked for"""
    unknown: list[str]
    """the keys asked for that no pair of the run has"""


class AnswersOut(Out):
    events: list[AnswerEvent]
    cursor: str
    """pass it as `after` to read on from here (keep it: it resumes after a crash)"""
    open_pairs: int
    """ordinary pairs still short of their k answers"""
    status: str
    """the run's status"""
