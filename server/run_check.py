"""A run no worker could train, refused when it is created (`labelqueue.create_run` resolves
it with `runvocab.queued_run`): a bad or contradictory field is a 422 whose `loc` points at it
in the request body. And a new run's defaults."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from fastapi.exceptions import RequestValidationError

from runvocab.clip_format import CLIP_FPS, step_seconds
from runvocab.config import build_config, typed_overrides
from runvocab.first_round import first_round_step
from runvocab.names import ConfigError
from runvocab.queued_run import TOP_LEVEL_FIELDS
from runvocab.validate import validate


def refusal(err: ConfigError, *, teacher_params: Mapping[str, Any], config: Mapping[str, Any],
            params_at: str = "teacher_params") -> RequestValidationError:
    """The 422 for a run no worker could train. `params_at`: the body field that holds the
    teacher parameters."""
    return RequestValidationError([{
        "type": "value_error", "msg": str(err),
        "loc": _location(err.field, teacher_params, config, params_at),
    }])


def _location(field: str, teacher_params: Mapping[str, Any], config: Mapping[str, Any],
              params_at: str) -> tuple[str, ...]:
    param = field.removeprefix("teacher.")
    if field in config:
        return ("body", "config", field)
    if field.startswith("teacher.") and param in teacher_params:
        return ("body", params_at, param)
    if field in TOP_LEVEL_FIELDS:
        return ("body", TOP_LEVEL_FIELDS[field])
    return ("body",)  # a preset's value the rest of the run contradicts; the message names it


DEFAULT_PRETRAIN_STEPS_PER_S = 230.0
"""APS skill pretraining's pace with the small preset on 2 CPU cores, the estimate's fallback
when no worker of this server has reported its own"""


def run_defaults(*, task: str, algo: str, preset: str, config: Mapping[str, Any],
                 measured_pace: float | None) -> dict[str, Any]:
    """What a run of this task, algorithm and preset gets unless `config` says otherwise
    (`RunDefaults`); a 422 naming the field for a config no worker could use, checked as
    `POST /api/runs` checks it (`runvocab.validate`: ranges, finite numbers, rules between
    fields), so no value a new run would be refused is shown as a default."""
    try:
        cfg = build_config(task, preset, {"algo": algo} | typed_overrides(dict(config)))
        validate(cfg)
    except ConfigError as err:
        raise RequestValidationError([{
            "type": "value_error", "msg": str(err), "loc": ("query", "config", err.field),
        }]) from None
    first = first_round_step(cfg)
    pretrain = cfg.skill.pretrain_steps if algo == "sepoa" else 0
    pace = measured_pace or DEFAULT_PRETRAIN_STEPS_PER_S
    step_s = step_seconds(task)
    segment = cfg.feedback.segment_length
    return {
        "budget": cfg.feedback.budget,
        "per_round": cfg.feedback.per_round,
        "segment_length": segment,
        "clip_seconds": round(segment / CLIP_FPS, 3),
        "task_seconds": None if step_s is None else round(segment * step_s, 3),
        "first_round_steps": first,
        "pretrain_steps": pretrain,
        "pretrain_seconds": round(pretrain / pace, 1) if pretrain else None,
        "pretrain_steps_per_s": round(pace, 1) if pretrain else None,
        "pretrain_pace_measured": bool(pretrain and measured_pace),
    }
