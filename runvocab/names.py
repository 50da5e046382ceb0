"""The valid names of a run's choices, and one way of refusing a name that is not among them.

The trainer's registries (selection rules, teachers, skill backends) are keyed by these names;
a test checks that they agree. The task list is data (`tasks.json`, written from the installed
dm_control and Metaworld by `python -m trainer.envs`), so reading it needs neither.
"""

from __future__ import annotations

import difflib
import functools
import json
from collections.abc import Iterable
from pathlib import Path

PEBBLE_FAMILY = ("pebble", "surf", "rune", "rime")
"""PEBBLE, and the baselines that are PEBBLE with one piece added"""
ALGOS = ("sac", *PEBBLE_FAMILY, "sepoa")
SIZE_PRESETS = ("paper", "small", "tiny")
SELECTION_RULES = ("uniform", "disagreement", "entropy", "skill")
SELECTION_MODES = ("per_query", "top_k")
TEACHER_KINDS = ("noisy", "bpref")
"""the scripted teachers' kinds (`teacher.kind`)"""
TIES = ("equal", "random", "first")
SKILL_BACKENDS = ("aps", "diayn", "cic")
SCORE_SPREADS = ("var", "std")
TASK_SKILL_DRAWS = ("episode", "refit")
ESTIMATOR_DATA = ("pool", "replay")
"""what S-EPOA's R_theta is fitted on (`skill.estimator_data`)"""
SKILL_ACTORS = ("sac", "ddpg")
"""S-EPOA's actor at fine-tuning (`skill.actor`)"""
DEVICES = ("auto", "cpu", "cuda")
FAMILIES = ("dmc", "metaworld")


def device_name_error(name: str) -> str | None:
    """Why `name` is not a device a run can name (auto, cpu, cuda or cuda:<index>), or None."""
    kind, _, index = name.partition(":")
    if kind in DEVICES and (not index or (kind == "cuda" and index.isdigit())):
        return None
    return f"unknown device {name!r}; valid: {', '.join(DEVICES)}, cuda:<index>"

TASKS_JSON = Path(__file__).with_name("tasks.json")


class ConfigError(ValueError):
    """A configuration that cannot run; `field` is the dotted path of the field at fault."""

    def __init__(self, field: str, message: str):
        super().__init__(message)
        self.field = field


@functools.cache
def tasks_by_family() -> dict[str, tuple[str, ...]]:
    """Every valid task name ("dmc:cheetah_run", "metaworld:door-open"), per family."""
    with open(TASKS_JSON) as f:
        return {family: tuple(names) for family, names in json.load(f).items()}


def all_tasks() -> tuple[str, ...]:
    return tuple(name for names in tasks_by_family().values() for name in names)


def task_family(task: str) -> str:
    return task.split(":", 1)[0]


def did_you_mean(value: str, valid: Iterable[str]) -> str:
    """" (did you mean 'x'?)" for the nearest miss, else ""."""
    close = difflib.get_close_matches(value, list(valid), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def unknown(field: str, value: object, valid: Iterable[str]) -> str:
    """The refusal of a name: which field, the near miss if any, and every valid value."""
    valid = list(valid)
    hint = did_you_mean(value, valid) if isinstance(value, str) else ""
    shown = ", ".join(repr(v) if v == "" else v for v in valid)
    return f"unknown {field} {value!r}{hint}; valid: {shown}"


def unknown_task(task: str) -> str:
    """The refusal of a task name: the near miss, and the valid names of its family (or the
    families, when the prefix itself is wrong)."""
    families = tasks_by_family()
    family = task_family(task)
    if family not in families:
        return (f"unknown task {task!r}{did_you_mean(task, all_tasks())}: a task is "
                f"'<family>:<name>' with family {' or '.join(FAMILIES)}, e.g. dmc:cheetah_run "
                f"or metaworld:door-open; `sepoa tasks` lists all {len(all_tasks())}")
    names = families[family]
    return (f"unknown task {task!r}{did_you_mean(task, names)}; valid {family} tasks: "
            f"{', '.join(names)}")
