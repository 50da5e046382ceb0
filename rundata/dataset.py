"""A run's data as a Minari dataset, with its preference labels as tables that point into it.

    write_dataset(session, run_id=3, clips_root=Path("data/clips"), root=Path("datasets"))

writes `datasets/sepoa/dmc-cheetah_run/run-3-v0/`, a local Minari dataset (arrow storage, or
HDF5 with `data_format="hdf5"`; its `env_spec` names the task's environment,
`rundata.dataset_env`):

- `data/`: Minari's own files. One Minari episode per episode of the run that a query points
  into (the run's episode store, `rundata.episodes`), in the run's order: observations
  (T + 1), actions, true rewards, terminations (never: the project's episodes end by time),
  truncations (the last step), and per step `infos["state"]` (the physics state at each
  observation, so any segment renders again) and `infos["context"]` (Metaworld's goal variant),
  plus `infos["skill"]` for skill-based runs. The spaces are the task's: a float32 Box of the
  observation size and a [-1, 1] float32 Box of the action size.
- `labels.parquet`: one row per answer (the label export's columns, docs/EXPORT.md) plus
  `first_episode` and `second_episode`, the Minari episode ids the two segments come from.
- `queries.parquet`: one row per answered query: both sides' episode, start and length, and its
  aggregate answer (what a reward model trains on).
- `episodes.parquet`: per Minari episode, the run's trajectory number, length, return, success,
  context and skill.
- `sepoa.json`: the run (task, algorithm, preset, seed, training config) and the counts.

`minari.load_dataset("sepoa/dmc-cheetah_run/run-3-v0")` reads it with `MINARI_DATASETS_PATH`
set to the root, and needs nothing of this project. The dataset is written into a hidden
folder beside its destination and renamed into place when complete: an error leaves nothing.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import zipfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy.orm import Session

from labelqueue.errors import Invalid, NotFound
from labelqueue.export import QUERY_COLUMNS, SCHEMA_VERSION, export_rows
from labelqueue.models import Run
from labelqueue.transaction import reading
from rundata.dataset_env import env_spec, requirements
from rundata.episodes import (
    StoredEpisode,
    episode_path,
    episodes_dir,
    read_episode,
    stored_trajectories,
)
from runvocab.config import to_dict
from runvocab.names import ConfigError
from runvocab.queued_run import queued_run_config

DATASET_VERSION = 1
"""the version of this layout (the files beside Minari's `data/` and their columns)"""
LABELS_FILE, QUERIES_FILE, EPISODES_FILE, INFO_FILE = (
    "labels.parquet", "queries.parquet", "episodes.parquet", "sepoa.json")
EPISODE_COLUMNS = ("first_episode", "second_episode")
"""the columns a label row gets besides the label export's"""
QUERY_TABLE_COLUMNS = (
    ("query_id", "first_episode", "first_start", "second_episode", "second_start",
     "segment_length", "aggregate", "query_answers", "labels_per_query")
    + tuple(c.name for c in QUERY_COLUMNS
            if c.name not in ("first_start", "second_start", "segment_length")))
"""queries.parquet's columns: the pointers and the aggregate first, then the query's fields"""
DATA_FORMATS = ("arrow", "hdf5")
"""Minari's storage formats: arrow (the default), or HDF5, which TorchRL's
`MinariExperienceReplay` reads (it reads no other)"""


class DatasetError(Invalid):
    """The dataset cannot be written or read as asked; the message says why, in one line."""


class NoEpisodes(DatasetError):
    """The run kept no episodes to export."""


@dataclass(frozen=True)
class DatasetSummary:
    path: Path
    """the dataset's folder (`root/dataset_id`)"""
    dataset_id: str
    episodes: int
    steps: int
    labels: int
    queries: int
    labels_left_out: int
    """labels whose episodes the run's store does not hold (a run trained before episodes were
    kept): not in the tables"""


def default_dataset_id(task: str, run_id: int) -> str:
    """`sepoa/<task>/run-<id>-v0`, e.g. `sepoa/dmc-cheetah_run/run-3-v0`: in the task, each
    character a Minari id does not take (':', '.', an external run's any other) as '-'."""
    name = re.sub(r"[^-_A-Za-z0-9]", "-", task)
    return f"sepoa/{name}/run-{run_id}-v0"


def check_dataset_id(dataset_id: str) -> str:
    from minari.dataset.minari_dataset import (  # type: ignore[import-untyped]
        DATASET_ID_RE,
    )

    match = DATASET_ID_RE.fullmatch(dataset_id)
    if match is None or match.group("version") is None:
        raise DatasetError(f"dataset id {dataset_id!r} is not a Minari id: give "
                           "[namespace/]name-v<version>, e.g. sepoa/cheetah/run-3-v0")
    if not dataset_id.isascii():  # Minari takes any letter; a file name in a header, latin-1
        raise DatasetError(f"dataset id {dataset_id!r}: use ASCII letters, digits, '-', '_' "
                           "and '/' only")
    if ".." in dataset_id.split("/"):
        raise DatasetError(f"dataset id {dataset_id!r} may not contain '..'")
    return dataset_id


def write_dataset(session: Session, *, run_id: int, clips_root: Path, root: Path,
                  dataset_id: str | None = None, data_format: str = "arrow") -> DatasetSummary:
    """Write run `run_id`'s episodes and labels as the Minari dataset `root/<dataset_id>`, in
    Minari's `data_format` (`DATA_FORMATS`).

    NotFound for an unknown run; DatasetError when it has no stored episodes, the destination
    exists, or the episodes disagree with each other. Nothing is left behind on an error."""
    if data_format not in DATA_FORMATS:
        raise DatasetError(f"format {data_format!r}: a dataset is stored as "
                           f"{' or '.join(DATA_FORMATS)}")
    with reading(session):
        run = session.get(Run, run_id)
        if run is None:
            raise NotFound(f"run {run_id} does not exist")
        info = _run_info(run)
    dataset_id = check_dataset_id(dataset_id or default_dataset_id(info["task"], run_id))
    # Absolute: Minari 0.5.4's arrow storage doubles a relative path as it writes the episodes.
    final = Path(root).absolute() / dataset_id
    if final.exists():
        raise DatasetError(f"{final} already exists; remove it or give another dataset id")
    # The labels first: a round's episodes are stored before its queries reach the queue, so
    # every label read now points into episodes the listing below finds.
    rows = list(export_rows(session, run_id=run_id))
    folder = episodes_dir(clips_root, run_id)
    trajectories = stored_trajectories(folder)
    if not trajectories:
        raise NoEpisodes(
            f"run {run_id} has no stored episodes in {folder}: a run keeps the episodes its "
            "queries point into from its first round on (runs trained before this version "
            "kept none)")
    made = [p for p in reversed(final.parents) if not p.exists()]
    tmp = final.parent / f".{final.name}.partial-{os.getpid()}"
    try:
        tmp.mkdir(parents=True)
        summary = _write(tmp, final, dataset_id, info, folder, trajectories, rows,
                         data_format)
        os.rename(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        for parent in reversed(made):  # the folders made for it, when still empty
            try:
                parent.rmdir()
            except OSError:
                break
        raise
    return summary


READ_ERRORS = (zipfile.BadZipFile, KeyError, ValueError, EOFError, OSError)
"""what NumPy raises for a damaged .npz: truncated, not a zip, an array missing or cut short"""


def _read_episode(folder: Path, trajectory: int) -> StoredEpisode:
    try:
        return read_episode(folder, trajectory)
    except READ_ERRORS as err:
        reason = " ".join(str(err).split()) or type(err).__name__
        raise DatasetError(
            f"{episode_path(folder, trajectory)} cannot be read ({reason}): the file is damaged; "
            "restore it from a copy, or move it away to export without the labels that point "
            "into it") from None


def _run_info(run: Run) -> dict[str, Any]:
    try:
        config: dict[str, Any] | None = to_dict(queued_run_config(
            task=run.task, algo=run.algo, preset=run.preset, seed=run.seed, budget=run.budget,
            teacher_params=run.teacher_params, config=run.config))
    except ConfigError:  # a run stored by an older version whose config no longer builds
        config = None
    return {"run_id": run.id, "run_name": run.name, "task": run.task, "algo": run.algo,
            "preset": run.preset, "seed": run.seed, "teacher": str(run.teacher),
            "status": str(run.status), "config": config, "source_dataset": run.dataset}


def _write(tmp: Path, final: Path, dataset_id: str, info: dict[str, Any], folder: Path,
           trajectories: list[int], rows: list[dict[str, Any]],
           data_format: str) -> DatasetSummary:
    import gymnasium as gym
    from minari import __version__ as minari_version  # type: ignore[import-untyped]
    from minari.dataset.minari_storage import MinariStorage  # type: ignore[import-untyped]

    episodes = [_read_episode(folder, t) for t in trajectories]
    _check_shapes(episodes, folder)
    first = episodes[0]
    obs_dim, action_dim = first.observations.shape[1], first.actions.shape[1]
    lengths = {e.length for e in episodes}
    storage = MinariStorage.new(
        tmp / "data",
        observation_space=gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32),
        action_space=gym.spaces.Box(-1.0, 1.0, (action_dim,), np.float32),
        env_spec=env_spec(info["task"], lengths.pop() if len(lengths) == 1 else None),
        data_format=data_format)
    storage.update_metadata({
        "dataset_id": dataset_id,
        "algorithm_name": f"sepoa {info['algo']}",
        "description": (
            f"Episodes of S-EPOA run {info['run_id']} ({info['run_name']}): {info['task']}, "
            f"{info['algo']}, preset {info['preset']}, seed {info['seed']}; the episodes its "
            "preference queries point into. Rewards are the task's true rewards; "
            "infos['state'] is the physics state at each observation. Labels: "
            f"{LABELS_FILE} and {QUERIES_FILE} beside data/."),
        "requirements": requirements(info["task"]),
        "minari_version": minari_version,
    })
    storage.update_episodes(_buffers(episodes))

    index = {t: i for i, t in enumerate(trajectories)}
    labels, left_out = _label_rows(
        rows, index, {t: e.length for t, e in zip(trajectories, episodes, strict=True)})
    queries = _query_rows(labels)
    _write_tables(tmp, labels, queries, episodes)
    steps = sum(e.length for e in episodes)
    counts = {"episodes": len(episodes), "steps": steps, "labels": len(labels),
              "queries": len(queries), "labels_left_out": left_out}
    (tmp / INFO_FILE).write_text(json.dumps(
        {"dataset_version": DATASET_VERSION, "label_schema_version": SCHEMA_VERSION,
         "dataset_id": dataset_id, "obs_dim": obs_dim, "action_dim": action_dim,
         "state_dim": first.states.shape[1]} | info | counts, indent=2) + "\n")
    return DatasetSummary(path=final, dataset_id=dataset_id, **counts)


def _check_shapes(episodes: list[StoredEpisode], folder: Path) -> None:
    first = episodes[0]
    for e in episodes:
        t = e.length
        shapes = (e.observations.shape, e.actions.shape, e.states.shape)
        want = ((t + 1, first.observations.shape[1]), (t, first.actions.shape[1]),
                (t + 1, first.states.shape[1]))
        if shapes != want:
            raise DatasetError(f"{folder}: episode {e.trajectory} has observations, actions "
                               f"and states of shapes {shapes}, expected {want}")


def _buffers(episodes: list[StoredEpisode]) -> list[Any]:
    from minari.data_collector import EpisodeBuffer  # type: ignore[import-untyped]

    out = []
    for i, e in enumerate(episodes):
        t = e.length
        # The context as a list: Minari's arrow storage cannot read back a 1-D array in infos.
        infos: dict[str, Any] = {"state": e.states, "context": [e.context] * (t + 1)}
        if e.skill is not None:
            infos["skill"] = np.repeat(e.skill[None].astype(np.float32), t + 1, axis=0)
        truncations = np.zeros(t, bool)
        truncations[-1] = True
        out.append(EpisodeBuffer(
            id=i, observations=e.observations, actions=e.actions,
            rewards=e.rewards.astype(np.float64), terminations=np.zeros(t, bool),
            truncations=truncations, infos=infos))
    return out


def _label_rows(rows: list[dict[str, Any]], index: dict[int, int],
                lengths: dict[int, int]) -> tuple[list[dict[str, Any]], int]:
    kept, left_out = [], 0
    for row in rows:
        sides = [(row[f"{side}_trajectory"], row[f"{side}_start"])
                 for side in ("first", "second")]
        if any(t not in index for t, _ in sides):
            left_out += 1
            continue
        for t, start in sides:
            if not 0 <= start <= lengths[t] - row["segment_length"]:
                raise DatasetError(f"label {row['label_id']}: its segment at step {start} of "
                                   f"trajectory {t} runs past the episode's {lengths[t]} steps")
        kept.append(row | {"first_episode": index[sides[0][0]],
                           "second_episode": index[sides[1][0]]})
    return kept, left_out


def _query_rows(labels: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    by_query: dict[int, dict[str, Any]] = {}
    for row in labels:
        by_query.setdefault(row["query_id"], {c: row[c] for c in QUERY_TABLE_COLUMNS})
    return list(by_query.values())


def _write_tables(tmp: Path, labels: list[dict[str, Any]], queries: list[dict[str, Any]],
                  episodes: list[StoredEpisode]) -> None:
    import pyarrow as pa  # type: ignore[import-untyped]
    import pyarrow.parquet as pq  # type: ignore[import-untyped]

    from rundata.label_files import parquet_schema

    meta = {"sepoa.dataset.version": str(DATASET_VERSION)}
    base = parquet_schema()
    label_schema = pa.schema(
        list(base) + [pa.field(c, pa.int64()) for c in EPISODE_COLUMNS],
        metadata=base.metadata | meta)
    pq.write_table(pa.Table.from_pylist(labels, schema=label_schema), tmp / LABELS_FILE)
    by_name = {f.name: f for f in label_schema}
    query_schema = pa.schema([by_name[c] for c in QUERY_TABLE_COLUMNS], metadata=meta)
    pq.write_table(pa.Table.from_pylist(queries, schema=query_schema), tmp / QUERIES_FILE)
    episode_rows = [{
        "episode_id": i, "trajectory": e.trajectory, "length": e.length,
        "return": float(e.rewards.sum(dtype=np.float64)), "success": e.success,
        "context": e.context,
        "skill": None if e.skill is None else [float(x) for x in e.skill],
        "final_resimulated": e.final_resimulated,
    } for i, e in enumerate(episodes)]
    episode_schema = pa.schema([
        pa.field("episode_id", pa.int64()), pa.field("trajectory", pa.int64()),
        pa.field("length", pa.int64()), pa.field("return", pa.float64()),
        pa.field("success", pa.bool_()), pa.field("context", pa.int64()),
        pa.field("skill", pa.list_(pa.float64())), pa.field("final_resimulated", pa.bool_()),
    ], metadata=meta)
    pq.write_table(pa.Table.from_pylist(episode_rows, schema=episode_schema),
                   tmp / EPISODES_FILE)


# -- reading ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DatasetEpisode:
    observations: np.ndarray
    """(T + 1, obs_dim) float32"""
    actions: np.ndarray
    """(T, action_dim) float32"""
    rewards: np.ndarray
    """(T,) float32 true rewards"""
    states: np.ndarray
    """(T + 1, state_dim) float64"""
    context: int

    @property
    def length(self) -> int:
        return len(self.rewards)


@dataclass(frozen=True)
class LabelledDataset:
    """A dataset export read back: its episodes, its answered queries and its run's info."""

    path: Path
    info: dict[str, Any]
    """sepoa.json"""
    episodes: list[DatasetEpisode]
    queries: list[dict[str, Any]]
    """queries.parquet's rows, each pointing inside its episodes"""

    @property
    def task(self) -> str:
        return str(self.info["task"])


def resolve_dataset(name: str) -> Path:
    """A dataset export's folder from a path, or from a Minari id under the Minari datasets
    folder (`MINARI_DATASETS_PATH`, else ~/.minari/datasets)."""
    path = Path(name)
    if _is_dir(path, name):
        return path
    root = os.environ.get("MINARI_DATASETS_PATH") or str(Path.home() / ".minari" / "datasets")
    if ".." not in name.split("/") and _is_dir(Path(root) / name, name):
        return Path(root) / name
    raise DatasetError(f"no dataset at {name}: give a dataset folder (sepoa export --dataset) "
                       f"or a Minari dataset id under {root}")


def read_dataset(name: str) -> LabelledDataset:
    """Read and check a dataset export; DatasetError naming the first problem."""
    import pyarrow.parquet as pq

    from runvocab.names import all_tasks

    path = resolve_dataset(name)
    info_path, queries_path = path / INFO_FILE, path / QUERIES_FILE
    for needed in (info_path, queries_path, path / "data"):
        if not needed.exists():
            raise DatasetError(f"{path} is not a dataset export of this project: no "
                               f"{needed.name} (sepoa export --dataset writes one)")
    try:
        info = json.loads(info_path.read_text())
    except (OSError, ValueError, RecursionError) as err:
        raise DatasetError(f"{info_path}: not readable JSON ({err})") from None
    if not isinstance(info, dict):
        raise DatasetError(f"{info_path}: not a JSON object (sepoa export --dataset writes one "
                           f"with the run's task and sizes), but a {type(info).__name__}")
    task = info.get("task")
    if not isinstance(task, str) or task not in all_tasks():
        raise DatasetError(f"{path}: task {task!r} is not one this project knows "
                           "(sepoa tasks lists them)")
    episodes = _read_minari(path, info)
    try:
        table = pq.read_table(queries_path)
    except Exception as err:  # noqa: BLE001 - pyarrow raises several kinds for a bad file
        raise DatasetError(f"{queries_path}: not a readable Parquet table ({err})") from None
    _check_query_columns(table, queries_path)
    queries = table.to_pylist()
    for row in queries:
        for side in ("first", "second"):
            episode, start = row[f"{side}_episode"], row[f"{side}_start"]
            length = row["segment_length"]
            if episode is None or not 0 <= episode < len(episodes):
                raise DatasetError(f"{queries_path}: query {row['query_id']}'s {side} segment "
                                   f"points at episode {episode}, but the dataset has episodes "
                                   f"0 to {len(episodes) - 1}")
            if start is None or length is None or not (
                    0 <= start and 1 <= length and start + length <= episodes[episode].length):
                raise DatasetError(f"{queries_path}: query {row['query_id']}'s {side} segment "
                                   f"[{start}, {start} + {length}) lies outside episode "
                                   f"{episode}'s {episodes[episode].length} steps")
    return LabelledDataset(path=path, info=info, episodes=episodes, queries=queries)


def _is_dir(path: Path, name: str) -> bool:
    try:
        return path.is_dir()
    except (OSError, ValueError) as err:  # a name the system refuses: too long, a NUL byte
        raise DatasetError(f"dataset {name[:100]!r} cannot be read: "
                           f"{getattr(err, 'strerror', None) or err}") from None


def _check_query_columns(table: Any, queries_path: Path) -> None:
    import pyarrow as pa

    pointers = QUERY_TABLE_COLUMNS[:7]
    missing = [c for c in pointers if c not in table.column_names]
    if missing:
        raise DatasetError(f"{queries_path}: columns {missing} are missing")
    # The ids, episodes, starts and length, then the round a fit replays (`sepoa reward fit`).
    for column in (*pointers[:6], "round"):
        if column not in table.column_names:
            raise DatasetError(f"{queries_path}: column {column} is missing")
        kind = table.schema.field(column).type
        if not (pa.types.is_integer(kind) or pa.types.is_null(kind)):
            raise DatasetError(f"{queries_path}: column {column} holds {kind} values; "
                               "it holds integers in an export (docs/EXPORT.md)")


def _read_minari(path: Path, info: dict[str, Any]) -> list[DatasetEpisode]:
    from minari import MinariDataset

    try:
        dataset = MinariDataset(path / "data")
    except Exception as err:  # noqa: BLE001 - Minari raises several kinds for a bad folder
        raise DatasetError(f"{path / 'data'}: not a readable Minari dataset ({err})") from None
    obs_shape, action_shape = dataset.observation_space.shape, dataset.action_space.shape
    if (obs_shape, action_shape) != ((info.get("obs_dim"),), (info.get("action_dim"),)):
        raise DatasetError(
            f"{path}: the Minari spaces (observations {obs_shape}, actions {action_shape}) do "
            f"not match sepoa.json (obs_dim {info.get('obs_dim')}, action_dim "
            f"{info.get('action_dim')})")
    episodes = []
    for index in dataset.episode_indices:
        try:  # Minari reads an episode's files only now
            [episode] = dataset.iterate_episodes([int(index)])
        except Exception as err:  # noqa: BLE001 - pyarrow, h5py and the OS raise several kinds
            raise DatasetError(f"{path}: episode {index} cannot be read "
                               f"({_first_line(err)})") from None
        infos = episode.infos
        if "state" not in infos:
            raise DatasetError(f"{path}: episode {episode.id} has no physics states "
                               "(infos['state'])")
        t = len(episode.actions)
        if episode.observations.shape != (t + 1, *obs_shape) or len(infos["state"]) != t + 1:
            raise DatasetError(f"{path}: episode {episode.id} has observations "
                               f"{episode.observations.shape} and states "
                               f"{infos['state'].shape} for {t} actions; expected {t + 1} each")
        context = infos.get("context")
        episodes.append(DatasetEpisode(
            observations=np.asarray(episode.observations, np.float32),
            actions=np.asarray(episode.actions, np.float32),
            rewards=np.asarray(episode.rewards, np.float32),
            states=np.asarray(infos["state"], np.float64),
            context=int(context[0]) if context is not None else 0))
    if not episodes:
        raise DatasetError(f"{path}: the Minari dataset holds no episodes")
    return episodes


def _first_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0][:300]}" if text else type(err).__name__
