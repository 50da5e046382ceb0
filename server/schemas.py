"""The API's request and response bodies, separate from the ORM tables in `labelqueue.models`.

Labeller-facing bodies (`NextQuery`, `LabelOut`) carry no ground truth: no segment or trajectory
returns, no model probability, no selection score.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

TASK_PATTERN = r"^(dmc|metaworld):[a-z0-9_\-]+$"
Algo = Literal["sac", "pebble", "surf", "rune", "rime", "sepoa"]
Preset = Literal["paper", "small", "tiny"]
Teacher = Literal["human", "scripted"]
RoleName = Literal["labeller", "operator"]
StreamName = Literal["episodes", "eval", "rounds"]
ChoiceName = Literal["left", "right", "equal", "cant_tell", "skip"]


class Body(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Out(BaseModel):
    model_config = ConfigDict(from_attributes=True)


class RunCreate(Body):
    task: str = Field(pattern=TASK_PATTERN, examples=["dmc:cheetah_run"])
    algo: Algo
    budget: int = Field(ge=0)
    preset: Preset = "small"
    seed: int = Field(default=0, ge=0)
    teacher: Teacher = "human"
    teacher_params: dict[str, Any] = Field(default_factory=dict, examples=[{"eps": 0.1}])
    config: dict[str, Any] = Field(default_factory=dict, examples=[{"sac.lr": 1e-4}])
    name: str | None = Field(default=None, min_length=1, max_length=200)
    """defaults to `<task>-<algo>-s<seed>`"""


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


class TeacherUpdate(Body):
    teacher: Teacher
    params: dict[str, Any] = Field(default_factory=dict)


class MetricOut(Out):
    step: int
    values: dict[str, Any]


class LabellerCreate(Body):
    name: str = Field(min_length=1, max_length=100)
    role: RoleName = "labeller"


class LabellerOut(Out):
    id: int
    name: str
    role: str
    active: bool
    created_at: datetime


class LabellerCreated(BaseModel):
    """A new labeller with its bearer token: shown this once, never stored."""

    id: int
    name: str
    role: str
    token: str


class NextQuery(BaseModel):
    """A leased query as a labeller sees it: two clip URLs, and nothing that hints the answer."""

    query_id: int
    run_id: int
    lease_expires_at: datetime
    left_clip_url: str
    right_clip_url: str
    left_is_first: bool
    """echo it back with the label: which segment was on the left"""
    segment_length: int


class LabelSubmit(Body):
    choice: ChoiceName
    left_is_first: bool
    shown_at: datetime


class LabelOut(Out):
    id: int
    query_id: int
    run_id: int
    labeller_id: int
    choice: str
    left_is_first: bool
    preferred: str | None
    shown_at: datetime | None
    answered_at: datetime


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
    """labels per source: human, scripted, gold (every source present, 0 if none)"""
    median_answer_s: float | None
    """median of answered_at - shown_at over human labels that record shown_at; None if none"""
    buckets: list[ThroughputBucket]
    """labels answered per bucket, oldest first; buckets without labels are left out"""


class LabelCount(BaseModel):
    """How many labels the caller has given, over all runs."""

    labels: int
