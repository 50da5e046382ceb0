"""Experiment specs: a TOML grid of runs, checked on load and expanded into runs.

A spec is tasks x variants x eps x seeds (x budgets) under one preset and one length, with
shared config overrides; a variant is a label, an algorithm, its own overrides, which win over
the shared ones, and optionally its own seeds (a reference arm may need fewer). An optional
`[analysis]` pre-registers the report's primary comparison. Each run gets a stable folder under
the spec's results folder: `<task>/<variant>/eps<e>[/budget<b>]/s<seed>`. docs/EXPERIMENTS.md
describes the format.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from runvocab.config import PRESETS, RunConfig, build_config, typed_overrides
from runvocab.names import ALGOS, all_tasks, unknown, unknown_task
from runvocab.snapshot_names import snapshot_path
from runvocab.validate import validate

KINDS = ("curves", "ablation")
REQUIRED = ("name", "preset", "steps", "tasks", "eps", "seeds", "variants")
OPTIONAL = ("title", "kind", "budgets", "threads", "overrides", "analysis", "stop_after_hours")
METRICS = {"final_quarter": "the mean evaluation return over the last 25 % of steps"}
"""pre-registered primary metrics, by the name `[analysis] metric` gives"""

# Fields the spec sets through its own keys: an override of one would contradict the grid.
RESERVED = {
    "task": "tasks", "algo": "a variant's algo", "preset": "preset", "seed": "seeds",
    "steps": "steps", "teacher.eps": "eps", "threads": "threads", "run_dir": "the worker",
}


class SpecError(ValueError):
    """A spec that cannot be run; the message names the file and the problem."""


Fail = Callable[[str], SpecError]


@dataclass(frozen=True)
class Variant:
    label: str
    algo: str
    overrides: dict[str, Any]
    """the variant's own dotted-path overrides"""
    seeds: tuple[int, ...] = ()
    """the variant's own seeds; empty: the spec's"""


@dataclass(frozen=True)
class Analysis:
    """A pre-registered comparison (`[analysis]`): the primary metric per run, and the variant
    whose probability of improvement over each of `compare_to` the report estimates."""

    metric: str
    reference: str
    compare_to: tuple[str, ...]
    also: tuple[tuple[str, str], ...] = ()
    """further pairs (X, Y) whose P(X > Y) the report estimates, beside the reference's"""

    def pairs(self) -> list[tuple[str, str]]:
        """Every (X, Y) whose P(X > Y) is pre-registered: the reference against each compared
        variant, then `also`."""
        return [(self.reference, other) for other in self.compare_to] + list(self.also)


@dataclass(frozen=True)
class Run:
    task: str
    variant: str
    """the variant's label"""
    algo: str
    eps: float
    budget: int | None
    """the budgets axis' value; None: the task's and preset's own feedback.budget"""
    seed: int
    preset: str
    steps: int
    overrides: dict[str, Any]
    """shared overrides, then the variant's (which win), then the budget"""
    dir: Path
    """relative to the spec's results folder"""

    def config_overrides(self) -> dict[str, Any]:
        """Every dotted-path value the run sets, grid axes included."""
        axes = {"algo": self.algo, "seed": self.seed, "steps": self.steps,
                "teacher.eps": self.eps}
        return axes | self.overrides

    def config(self) -> RunConfig:
        """The run's resolved configuration (run_dir left empty)."""
        return build_config(self.task, self.preset, self.config_overrides())

    def snapshot(self) -> str | None:
        """The skill snapshot the run starts from (its name, as where its workers keep
        snapshots), or None when it needs none."""
        cfg = self.config()
        return snapshot_path(cfg) if cfg.algo == "sepoa" and cfg.skill.pretrain_steps > 0 \
            else None

    def identity(self) -> dict[str, Any]:
        """What defines the run's results, as JSON gives it back."""
        ident = {"task": self.task, "variant": self.variant, "algo": self.algo,
                 "eps": self.eps, "budget": self.budget, "seed": self.seed,
                 "preset": self.preset, "steps": self.steps, "overrides": self.overrides}
        return json.loads(json.dumps(ident, default=str))


@dataclass(frozen=True)
class Spec:
    name: str
    title: str
    kind: str
    preset: str
    steps: int
    tasks: tuple[str, ...]
    eps: tuple[float, ...]
    seeds: tuple[int, ...]
    budgets: tuple[int, ...]
    """empty: each task's own budget"""
    threads: int
    """torch threads per process"""
    overrides: dict[str, Any]
    variants: tuple[Variant, ...]
    source: str = ""
    """the TOML text, stored beside the results"""
    analysis: Analysis | None = None
    stop_after_hours: float | None = None
    """no seed starts once the grid's workers have trained this long (experiments.stop_rule)"""
    part_of: Spec | None = dataclasses.field(default=None, compare=False, repr=False)
    """the whole grid when this spec is a part of it (`only`); None: this spec is the whole"""

    @property
    def whole(self) -> Spec:
        """The whole grid this spec is a part of, or the spec itself."""
        return self.part_of or self

    def runs(self) -> list[Run]:
        """Every run of the grid, in folder order (task, variant, eps, budget, seed)."""
        budgets: tuple[int | None, ...] = self.budgets or (None,)
        out = []
        for task in self.tasks:
            for v in self.variants:
                for eps in self.eps:
                    for budget in budgets:
                        for seed in v.seeds or self.seeds:
                            extra = {} if budget is None else {"feedback.budget": budget}
                            folder = Path(safe_name(task), safe_name(v.label), f"eps{eps:g}")
                            if budget is not None:
                                folder /= f"budget{budget}"
                            out.append(Run(task, v.label, v.algo, eps, budget, seed,
                                           self.preset, self.steps,
                                           self.overrides | v.overrides | extra,
                                           folder / f"s{seed}"))
        return out

    def runs_seed_first(self) -> list[Run]:
        """Every run, the first seed of every variant before the second of any: the order runs
        are queued in, so a grid stopped half-way has a balanced share of every variant.
        Within a seed, folder order, except that a run starting from a skill snapshot an
        earlier run also needs comes after the runs that need none: the first run's worker
        pretrains the snapshot meanwhile, where a second worker would wait for it idle."""
        seeds = {v.label: v.seeds or self.seeds for v in self.variants}
        runs = self.runs()
        needed: set[str] = set()
        waits: dict[Path, bool] = {}
        for run in runs:
            snapshot = run.snapshot()
            waits[run.dir] = snapshot in needed
            if snapshot is not None:
                needed.add(snapshot)
        # A stable sort: within a seed's rank, folder order among those that wait and not.
        return sorted(runs, key=lambda r: (seeds[r.variant].index(r.seed), waits[r.dir]))

    def only(self, variants: list[str] | None = None, seeds: list[int] | None = None) -> Spec:
        """The part of the grid with these variants (labels) and seeds (None: all of them):
        the same runs, folders and configurations, so a part trained elsewhere (another host,
        a GPU) joins the whole grid's results. SpecError naming what the spec lacks."""
        labels = [v.label for v in self.variants]
        for label in variants or []:
            if label not in labels:
                raise SpecError(f"spec {self.name!r} has no variant {label!r}; its variants: "
                                + ", ".join(repr(x) for x in labels))
        kept = []
        for v in self.variants:
            if variants is not None and v.label not in variants:
                continue
            own = tuple(s for s in v.seeds or self.seeds if seeds is None or s in seeds)
            if own:
                kept.append(dataclasses.replace(v, seeds=own))
        chosen = ", ".join(repr(x) for x in variants) if variants else "any variant"
        if not kept:
            raise SpecError(f"spec {self.name!r} runs none of seeds "
                            f"{', '.join(map(str, seeds or []))} with {chosen}")
        # One seed the part lacks among several it has would be left out without a word.
        have = sorted({s for v in self.variants if variants is None or v.label in variants
                       for s in v.seeds or self.seeds})
        lacking = [s for s in seeds or [] if s not in have]
        if lacking:
            raise SpecError(f"spec {self.name!r} runs no seed {', '.join(map(str, lacking))} "
                            f"with {chosen}; its seeds there: {', '.join(map(str, have))}")
        return dataclasses.replace(self, variants=tuple(kept), part_of=self.whole)


def safe_name(text: str) -> str:
    """A folder name for `text`: ':', '/' and '\\' become '-', other characters outside
    [A-Za-z0-9._+-] become '_'."""
    name = re.sub(r"[:/\\]", "-", text)
    name = re.sub(r"[^A-Za-z0-9._+-]+", "_", name).strip("._")
    return name or "_"


def load_spec(path: str | Path, check: bool = True) -> Spec:
    """Read and check a spec file. `check` also validates algorithms, task names and every
    run's full configuration against the trainer (imports torch); without it only the grid and
    the config field names and types are checked (enough to read results)."""
    path = Path(path)
    try:
        text = path.read_text()
        data = tomllib.loads(text)
    except OSError as err:
        raise SpecError(f"{path}: cannot read the spec: {err.strerror}") from err
    except UnicodeDecodeError:
        raise SpecError(f"{path}: cannot read the spec: not UTF-8 text (a spec is a TOML "
                        "file)") from None
    except tomllib.TOMLDecodeError as err:
        raise SpecError(f"{path}: not valid TOML: {err}") from err
    return parse_spec(data, str(path), source=text, check=check)


def parse_spec(data: dict[str, Any], where: str, source: str = "",
               check: bool = True) -> Spec:
    """The spec in the parsed TOML `data`; errors are prefixed by `where` (the file name)."""

    def fail(message: str) -> SpecError:
        return SpecError(f"{where}: {message}")

    unknown = sorted(set(data) - set(REQUIRED) - set(OPTIONAL))
    if unknown:
        raise fail(f"unknown key {unknown[0]!r}; valid keys: {', '.join(REQUIRED + OPTIONAL)}")
    missing = [k for k in REQUIRED if k not in data]
    if missing:
        raise fail(f"missing required key {missing[0]!r}")

    name = data["name"]
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", name):
        raise fail(f"'name' must be a folder name of letters, digits, '.', '_' or '-'; "
                   f"got {name!r}")
    preset = data["preset"]
    if preset not in PRESETS:
        raise fail(f"unknown preset {preset!r}; valid: {', '.join(PRESETS)}")
    kind = data.get("kind", "curves")
    if kind not in KINDS:
        raise fail(f"unknown kind {kind!r}; valid: {', '.join(KINDS)}")
    title = data.get("title", name)
    if not isinstance(title, str):
        raise fail("'title' must be a string")
    steps = _integer(data["steps"], "steps", 1, fail)
    threads = _integer(data.get("threads", 1), "threads", 1, fail)
    hours = data.get("stop_after_hours")
    if hours is not None and (isinstance(hours, bool) or not isinstance(hours, int | float)
                              or not hours > 0):
        raise fail(f"'stop_after_hours' takes a number of hours above 0; got {hours!r}")

    tasks = _axis(data, "tasks", fail, lambda v, k: _text(v, k, fail))
    eps = _axis(data, "eps", fail, lambda v, k: _rate(v, k, fail))
    seeds = _axis(data, "seeds", fail, lambda v, k: _integer(v, k, 0, fail))
    budgets = _axis(data, "budgets", fail, lambda v, k: _integer(v, k, 1, fail),
                    allow_empty=True)

    shared = data.get("overrides", {})
    if not isinstance(shared, dict):
        raise fail("'overrides' must be a table of config fields")
    shared = _check_overrides(flatten(shared), "[overrides]", bool(budgets), fail)

    table = data["variants"]
    if not isinstance(table, dict) or not table:
        raise fail("'variants' is empty: a grid needs at least one variant "
                   "([variants.<label>] with an algo)")
    variants = []
    for label, body in table.items():
        section = f"[variants.{json.dumps(label)}]"
        if not isinstance(body, dict):
            raise fail(f"{section} must be a table with an 'algo'")
        if "algo" not in body:
            raise fail(f"{section}: missing required key 'algo'")
        if not isinstance(body["algo"], str):
            raise fail(f"{section}: 'algo' must be a string")
        own = flatten({k: v for k, v in body.items() if k not in ("algo", "seeds")})
        own_seeds = (_axis(body, "seeds", fail, lambda v, k: _integer(v, k, 0, fail))
                     if "seeds" in body else ())
        variants.append(Variant(label, body["algo"],
                                _check_overrides(own, section, bool(budgets), fail),
                                own_seeds))

    analysis = _analysis(data.get("analysis"), [v.label for v in variants], fail)
    spec = Spec(name, title, kind, preset, steps, tasks, eps, seeds, budgets, threads, shared,
                tuple(variants), source, analysis,
                None if hours is None else float(hours))
    folders: dict[Path, Run] = {}
    for run in spec.runs():
        if run.dir in folders:
            raise fail(f"duplicate run folder {run.dir} (variants {folders[run.dir].variant!r} "
                       f"and {run.variant!r} give the same folder name)")
        folders[run.dir] = run
    if check:
        check_runs(spec, fail)
    return spec


def check_runs(spec: Spec, fail: Fail) -> None:
    """Algorithms, task names and each run's full configuration, as `train` would check them."""
    for v in spec.variants:
        if v.algo not in ALGOS:
            raise fail(f"[variants.{json.dumps(v.label)}]: {unknown('algo', v.algo, ALGOS)}")
    for task in spec.tasks:
        if task not in all_tasks():
            raise fail(f"'tasks': {unknown_task(task)}")
    for run in spec.runs():
        try:
            validate(run.config())
        except ValueError as err:
            raise fail(f"variant {run.variant!r} on {run.task}, eps {run.eps:g}: {err}") from err


def _analysis(table: Any, labels: list[str], fail: Fail) -> Analysis | None:
    if table is None:
        return None
    keys = ("metric", "reference", "compare_to")
    if not isinstance(table, dict) or not set(keys) <= set(table) <= {*keys, "also"}:
        raise fail(f"[analysis] takes the keys {', '.join(keys)}, and optionally also")
    if table["metric"] not in METRICS:
        raise fail(f"[analysis] unknown metric {table['metric']!r}; valid: "
                   + ", ".join(f"{k} ({v})" for k, v in METRICS.items()))
    compare_to = table["compare_to"]
    if not isinstance(compare_to, list) or not compare_to:
        raise fail("[analysis] 'compare_to' must be a non-empty list of variant labels")
    for label in [table["reference"], *compare_to]:
        if label not in labels:
            raise fail(f"[analysis] {label!r} is not a variant; variants: {', '.join(labels)}")
    if table["reference"] in compare_to:
        raise fail("[analysis] 'compare_to' lists the reference variant itself")
    also = table.get("also", [])
    if not isinstance(also, list) or not all(
            isinstance(p, list) and len(p) == 2 and p[0] != p[1] for p in also):
        raise fail("[analysis] 'also' must be a list of pairs of two variant labels, "
                   'e.g. [["C", "A"]] for P(C > A)')
    for label in [x for pair in also for x in pair]:
        if label not in labels:
            raise fail(f"[analysis] {label!r} is not a variant; variants: {', '.join(labels)}")
    return Analysis(table["metric"], table["reference"], tuple(compare_to),
                    tuple((x, y) for x, y in also))


def flatten(table: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested tables (TOML's, a config.json's) to dotted paths: TOML reads
    `skill.backend = "diayn"` (unquoted) as a table, `"skill.backend" = "diayn"` as one key;
    both mean the same field."""
    out: dict[str, Any] = {}
    for key, value in table.items():
        if isinstance(value, dict):
            out |= flatten(value, f"{prefix}{key}.")
        else:
            out[prefix + key] = value
    return out


def _check_overrides(values: dict[str, Any], section: str, has_budgets: bool,
                     fail: Fail) -> dict[str, Any]:
    for path in values:
        if path in RESERVED:
            raise fail(f"{section}: {path!r} is set by the spec's {RESERVED[path]}, "
                       "not by an override")
        if path == "feedback.budget" and has_budgets:
            raise fail(f"{section}: 'feedback.budget' is set by the spec's budgets")
    try:
        return typed_overrides(values)
    except ValueError as err:
        raise fail(f"{section}: {err}") from err


def _axis(data: dict[str, Any], key: str, fail: Fail, item: Callable[[Any, str], Any],
          allow_empty: bool = False) -> tuple:
    values = data.get(key, [])
    if not isinstance(values, list):
        raise fail(f"{key!r} must be a list")
    if not values and not allow_empty:
        raise fail(f"{key!r} is empty: a grid needs at least one")
    out = tuple(item(v, key) for v in values)
    dupes = sorted({v for v in out if out.count(v) > 1}, key=str)
    if dupes:
        raise fail(f"{key!r} lists {dupes[0]!r} twice (a duplicate run)")
    return out


def _integer(value: Any, key: str, least: int, fail: Fail) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise fail(f"{key!r} takes integers of at least {least}; got {value!r}")
    return value


def _rate(value: Any, key: str, fail: Fail) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0 <= value < 1:
        raise fail(f"{key!r} takes numbers in [0, 1); got {value!r}")
    return float(value)


def _text(value: Any, key: str, fail: Fail) -> str:
    if not isinstance(value, str) or not value:
        raise fail(f"{key!r} takes non-empty strings; got {value!r}")
    return value


def grid_snapshots(spec: Spec) -> set[str]:
    """The names of the skill snapshots the spec's runs start from."""
    return {os.path.basename(path) for run in spec.runs() if (path := run.snapshot())}
