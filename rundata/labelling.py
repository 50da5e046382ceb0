"""Labelling-only runs: a run over an existing dataset export, with no training.

    create_labelling_run(session, dataset="datasets/sepoa/dmc-cheetah_run/run-3-v0", budget=200,
                         per_round=20, selection="disagreement")

queues a run whose worker (`trainer.dataset_labelling`) draws each round's pairs from the
dataset's episodes instead of from a policy's: the first round uniformly, the next ones by
`selection` (uniform, or the disagreement of a reward ensemble refitted on the labels so far),
renders their clips from the episodes' stored physics states, and serves rounds until the
budget is spent. The label page, the label export and the dataset export are those of any run;
a query's `first_trajectory`/`second_trajectory` is the dataset's episode id.

The dataset is checked here, before anything is stored (`rundata.dataset.read_dataset`: a
task this project knows, physics states, spaces that agree with its `sepoa.json`), and so is
the run's configuration (resolved and stored by `create_run`), so a run no worker could serve
is refused with one line naming the problem. The run stores the dataset's absolute folder
(`runs.dataset`): the workers read it there, so on several hosts it must be a folder they all
reach, like the clips.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session

from labelqueue.instructions import checked_instruction
from labelqueue.models import Run
from labelqueue.run_config import resolve
from labelqueue.runs import checked_clip_size, create_run
from rundata.dataset import DatasetError, LabelledDataset, read_dataset
from runvocab.config import build_config
from runvocab.names import ConfigError
from runvocab.text import filled

LABELLING_ALGO = "pebble"
"""the algorithm a labelling run records: its reward ensemble and selection rules are PEBBLE's;
nothing trains a policy"""
LABELLING_SELECTIONS = ("uniform", "disagreement")
"""how rounds after the first draw their pairs (the first is always uniform: before any label
the ensemble's disagreement is noise)"""
NAME_MAX = 200


class LabellingError(ConfigError):
    """A labelling run that cannot be made; `field` names the input at fault (`dataset`, or a
    configuration path such as `feedback.segment_length`)."""


def labelling_dataset(dataset: str) -> LabelledDataset:
    """The dataset a labelling run would label, checked; LabellingError naming the problem."""
    try:
        found = read_dataset(dataset)
    except DatasetError as err:
        raise LabellingError("dataset", str(err)) from None
    except (OSError, ValueError) as err:  # a path the system refuses (too long, a NUL byte)
        raise LabellingError("dataset", f"dataset {dataset!r} cannot be read: {err}") from None
    if len(found.episodes) < 2:
        raise LabellingError("dataset", f"{found.path}: a labelling run compares segments of "
                             f"two different episodes; the dataset has {len(found.episodes)}")
    return found


def labelling_config(found: LabelledDataset, *, per_round: int | None, selection: str,
                     segment_length: int | None, preset: str,
                     config: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The run's `config` overrides: the rounds as asked, the first one uniform, and a segment
    that fits the dataset's episodes (default: the preset's, or the shortest episode's length
    when that is shorter). LabellingError naming a bad value."""
    if selection not in LABELLING_SELECTIONS:
        raise LabellingError("feedback.selection", f"selection {selection!r}: a labelling run "
                             f"draws pairs by {' or '.join(LABELLING_SELECTIONS)}")
    shortest = sorted(e.length for e in found.episodes)[1]  # two episodes must hold a segment
    if segment_length is None:
        preset_length = build_config(found.task, preset, {}).feedback.segment_length
        segment_length = min(preset_length, shortest)
    if not 1 <= segment_length <= shortest:
        raise LabellingError("feedback.segment_length", (
            f"segment length {segment_length}: give 1 to {shortest}, so that two of the "
            f"dataset's episodes (the shortest are {shortest} steps) hold a segment"))
    overrides: dict[str, Any] = dict(config or {})
    overrides |= {"feedback.selection": selection, "feedback.first_round_selection": "uniform",
                  "feedback.segment_length": segment_length,
                  # Nothing trains meanwhile: a round waits for its answers.
                  "feedback.wait_for_labels": True}
    if per_round is not None:
        overrides["feedback.per_round"] = per_round
    return overrides


def create_labelling_run(session: Session, *, dataset: str, budget: int,
                         per_round: int | None = None, selection: str = "disagreement",
                         segment_length: int | None = None, name: str | None = None,
                         preset: str = "small", seed: int = 0, teacher: str = "human",
                         teacher_params: Mapping[str, Any] | None = None,
                         config: Mapping[str, Any] | None = None,
                         instruction: str | None = None, clip_size: str | None = None) -> Run:
    """A queued labelling-only run over `dataset` (a dataset export's folder, or its Minari id
    under `MINARI_DATASETS_PATH`). LabellingError (a ConfigError: its `field` names the input)
    for a dataset or a configuration no worker could serve; nothing is stored then."""
    return create_run(session, **labelling_run(
        labelling_dataset(dataset), budget=budget, per_round=per_round, selection=selection,
        segment_length=segment_length, name=name, preset=preset, seed=seed, teacher=teacher,
        teacher_params=teacher_params, config=config, instruction=instruction,
        clip_size=clip_size))


def labelling_run(found: LabelledDataset, *, budget: int, per_round: int | None = None,
                  selection: str = "disagreement", segment_length: int | None = None,
                  name: str | None = None, preset: str = "small", seed: int = 0,
                  teacher: str = "human", teacher_params: Mapping[str, Any] | None = None,
                  config: Mapping[str, Any] | None = None, instruction: str | None = None,
                  clip_size: str | None = None) -> dict[str, Any]:
    """`create_run`'s arguments for a labelling-only run over the checked dataset `found`,
    checked as `create_run` checks them, without a database: LabellingError naming a bad
    input, Invalid for a bad instruction or clip size."""
    if budget < 1:
        raise LabellingError("feedback.budget", f"budget {budget}: give at least 1 answer")
    if per_round is not None and per_round < 1:
        raise LabellingError("feedback.per_round", f"per round {per_round}: give at least 1")
    if name is not None and not 1 <= len(name) <= NAME_MAX:
        raise LabellingError("name", f"name {name!r}: give 1 to {NAME_MAX} characters")
    if name is not None:  # stored as POST /api/runs/labelling stores it
        try:
            name = filled(name, f"name {name!r}")
        except ValueError as err:
            raise LabellingError("name", str(err)) from None
    overrides = labelling_config(found, per_round=per_round, selection=selection,
                                 segment_length=segment_length, preset=preset, config=config)
    path = Path(found.path).resolve()
    fields: dict[str, Any] = {
        "name": name or f"label {found.info.get('dataset_id') or path.name}",
        "task": found.task, "algo": LABELLING_ALGO, "budget": budget, "preset": preset,
        "seed": seed, "teacher": teacher, "teacher_params": teacher_params,
        "config": overrides, "instruction": instruction, "clip_size": clip_size,
        "dataset": str(path)}
    checked_instruction(instruction)
    checked_clip_size(clip_size)
    resolve(task=found.task, algo=LABELLING_ALGO, preset=preset, seed=seed, budget=budget,
            teacher_params=teacher_params or {}, config=overrides)
    return fields
