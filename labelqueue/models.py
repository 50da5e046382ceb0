"""The queue database's tables: labellers, runs, workers, queries, labels, metrics.

Enumerated columns are VARCHAR with a named CHECK constraint, not native PostgreSQL enums: adding
a value later alters a constraint the same way on both databases. Times are UTC and come back
timezone-aware from either database. Defaults are set in Python, not by the database, so an
inserted row is complete in memory and reading it never opens a new transaction.
"""

from __future__ import annotations

from datetime import UTC, datetime
from enum import StrEnum
from typing import Any, cast

from sqlalchemy import (
    JSON,
    Boolean,
    DateTime,
    Dialect,
    Enum,
    Float,
    ForeignKey,
    Index,
    Integer,
    MetaData,
    String,
    Table,
    Text,
    TypeDecorator,
    UniqueConstraint,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

from runvocab.answers import Answer, Click, Flag


class Role(StrEnum):
    LABELLER = "labeller"
    OPERATOR = "operator"


class RunStatus(StrEnum):
    QUEUED = "queued"
    RUNNING = "running"
    PAUSED = "paused"
    STOPPING = "stopping"
    STOPPED = "stopped"
    FINISHED = "finished"
    FAILED = "failed"


class TeacherKind(StrEnum):
    HUMAN = "human"
    SCRIPTED = "scripted"


class QueryStatus(StrEnum):
    PENDING = "pending"
    LEASED = "leased"
    LABELLED = "labelled"
    CANCELLED = "cancelled"


class LabelSource(StrEnum):
    """Who answered: a person, or a scripted teacher (the run's own, or a simulated crowd)."""

    HUMAN = "human"
    SCRIPTED = "scripted"


class MetricStream(StrEnum):
    EPISODES = "episodes"
    EVAL = "eval"
    ROUNDS = "rounds"


def utcnow() -> datetime:
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator[datetime]):
    """A timezone-aware UTC datetime on every backend (SQLite keeps no offset of its own)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        value = value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)
        # SQLite stores the text as given; one fixed offset keeps comparisons in SQL correct.
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


def _enum(cls: type[StrEnum], name: str) -> Enum:
    # Store the values ("running"), not the member names ("RUNNING").
    return Enum(
        cls,
        name=name,
        native_enum=False,
        create_constraint=True,
        length=16,
        values_callable=lambda members: [m.value for m in members],
        validate_strings=True,
    )


class Base(DeclarativeBase):
    # Named constraints, so Alembic's batch mode on SQLite can find and alter them later.
    metadata = MetaData(
        naming_convention={
            "ix": "ix_%(column_0_label)s",
            "uq": "uq_%(table_name)s_%(column_0_N_name)s",
            "ck": "ck_%(table_name)s_%(constraint_name)s",
            "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
            "pk": "pk_%(table_name)s",
        }
    )


SCRIPTED_TEACHER = "scripted-teacher"
"""the labeller the runs' scripted teacher answers as (made by the first worker that needs it)"""


class Labeller(Base):
    """A person (or a scripted teacher) who answers queries; operators also manage runs."""

    __tablename__ = "labellers"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(100), unique=True)
    role: Mapped[Role] = mapped_column(_enum(Role, "role"))
    token_hash: Mapped[str] = mapped_column(String(64))
    """sha256 hex of the bearer token `"<id>.<secret>"`; the token itself is never stored"""
    active: Mapped[bool] = mapped_column(Boolean, default=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


class Run(Base):
    """One training run: what to train, who teaches it, and where it stands."""

    __tablename__ = "runs"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(200))
    task: Mapped[str] = mapped_column(String(100))
    algo: Mapped[str] = mapped_column(String(50))
    preset: Mapped[str] = mapped_column(String(50))
    seed: Mapped[int] = mapped_column(Integer)
    config: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    """overrides of the preset, as the trainer's CLI flags name them (`{"sac.lr": 1e-4}`)"""
    resolved_config: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    """the configuration the run trains with, resolved from the presets, `config` and the
    top-level fields when it was created (`runvocab.config.to_dict`); none: a run stored before
    migration 0015, resolved when read (`labelqueue.run_config`)"""
    teacher: Mapped[TeacherKind] = mapped_column(_enum(TeacherKind, "teacher"))
    teacher_params: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    budget: Mapped[int] = mapped_column(Integer)
    """answers the run may ask for in all"""
    labels_used: Mapped[int] = mapped_column(Integer, default=0)
    step: Mapped[int] = mapped_column(Integer, default=0)
    progress: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    """the worker's latest summary (last return, round, ...), for the dashboard"""
    status: Mapped[RunStatus] = mapped_column(_enum(RunStatus, "status"), index=True)
    worker_id: Mapped[str | None] = mapped_column(String(200))
    heartbeat_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    error: Mapped[str | None] = mapped_column(Text)
    instruction: Mapped[str | None] = mapped_column(Text)
    """the operator's instruction to labellers; none: the task's own (`runvocab.instructions`)"""
    clip_size: Mapped[str | None] = mapped_column(String(16))
    """the size clips are rendered at ("256x256", `runvocab.clip_format`); none: the default"""
    grid_key: Mapped[str | None] = mapped_column(String(300), unique=True, index=True)
    """an experiment's run: `<spec name>/<run folder>` (`experiments.spec`), unique, so a grid
    enqueued again adds nothing; its worker trains it in `<results>/<grid key>`"""
    dataset: Mapped[str | None] = mapped_column(String(1000))
    """a labelling-only run: the dataset export its pairs are drawn from (its folder, as the
    workers reach it; `rundata.labelling`); none: a training run"""


class RunInstruction(Base):
    """The instruction a run showed from `set_at` on, as its full text: what a label was given
    under is the newest row not after its answer."""

    __tablename__ = "run_instructions"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id"), index=True)
    text: Mapped[str] = mapped_column(Text)
    sha256: Mapped[str] = mapped_column(String(64))
    custom: Mapped[bool] = mapped_column(Boolean)
    """whether an operator wrote it (false: the task's default instruction)"""
    set_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


class Invite(Base):
    """A link that lets people join as labellers without a token from an operator."""

    __tablename__ = "invites"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    code: Mapped[str] = mapped_column(String(64), unique=True)
    """the secret part of the link `/join/<code>`"""
    run_id: Mapped[int | None] = mapped_column(ForeignKey("runs.id"))
    """the one run its labellers are sent to; none: all runs"""
    note: Mapped[str | None] = mapped_column(String(200))
    """the operator's name for it ("pilot study, batch 2")"""
    expires_at: Mapped[datetime] = mapped_column(UTCDateTime)
    max_uses: Mapped[int | None] = mapped_column(Integer)
    """labellers it may create; none: no limit"""
    uses: Mapped[int] = mapped_column(Integer, default=0)
    target_answers: Mapped[int | None] = mapped_column(Integer)
    """answers after which a labeller is shown `completion_code`; none: no target"""
    completion_code: Mapped[str | None] = mapped_column(String(64))
    """the study's code (a platform's): the prefix of each participant's own completion code
    (`crowdstudy.completion.participant_code`); none: their own part alone"""
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    revoked_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    redirect_url: Mapped[str | None] = mapped_column(String(2000))
    """where a participant is sent once their study is complete (a platform's completion URL);
    `{participant}` and `{code}` in it are filled in"""
    consent_text: Mapped[str | None] = mapped_column(Text)
    """shown on the invite's page before joining: nobody joins without agreeing to it"""
    pause_message: Mapped[str | None] = mapped_column(Text)
    """what a participant paused by check pairs is told instead of being given their code;
    none: they get their code"""
    wait_limit_s: Mapped[int | None] = mapped_column(Integer)
    """after asking this long for a pair and getting none, a participant may finish with their
    code ("nothing left to label"); none: `crowdstudy.invites.WAIT_LIMIT_S`"""
    entry_pass: Mapped[int | None] = mapped_column(Integer)
    """an entry test: the practice answers a participant must get right, of the run's
    `feedback.practice_pairs`, to go on (`labelqueue.entry_test`); none: no test"""


class Invitee(Base):
    """A labeller who joined by an invite link."""

    __tablename__ = "invitees"

    labeller_id: Mapped[int] = mapped_column(ForeignKey("labellers.id"), primary_key=True)
    invite_id: Mapped[int] = mapped_column(ForeignKey("invites.id"), index=True)
    participant: Mapped[str | None] = mapped_column(String(100))
    """the `participant` the link was opened with (a crowdsourcing platform's worker id); one
    labeller per participant and invite (joining again returns it)"""
    joined_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    asked_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    """when the participant last asked for a pair (`labelqueue.waiting`)"""
    waiting_since: Mapped[datetime | None] = mapped_column(UTCDateTime)
    """since when they have asked without getting a pair, asking at least every
    `labelqueue.waiting.GAP_S`; none while they have one"""
    nothing_left_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    """when they had waited the invite's `wait_limit_s` with nothing to label: their study is
    complete from then on ("nothing left to label")"""
    completed_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    """when their study was first found complete with a code: it stays complete from then on,
    why `completed_why` says, whatever their runs do later (`crowdstudy.completion`)"""
    completed_why: Mapped[str | None] = mapped_column(String(20))
    entry_passed: Mapped[bool | None] = mapped_column(Boolean)
    """the invite's entry test, once decided (all practice pairs answered): passed, or failed
    and let go without a code; none: undecided, or no test (`labelqueue.entry_test`)"""
    entry_correct: Mapped[int | None] = mapped_column(Integer)
    """practice answers they got right when the entry test was decided"""


Index("ix_invitees_invite_id_participant", Invitee.invite_id, Invitee.participant)


class Worker(Base):
    """A trainer process, as last seen: lets an operator tell idle workers from dead ones."""

    __tablename__ = "workers"

    id: Mapped[str] = mapped_column(String(200), primary_key=True)
    run_id: Mapped[int | None] = mapped_column(ForeignKey("runs.id"))
    host: Mapped[str | None] = mapped_column(String(200))
    """the host the worker last reported from"""
    first_seen_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    last_seen_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


class ServerKey(Base):
    """A secret the server keeps in its database, made on first use, so every process and host
    sharing the database uses the same one (`labelqueue.keys`): never shown to labellers."""

    __tablename__ = "server_keys"

    name: Mapped[str] = mapped_column(String(64), primary_key=True)
    value: Mapped[str] = mapped_column(String(128))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


class Query(Base):
    """A pair of segments to compare, with provenance, clips and hidden ground truth.

    "first" and "second" are the trainer's segment 0 and 1; which one a labeller sees on the
    left is decided per label. The returns are ground truth for scripted teachers and accuracy
    statistics and must never reach a labeller's browser.
    """

    __tablename__ = "queries"
    __table_args__ = (UniqueConstraint("run_id", "round", "position"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id"))
    round: Mapped[int] = mapped_column(Integer)
    position: Mapped[int] = mapped_column(Integer)
    """index of the query within its round"""
    step: Mapped[int | None] = mapped_column(Integer)
    """training step at which the query was selected"""
    segment_length: Mapped[int] = mapped_column(Integer)

    first_trajectory: Mapped[int] = mapped_column(Integer)
    first_start: Mapped[int] = mapped_column(Integer)
    first_skill: Mapped[list[float] | None] = mapped_column(JSON)
    first_clip: Mapped[str | None] = mapped_column(String(500))
    """storage key of the rendered clip, relative to the clips folder"""
    # The four returns are null only for an external client's pair pushed without them.
    first_segment_return: Mapped[float | None] = mapped_column(Float)
    first_trajectory_return: Mapped[float | None] = mapped_column(Float)

    second_trajectory: Mapped[int] = mapped_column(Integer)
    second_start: Mapped[int] = mapped_column(Integer)
    second_skill: Mapped[list[float] | None] = mapped_column(JSON)
    second_clip: Mapped[str | None] = mapped_column(String(500))
    second_segment_return: Mapped[float | None] = mapped_column(Float)
    second_trajectory_return: Mapped[float | None] = mapped_column(Float)

    model_p: Mapped[float | None] = mapped_column(Float)
    """the reward model's P[second preferred] at selection time"""
    score: Mapped[float | None] = mapped_column(Float)
    """the selection score (none for uniform picks)"""
    rule: Mapped[str | None] = mapped_column(String(50))
    """the selection rule that picked the pair"""
    shadow_choice: Mapped[Answer | None] = mapped_column(
        _enum(Answer, "shadow_choice"), nullable=True
    )
    """the run's scripted teacher's answer (hidden): compared with people's and the model's"""
    distinguishable: Mapped[bool | None] = mapped_column(Boolean)
    """whether the scripted teacher can tell the pair apart (hidden)"""
    r_avg: Mapped[float | None] = mapped_column(Float)
    """R_avg when the pair was selected, the scale of the noisy teacher's band (hidden)"""

    needs_labels: Mapped[int] = mapped_column(Integer, default=1)
    """distinct labellers' answers wanted: the run's `feedback.labels_per_query` (a gold pair
    takes every labeller's, `GOLD_NEEDS_LABELS`)"""
    gold: Mapped[bool] = mapped_column(Boolean, default=False)
    """a known-answer pair (`labelqueue.gold`): answered to measure labellers, never trained on
    and never counted against the budget; its answer is the segment with the larger return"""
    practice: Mapped[bool] = mapped_column(Boolean, default=False)
    """one of the run's practice pairs (`labelqueue.practice`), reserved from its first gold
    pairs: shown to every newcomer at once, never leased, never a check pair"""
    label_count: Mapped[int] = mapped_column(Integer, default=0)
    status: Mapped[QueryStatus] = mapped_column(_enum(QueryStatus, "status"))
    lease_holder: Mapped[int | None] = mapped_column(ForeignKey("labellers.id"), index=True)
    lease_expires_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    leased_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    """when the current lease was taken (a renewal keeps it); a label's shown_at is not earlier"""
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


# The lease scan: open queries of a run, oldest first.
Index("ix_queries_run_id_status", Query.run_id, Query.status, Query.id)
# The lease's two looks, for a gold pair and for any other: every lease makes both, and most
# runs have no gold pairs, which without `gold` in the index meant reading every open query.
Index("ix_queries_run_id_gold_status", Query.run_id, Query.gold, Query.status, Query.id)


class Label(Base):
    """One labeller's answer to one query. An answer taken back (undo) stays, withdrawn: the
    labeller may answer the query again, and the trainer never takes a withdrawn label."""

    __tablename__ = "labels"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    query_id: Mapped[int] = mapped_column(ForeignKey("queries.id"))
    # Copied from the query so the trainer's consume scan needs no join.
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id"))
    labeller_id: Mapped[int] = mapped_column(ForeignKey("labellers.id"))
    answer: Mapped[Answer] = mapped_column(_enum(Answer, "answer"))
    """the answer in segment terms (`runvocab.answers`)"""
    choice: Mapped[Click] = mapped_column(_enum(Click, "choice"))
    """what was clicked, in screen terms"""
    left_is_first: Mapped[bool] = mapped_column(Boolean)
    """the sides the server chose: whether the first segment was shown on the left"""
    source: Mapped[LabelSource] = mapped_column(_enum(LabelSource, "source"))
    shown_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    answered_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    consumed_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    """when the trainer took the label; none until then"""
    withdrawn_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    """when the labeller took the answer back (`labelqueue.undo`); none for a standing label"""
    flag: Mapped[Flag | None] = mapped_column(_enum(Flag, "flag"))
    """the labeller flagged the pair as broken (`runvocab.answers.Flag`); only with a skip, so
    this answer is never trained on (other labellers' answers to the pair may be); none for an
    unflagged answer"""
    flag_note: Mapped[str | None] = mapped_column(Text)
    """the labeller's optional words on the flag"""
    practice: Mapped[bool] = mapped_column(Boolean, default=False)
    """an answer of the labeller's practice round on the run (`labelqueue.practice`): a gold
    pair, explained once answered, not counted in gold accuracy"""


Index("ix_labels_run_id_consumed_at", Label.run_id, Label.consumed_at)
# One standing answer per labeller and query; withdrawn ones beside it.
_STANDING = Label.withdrawn_at.is_(None)
Index("uq_labels_query_id_labeller_id_standing", Label.query_id, Label.labeller_id, unique=True,
      sqlite_where=_STANDING, postgresql_where=_STANDING)


class RunToken(Base):
    """A bearer token scoped to one run (`externalruns`): it pushes the run's pairs and
    reads its answers, and nothing else. The token reads `"run.<id>.<secret>"`; only its sha256
    is stored."""

    __tablename__ = "run_tokens"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id"))
    token_hash: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    revoked_at: Mapped[datetime | None] = mapped_column(UTCDateTime)


class ExternalPair(Base):
    """What an external client pushed with one of its run's queries (`externalruns`):
    never shown to a labeller."""

    __tablename__ = "external_pairs"
    __table_args__ = (UniqueConstraint("run_id", "key"),)

    query_id: Mapped[int] = mapped_column(ForeignKey("queries.id"), primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id"))
    key: Mapped[str] = mapped_column(String(200))
    """the client's idempotency key: a push again under it returns the same query"""
    digest: Mapped[str] = mapped_column(String(64))
    """sha256 of what was pushed under the key: the same key with other content is refused"""
    meta: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    """the client's own hidden metadata (its ids), returned with the pair's answers"""
    gold_answer: Mapped[Answer | None] = mapped_column(_enum(Answer, "gold_answer"))
    """a gold pair's known answer (first or second); none: not gold, or known from its true
    returns"""


class Withdrawal(Base):
    """An answer taken back (`labelqueue.undo`), in the order they happened: the answers feed
    resumes after one as after an answer."""

    __tablename__ = "withdrawals"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    label_id: Mapped[int] = mapped_column(ForeignKey("labels.id"))
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id"))
    withdrawn_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


Index("ix_withdrawals_run_id", Withdrawal.run_id, Withdrawal.id)


class LabellerPause(Base):
    """A labeller kept from a run's queries because their accuracy on its gold pairs fell below
    the run's threshold (`labelqueue.gold`); their answers stay stored. An operator lifts it."""

    __tablename__ = "labeller_pauses"
    __table_args__ = (UniqueConstraint("run_id", "labeller_id"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id"))
    labeller_id: Mapped[int] = mapped_column(ForeignKey("labellers.id"))
    gold_answers: Mapped[int] = mapped_column(Integer)
    gold_correct: Mapped[int] = mapped_column(Integer)
    paused_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


class Metric(Base):
    """One row of a run's learning curve (an episode, an evaluation or a feedback round)."""

    __tablename__ = "metrics"
    # One row per (run, stream, step): a resumed run rewrites the steps it repeats.
    __table_args__ = (UniqueConstraint("run_id", "stream", "step"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id"))
    stream: Mapped[MetricStream] = mapped_column(_enum(MetricStream, "stream"))
    step: Mapped[int] = mapped_column(Integer)
    values: Mapped[dict[str, Any]] = mapped_column(JSON)


# The tables as SQLAlchemy Core sees them, for statements built once (the label API's hot path).
LABELLERS = cast(Table, Labeller.__table__)
RUNS = cast(Table, Run.__table__)
QUERIES = cast(Table, Query.__table__)
LABELS = cast(Table, Label.__table__)
PAUSES = cast(Table, LabellerPause.__table__)
INVITEES = cast(Table, Invitee.__table__)
INVITES = cast(Table, Invite.__table__)
EXTERNAL_PAIRS = cast(Table, ExternalPair.__table__)
