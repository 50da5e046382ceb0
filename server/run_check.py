"""A run checked as the worker will build it (`runvocab.queued_run`), before it is stored: a bad
or contradictory field is a 422 whose `loc` points at it in the request body."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from fastapi.exceptions import RequestValidationError

from runvocab.names import ConfigError
from runvocab.queued_run import TOP_LEVEL_FIELDS, queued_run_config


def check_run(*, task: str, algo: str, preset: str, seed: int, budget: int,
              teacher_params: Mapping[str, Any], config: Mapping[str, Any],
              params_at: str = "teacher_params") -> None:
    """Raise a RequestValidationError (422) for a run no worker could train. `params_at`: the
    body field that holds the teacher parameters."""
    try:
        queued_run_config(task=task, algo=algo, preset=preset, seed=seed, budget=budget,
                          teacher_params=teacher_params, config=config)
    except ConfigError as err:
        raise RequestValidationError([{
            "type": "value_error", "msg": str(err),
            "loc": _location(err.field, teacher_params, config, params_at),
        }]) from None


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
