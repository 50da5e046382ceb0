"""The configuration a queued run describes: its top-level fields (task, algorithm, preset, seed,
label budget), its teacher parameters and its `config` overrides. The server checks a run with
it before accepting one; the worker builds the run's training configuration with it."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from runvocab.config import RunConfig, build_config, typed_overrides
from runvocab.names import ConfigError
from runvocab.validate import validate

WORKER_FIELDS = ("run_dir",)
"""chosen by the worker that trains the run, never by the run's `config`"""
TOP_LEVEL_FIELDS = {"task": "task", "algo": "algo", "preset": "preset", "seed": "seed",
                    "feedback.budget": "budget"}
"""config paths that a queued run also gives as top-level fields, and those fields' names"""


def queued_run_config(*, task: str, algo: str, preset: str, seed: int, budget: int,
                      teacher_params: Mapping[str, Any], config: Mapping[str, Any]) -> RunConfig:
    """The run's training configuration; a ConfigError naming the field when a value is bad, or
    when `config` or `teacher_params` contradicts a top-level field or each other."""
    overrides = typed_overrides(dict(config))
    teacher = _teacher_params(teacher_params)
    for path in WORKER_FIELDS:
        if path in overrides:
            raise ConfigError(path, f"config sets {path}, which the worker that trains a queued "
                                    "run chooses; leave it out")
    given = {"task": task, "algo": algo, "preset": preset, "seed": seed, "budget": budget}
    top = {path: given[name] for path, name in TOP_LEVEL_FIELDS.items()}
    for path, value in (top | teacher).items():
        if path in overrides and overrides[path] != value:
            where = "teacher_params" if path in teacher else "the run's top-level field"
            raise ConfigError(path, f"config sets {path} to {overrides[path]!r}, but {where} "
                                    f"says {value!r}; give it once")
    cfg = build_config(task, preset, overrides | teacher | top)
    validate(cfg)
    return cfg


def _teacher_params(params: Mapping[str, Any]) -> dict[str, Any]:
    try:
        return typed_overrides({f"teacher.{k}": v for k, v in params.items()})
    except ConfigError as err:
        raise ConfigError(err.field, f"teacher_params: {err}") from None
