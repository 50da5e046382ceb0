"""The configuration a queued run trains with, resolved once, when the run is created.

`create_run` resolves a run's top-level fields, teacher parameters and `config` overrides
against the presets (`runvocab.queued_run`) and stores the result in `runs.resolved_config`.
The worker trains exactly that, the run page shows it, and the label API reads the run's gold
and practice settings from its feedback section; a preset changed later changes no stored run.
A run stored before migration 0015 has none: it is resolved as it always was, the worker's
way, and its label settings are its `config` overrides over the defaults.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

from labelqueue.models import RUNS, Run
from runvocab.config import RunConfig, apply_overrides, from_dict, to_dict, typed_overrides
from runvocab.queued_run import queued_run_config

FEEDBACK = RUNS.c.resolved_config["feedback"].label("feedback")
"""the feedback section of a run's resolved config (null for a run stored without one), for
statements that select a run's label settings beside its `config`"""


def resolve(*, task: str, algo: str, preset: str, seed: int, budget: int,
            teacher_params: Mapping[str, Any], config: Mapping[str, Any]) -> dict[str, Any]:
    """The run's resolved configuration as stored (JSON); a ConfigError naming the field for
    a run no worker could train."""
    cfg = queued_run_config(task=task, algo=algo, preset=preset, seed=seed, budget=budget,
                            teacher_params=teacher_params, config=config)
    return as_json(cfg)


def as_json(cfg: RunConfig) -> dict[str, Any]:
    """`to_dict(cfg)` as strict JSON, which PostgreSQL and SQLite's JSON functions take: an
    infinite float (`teacher.beta`) as the text "inf", a tuple as a list."""
    def plain(value: Any) -> Any:
        if isinstance(value, dict):
            return {key: plain(item) for key, item in value.items()}
        if isinstance(value, list | tuple):
            return [plain(item) for item in value]
        if isinstance(value, float) and not math.isfinite(value):
            return str(value)
        return value

    stored: dict[str, Any] = plain(to_dict(cfg))
    return stored


def from_json(stored: Mapping[str, Any]) -> RunConfig:
    """The configuration `as_json` stored; its text values read by their fields' own parser
    (`runvocab.config.parse_value`), so "inf" is a float again."""
    texts = {path: value for path, value in fields(stored).items() if isinstance(value, str)}
    return apply_overrides(from_dict(dict(stored)), typed_overrides(texts))


def run_config(run: Run) -> RunConfig:
    """What the run trains with: its stored configuration, or for a run stored without one,
    its fields resolved against today's presets (a ConfigError when they no longer resolve)."""
    if run.resolved_config is not None:
        return from_json(run.resolved_config)
    return _resolved_now(run, run.teacher_params, run.config)


def _resolved_now(run: Run, teacher_params: Mapping[str, Any],
                  config: Mapping[str, Any]) -> RunConfig:
    return queued_run_config(task=run.task, algo=run.algo, preset=run.preset, seed=run.seed,
                             budget=run.budget, teacher_params=teacher_params, config=config)


def fields(stored: Mapping[str, Any]) -> dict[str, Any]:
    """A stored configuration as `{dotted path: value}`, in the schema's order."""
    out: dict[str, Any] = {}
    for name, value in stored.items():
        if isinstance(value, dict):
            out |= {f"{name}.{leaf}": item for leaf, item in value.items()}
        else:
            out[name] = value
    return out


def overridden(run: Run) -> list[str]:
    """The paths the run sets itself rather than taking from the presets: its `config`
    overrides and its teacher parameters (`teacher.<name>`)."""
    return [*run.config, *(f"teacher.{name}" for name in run.teacher_params)]


def with_teacher(run: Run, params: Mapping[str, Any]
                 ) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """The run's `config` and stored configuration (None for a run stored without one) with new
    teacher parameters: `params` take the place of the config's own (`teacher.eps`), so the run
    holds each once; the rest as stored. A ConfigError names a bad or contradictory parameter."""
    given = {f"teacher.{name}" for name in params}
    config = {path: value for path, value in run.config.items() if path not in given}
    teacher = _resolved_now(run, params, config).teacher
    if run.resolved_config is None:
        return config, None
    return config, as_json(dataclasses.replace(from_json(run.resolved_config), teacher=teacher))


def run_feedback(row: Any) -> Mapping[str, Any]:
    """A run's feedback settings by field name (`gold_rate`), from a row with its `config`
    and `feedback` (`FEEDBACK`): the resolved section, or for a run stored without one, the
    section's `config` overrides. A field missing from them takes its default."""
    if row.feedback is not None:
        section: Mapping[str, Any] = row.feedback
        return section
    return {path.removeprefix("feedback."): value for path, value in (row.config or {}).items()
            if path.startswith("feedback.")}
