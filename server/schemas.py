"""The API's request and response bodies, separate from the ORM tables in `labelqueue.models`:
the types every body shares (whole numbers as the database holds them, ids, times, refusals)
and the operator's runs, labellers and statistics. The label API's bodies are in
`label_schemas`, a crowd study's in `study_schemas`, an external run's in `external_schemas`;
enumerations are the queue's own (`TeacherKind`, `Role`, `MetricStream`, ...).
"""

from __future__ import annotations

import functools
import json
import re
import typing
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from typing import Annotated, Any, Literal

from fastapi import Path
from fastapi import Query as QueryParam
from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, computed_field

from labelqueue.models import SCRIPTED_TEACHER, Role, TeacherKind
from runviews.activity import WorkerStateName
from runvocab.clip_format import CLIP_SIZES
from runvocab.config.schema import BOOL_WORDS, leaf_fields
from runvocab.instructions import MAX_CHARS as MAX_INSTRUCTION_CHARS
from runvocab.instructions import clean_instruction, run_instruction
from runvocab.names import ALGOS, SIZE_PRESETS, all_tasks, unknown, unknown_task
from runvocab.queued_run import WORKER_FIELDS
from runvocab.text import VISIBLE_CHAR, filled
from runvocab.validate import MAX_INT, choice_fields

INT32_MAX = 2**31 - 1
"""the largest value an INTEGER column holds on PostgreSQL: ids, budgets, seeds and steps"""
INT64_MAX = 2**63 - 1


def _whole(value: Any) -> Any:
    """A whole number as JSON Schema's `integer` takes one: 12 or 12.0, never `true` or
    `"12"`."""
    if isinstance(value, bool | str):
        raise ValueError("must be a whole number written as a JSON number (not text or a "
                         "boolean)")
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


# The bounds come before the validator, so that the OpenAPI states them as minimum and maximum.
StoredInt = Annotated[int, Field(ge=0, le=INT32_MAX), BeforeValidator(_whole)]
"""a seed or a budget, what an INTEGER column holds: `12` or `12.0`, never `true` or `"12"`"""
Positive = Annotated[int, Field(ge=1, le=INT32_MAX), BeforeValidator(_whole)]
CONFIG_MAX_BYTES = 16 * 1024
"""the most a run's `config` (or `teacher_params`) may take as JSON"""


def _small_json(value: dict[str, Any]) -> dict[str, Any]:
    size = len(json.dumps(value, default=str).encode())  # middleware.JSON_DEPTH_LIMIT bounds it
    if size > CONFIG_MAX_BYTES:
        raise ValueError(f"is {size} bytes as JSON; at most {CONFIG_MAX_BYTES} are stored")
    return value


_INT_TEXT = r"^-?[0-9]{1,9}$"
_FLOAT_TEXT = r"^-?[0-9]{1,9}(\.[0-9]{1,9})?$"


def _config_value(kind: Any, path: str) -> dict[str, Any]:
    """What JSON value a config field of this kind takes (`runvocab.config.parse_value`)."""
    if kind is bool:
        return {"anyOf": [{"type": "boolean"}, {"enum": [0, 1]},
                          {"enum": sorted(BOOL_WORDS)}]}
    if kind is int:
        return {"anyOf": [{"type": "integer", "minimum": -MAX_INT, "maximum": MAX_INT},
                          {"type": "string", "pattern": _INT_TEXT}]}
    if kind is float:
        return {"anyOf": [{"type": "number"}, {"type": "string", "pattern": _FLOAT_TEXT}]}
    if kind is str:
        choices = choice_fields().get(path)
        return {"type": "string"} if choices is None else {"enum": list(choices)}
    items = [_config_value(k, path) for k in typing.get_args(kind)]
    return {"type": "array", "prefixItems": items, "minItems": len(items),
            "maxItems": len(items)}


@functools.cache
def config_schema(prefix: str = "") -> dict[str, Any]:
    """The JSON Schema of a run's `config` (prefix ""), or of its teacher parameters (prefix
    "teacher.": the teacher's fields without it): the fields by name and the JSON each takes."""
    fields = {leaf.path.removeprefix(prefix): _config_value(leaf.kind, leaf.path)
              for leaf in leaf_fields()
              if leaf.path.startswith(prefix) and leaf.path not in WORKER_FIELDS}
    return {"propertyNames": {"enum": list(fields)}, "properties": fields}


CONFIG_RULES = ("Each field's own range and the rules between fields are checked as a worker "
                "would build the run: a 422 names the field.")

def _utc(value: datetime) -> datetime:
    try:
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)
    except OverflowError:
        raise ValueError("is out of range once converted to UTC") from None


# Path and query parameters, bounded so that no number reaches the database unchecked (422).
RunId = Annotated[int, Path(ge=1, le=INT32_MAX, description="the run's id")]
QueryId = Annotated[int, Path(ge=1, le=INT32_MAX, description="the query's id")]
LabellerId = Annotated[int, Path(ge=1, le=INT32_MAX, description="the labeller's id")]
RunFilter = Annotated[int | None, QueryParam(ge=1, le=INT32_MAX, description="one run only")]
AheadOf = Annotated[
    int | None,
    QueryParam(ge=1, le=INT32_MAX, description="the query being shown: keep it, lease one more"),
]
AfterStep = Annotated[
    int | None,
    QueryParam(ge=0, le=INT32_MAX, description="rows after this step only (leave it out for all)"),
]
Expires = Annotated[int | None, QueryParam(ge=0, le=INT64_MAX, description="unix seconds")]

SmallJson = Annotated[dict[str, Any], AfterValidator(_small_json)]
RunConfigJson = Annotated[SmallJson, Field(json_schema_extra=config_schema(),
                                           description=CONFIG_RULES)]
TeacherJson = Annotated[SmallJson, Field(json_schema_extra=config_schema("teacher."),
                                         description=CONFIG_RULES)]
DATE_TIME_PATTERN = (r"^[0-9]{4}-[0-9]{2}-[0-9]{2}[Tt ][0-9]{2}:[0-9]{2}:[0-9]{2}(\.[0-9]+)?"
                     r"([Zz]|[+-][0-9]{2}:[0-9]{2})$")
"""RFC 3339's date-time, with its offset (`2026-01-01T12:00:00Z`)"""


def _date_time(value: Any) -> Any:
    if not isinstance(value, str) or not re.match(DATE_TIME_PATTERN, value):
        raise ValueError("must be an RFC 3339 date-time with its offset, such as "
                         "2026-01-01T12:00:00Z (not a number or a time without its zone)")
    return value


UTCTime = Annotated[datetime, BeforeValidator(_date_time), AfterValidator(_utc)]
"""a date-time as text with its offset, read as UTC"""


class ErrorOut(BaseModel):
    """Every refusal's body."""

    detail: str


class InvalidOut(BaseModel):
    """A 422: FastAPI's list of `{loc, msg, type}` for a malformed request, or one sentence for
    a well-formed one the queue refuses."""

    detail: str | list[dict[str, Any]]


ERROR_TEXT: dict[int, str] = {
    400: "the body cannot be read as JSON (not UTF-8 text, or nested deeper than 64 levels)",
    401: "missing, invalid or revoked bearer token",
    403: "the caller's role may not do this, a labeller was revoked, or a clip URL's signature "
    "is invalid or expired",
    404: "no such run, query, labeller or clip",
    409: "the request contradicts the stored state (a taken name, a move the run's status "
    "forbids, a lease that ran out, a stopped run)",
    413: "the request body is larger than the server accepts (64 KiB by default; an external "
    "run's clip, `clip_upload_bytes`)",
    415: "the body's content type is not one the operation takes",
    422: "a malformed request, or values the queue refuses",
    429: "too many requests from this labeller or by this invite link: wait the seconds "
    "`Retry-After` says",
    503: "the queue database is damaged (SQLite's integrity check found it so): restore it from "
    "a backup",
}


Responses = dict[int | str, dict[str, Any]]


def errors(*codes: int, also: Responses | None = None) -> Responses:
    """OpenAPI `responses` for the refusals an operation can answer with (and `also`)."""
    refusals: Responses = {
        code: {"model": InvalidOut if code == 422 else ErrorOut, "description": ERROR_TEXT[code]}
        for code in codes
    }
    return (also or {}) | refusals


class Body(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Out(BaseModel):
    model_config = ConfigDict(from_attributes=True)


def _one_of(field: str, valid: Sequence[str],
            refusal: Callable[[str], str] | None = None) -> Callable[[str], str]:
    """A validator taking only `valid` values; a refusal names the field, the near miss and
    what is valid (`refusal`: a message of the value's own)."""
    def check(value: str) -> str:
        if value not in valid:
            raise ValueError(refusal(value) if refusal else unknown(field, value, valid))
        return value

    return check


TaskName = Annotated[str, AfterValidator(_one_of("task", all_tasks(), unknown_task)),
                     Field(json_schema_extra={"enum": list(all_tasks())},
                           examples=["dmc:cheetah_run"])]
AlgoName = Annotated[str, AfterValidator(_one_of("algo", ALGOS)),
                     Field(json_schema_extra={"enum": list(ALGOS)})]
PresetName = Annotated[str, AfterValidator(_one_of("preset", SIZE_PRESETS)),
                       Field(json_schema_extra={"enum": list(SIZE_PRESETS)})]
ClipSizeName = Annotated[str, AfterValidator(_one_of("clip_size", list(CLIP_SIZES))),
                         Field(json_schema_extra={"enum": list(CLIP_SIZES)})]
NO_NUL = r"^[^\x00]*$"
"""text without a NUL character: PostgreSQL's text holds none"""


def _no_nul(text: str) -> str:
    if "\x00" in text:
        raise ValueError("holds a NUL character (\\u0000), which no text can store")
    return text


PlainText = Annotated[str, AfterValidator(_no_nul), Field(json_schema_extra={"pattern": NO_NUL})]
"""free text a request stores (a name, a note, a message): any characters but NUL, refused
with a 422 naming the field (the database would refuse it, in words about numbers)"""

# What `clean_instruction` takes, stated in the schema: at most MAX_INSTRUCTION_CHARS characters,
# something besides white space, and no control character but tab and line ends (its own
# refusals name each problem).
_TEXT_CHAR = r"[^\x00-\x08\x0b\x0c\x0e-\x1f]"
INSTRUCTION_PATTERN = f"^{_TEXT_CHAR}*{VISIBLE_CHAR}{_TEXT_CHAR}*$"
NOT_BLANK = f"^[^\\x00]*{VISIBLE_CHAR}[^\\x00]*$"
"""text without a NUL character and with something besides white space"""


def _not_blank(text: str) -> str:
    return filled(_no_nul(text))


FilledText = Annotated[str, AfterValidator(_not_blank),
                       Field(json_schema_extra={"pattern": NOT_BLANK})]
"""free text that must say something (a name, a note, a consent text): as `PlainText`, stored
without its outer white space, and refused with a 422 naming the field when nothing else is
left (a blank name, or a consent text of spaces that would ask no consent)"""
InstructionText = Annotated[str, AfterValidator(clean_instruction),
                            Field(max_length=MAX_INSTRUCTION_CHARS,
                                  json_schema_extra={"minLength": 1,
                                                     "pattern": INSTRUCTION_PATTERN},
                                  examples=["Run forward as fast as possible."])]


class RunCreate(Body):
    """A new run. Besides each field's own check, the whole run is checked as a worker would
    build it (`runvocab.queued_run`): an unknown or bad `config` field, or one that contradicts
    a top-level field or `teacher_params`, is a 422 naming it."""

    task: TaskName
    algo: AlgoName
    budget: StoredInt | None = None
    """answers the run may ask for in all; defaults to its preset's (`GET /api/runs/defaults`)"""
    preset: PresetName = "small"
    seed: StoredInt = 0
    teacher: TeacherKind = TeacherKind.HUMAN
    teacher_params: TeacherJson = Field(default_factory=dict, examples=[{"eps": 0.1}])
    config: RunConfigJson = Field(default_factory=dict, examples=[{"sac.lr": 1e-4}])
    name: FilledText | None = Field(default=None, min_length=1, max_length=200)
    """defaults to `<task>-<algo>-s<seed>`"""
    instruction: InstructionText | None = None
    """what labellers are told "better" means; defaults to the task's own instruction"""
    clip_size: ClipSizeName | None = None
    """the size the run's clips are rendered at; defaults to 256x256"""


DATASET_ID_PATTERN = r"^[A-Za-z0-9_][A-Za-z0-9_.-]*(/[A-Za-z0-9_][A-Za-z0-9_.-]*)*$"
"""a dataset's Minari id (`sepoa/dmc-cheetah_run/run-3-v0`): names of letters, digits, `_`, `.`
and `-` joined by `/`, none starting with a dot"""


class LabellingRunCreate(Body):
    """A labelling-only run over a dataset export in the server's datasets folder
    (`<data dir>/datasets`, where `sepoa export --dataset data/datasets` writes): rounds of pairs
    of its episodes for people to label, no training (`rundata.labelling`)."""

    dataset: str = Field(min_length=1, max_length=300, pattern=DATASET_ID_PATTERN,
                         examples=["sepoa/dmc-cheetah_run/run-3-v0"])
    """the dataset's id: its folder under the datasets folder"""
    budget: Positive
    """answers the run asks for in all"""
    per_round: Positive | None = None
    """pairs per round; defaults to the preset's"""
    selection: Literal["uniform", "disagreement"] = "disagreement"
    """how rounds after the first (always uniform) draw their pairs: uniformly, or by the
    disagreement of the reward ensemble refitted on the labels so far"""
    segment_length: Positive | None = None
    """steps per clip; defaults to the preset's, at most the dataset's shortest episode"""
    preset: PresetName = "small"
    seed: StoredInt = 0
    teacher: TeacherKind = TeacherKind.HUMAN
    teacher_params: TeacherJson = Field(default_factory=dict, examples=[{"eps": 0.1}])
    config: RunConfigJson = Field(default_factory=dict,
                                 examples=[{"reward.hidden_dim": 64}])
    name: FilledText | None = Field(default=None, min_length=1, max_length=200)
    """defaults to `label <dataset id>`"""
    instruction: InstructionText | None = None
    clip_size: ClipSizeName | None = None


class RunOut(Out):
    id: int
    name: str
    task: str
    algo: str
    preset: str
    seed: int
    config: dict[str, Any]
    teacher: str
    teacher_params: dict[str, Any]
    budget: int
    labels_used: int
    step: int
    progress: dict[str, Any]
    status: str
    worker_id: str | None
    heartbeat_at: datetime | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    error: str | None
    instruction: str | None
    """the operator's instruction; null: the task's own (see `instruction_text`)"""
    clip_size: str | None
    """null: the default size, 256x256"""
    dataset: str | None = None
    """a labelling-only run: the dataset export its pairs come from; null: a training run"""

    @computed_field  # type: ignore[prop-decorator]
    @property
    def instruction_text(self) -> str:
        """the instruction labellers are shown"""
        return run_instruction(self.task, self.instruction)


class RunConfigOut(Out):
    values: dict[str, Any]
    """every field the run trains with, by dotted path (`sac.lr`), in the schema's order; an
    infinite float as text ("inf")"""
    overridden: list[str]
    """the paths the run sets itself (its `config` overrides and teacher parameters); the rest
    come from the presets and the defaults"""
    stored: bool
    """whether the configuration was stored when the run was created; false for a run stored
    before that was kept, whose worker resolves it against the presets when it claims it, as
    shown here"""


class TeacherUpdate(Body):
    teacher: TeacherKind
    params: TeacherJson = Field(default_factory=dict)


class MetricOut(Out):
    step: int
    values: dict[str, Any]


class LabellerCreate(Body):
    name: FilledText = Field(min_length=1, max_length=100)
    role: Role = Role.LABELLER


class LabellerUpdate(Body):
    """What to change; a field left out stays as it is."""

    active: bool | None = None
    """false revokes the labeller's access (its labels stay); true restores it"""
    role: Role | None = None
    name: FilledText | None = Field(default=None, min_length=1, max_length=100)


class LabellerOut(Out):
    id: int
    name: str
    role: str
    active: bool
    created_at: datetime

    @computed_field  # type: ignore[prop-decorator]
    @property
    def scripted(self) -> bool:
        """the runs' scripted teacher, which answers as this labeller: no person"""
        return self.name == SCRIPTED_TEACHER


class LabellerCreated(BaseModel):
    """A new labeller with its bearer token: shown this once, never stored."""

    id: int
    name: str
    role: str
    token: str


class ThroughputBucket(BaseModel):
    t: datetime
    """the bucket's start (UTC, a multiple of the bucket length since the epoch)"""
    labels: int


class Throughput(BaseModel):
    """How fast a run gets its labels, from the labels' answer times (operator dashboard)."""

    run_id: int
    bucket_s: int
    total: int
    by_source: dict[str, int]
    """labels per source: human, scripted (every `LabelSource` present, 0 if none; an answer
    on a gold pair counts under the source that gave it)"""
    median_answer_s: float | None
    """median of answered_at - shown_at over the latest 1000 standing human labels that record
    shown_at; None if none"""
    buckets: list[ThroughputBucket]
    """labels answered per bucket, oldest first; buckets without labels are left out; labels
    taken back (withdrawn) count nowhere"""


class InstructionUpdate(Body):
    instruction: InstructionText | None
    """the run's instruction from now on; null: the task's own"""


class ActivityOut(BaseModel):
    """What a run is doing or waiting for now (`runviews.activity`)."""

    run_id: int
    phase: str
    text: str
    answers_needed: int
    pairs_open: int
    pairs_unrendered: int
    labellers_active: int
    labellers_paused: int
    eta_s: float | None
    workers_alive: int
    workers_idle: int
    queued_ahead: int


class WorkerOut(BaseModel):
    """A trainer worker as last seen."""

    id: str
    host: str | None
    run_id: int | None
    first_seen_at: datetime
    last_seen_at: datetime
    silent_s: float
    """seconds since it last reported"""
    state: WorkerStateName
    """silent: no word for over a minute; dead: for over five (its run may be taken over)"""


class RunDefaults(BaseModel):
    """What a new run of this task, algorithm and preset gets unless told otherwise, and how long
    its first pairs take (`GET /api/runs/defaults`)."""

    budget: int
    per_round: int
    segment_length: int
    """steps per clip"""
    clip_seconds: float
    """a clip's length on the label page at 1x"""
    task_seconds: float | None
    """the same clip in the task's own simulated time"""
    first_round_steps: int
    """environment steps before the first round of pairs"""
    pretrain_steps: int
    """S-EPOA's skill pretraining before anything else (0 for other algorithms)"""
    pretrain_seconds: float | None
    """its estimate, at `pretrain_steps_per_s`"""
    pretrain_steps_per_s: float | None
    pretrain_pace_measured: bool
    """whether the pace is this server's workers' own (else the small preset's on 2 CPU cores)"""
