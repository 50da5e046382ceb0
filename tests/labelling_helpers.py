"""A small dataset export to label: real episodes of a task, written by the project's own
dataset export, for the tests of labelling-only runs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from labelqueue import create_run, make_engine, migrate, session_factory
from rundata.dataset import INFO_FILE, write_dataset
from rundata.episodes import StoredEpisode, episodes_dir, write_episode

TASK = "dmc:cheetah_run"


def exported_dataset(folder: Path, *, episodes: int = 4, length: int = 60,
                     dataset_id: str = "sepoa/dmc-cheetah_run/source-v0", seed: int = 0,
                     task: str = TASK, data_format: str = "arrow") -> Path:
    """`episodes` random-action episodes of `task` (cheetah) of `length` steps, kept in a run's
    episode store as a worker keeps them and exported with `write_dataset` under `folder` (a
    Minari datasets folder, in Minari's `data_format`); the dataset's path. Its source run, in a
    database of its own, has no labels: the dataset is unlabelled."""
    from trainer.envs import make_env

    source = folder.parent / f"{folder.name}-source"
    url = f"sqlite:///{source / 'queue.db'}"
    source.mkdir(parents=True)
    migrate(url)
    engine = make_engine(url)
    sessions = session_factory(engine)
    with sessions() as session:
        run = create_run(session, name="source", task=task, algo="pebble", preset="tiny",
                         budget=1, teacher="scripted")
    store = episodes_dir(source / "clips", run.id)
    rng = np.random.default_rng(seed)
    with make_env(task, seed, length) as env:
        for trajectory in range(episodes):
            observations, states = [env.reset()], [env.physics_state()]
            actions, rewards = [], []
            for _ in range(length):
                action = rng.uniform(-1, 1, env.action_dim).astype(np.float32)
                step = env.step(action)
                actions.append(action)
                rewards.append(step.reward)
                observations.append(step.obs)
                states.append(env.physics_state())
            write_episode(store, StoredEpisode(
                trajectory=trajectory, observations=np.array(observations, np.float32),
                actions=np.array(actions), rewards=np.array(rewards, np.float32),
                states=np.array(states), context=env.episode_context(), success=False))
    with sessions() as session:
        summary = write_dataset(session, run_id=run.id, clips_root=source / "clips",
                                root=folder, dataset_id=dataset_id, data_format=data_format)
    engine.dispose()
    return summary.path


def edit_info(path: Path, **changes: object) -> None:
    """Change fields of a dataset's sepoa.json."""
    info = json.loads((path / INFO_FILE).read_text())
    (path / INFO_FILE).write_text(json.dumps(info | changes))


def drop_states(path: Path) -> None:
    """Rewrite a dataset's Minari episodes without their physics states (`infos["state"]`), as
    a dataset recorded elsewhere would come."""
    import shutil

    import gymnasium as gym
    import minari
    from minari import MinariDataset
    from minari.data_collector import EpisodeBuffer
    from minari.dataset.minari_storage import MinariStorage

    old = MinariDataset(path / "data")
    episodes = [EpisodeBuffer(id=int(e.id), observations=e.observations, actions=e.actions,
                              rewards=e.rewards, terminations=e.terminations,
                              truncations=e.truncations, infos={})
                for e in old.iterate_episodes()]
    obs, act = old.observation_space.shape, old.action_space.shape
    shutil.rmtree(path / "data")
    storage = MinariStorage.new(
        path / "data", observation_space=gym.spaces.Box(-np.inf, np.inf, obs, np.float32),
        action_space=gym.spaces.Box(-1.0, 1.0, act, np.float32), data_format="arrow")
    storage.update_metadata({"dataset_id": "sepoa/dmc-cheetah_run/source-v0",
                             "minari_version": minari.__version__})
    storage.update_episodes(episodes)


def malformed_copies(source: Path, folder: Path) -> dict[str, tuple[Path, str]]:
    """Copies of the dataset `source` under `folder`, each damaged in one way a dataset
    received from elsewhere can be: {case: (its path, what its one-line refusal says)}."""
    import shutil

    import pyarrow as pa
    import pyarrow.parquet as pq

    from rundata.dataset import QUERIES_FILE, QUERY_TABLE_COLUMNS

    def copy(name: str) -> Path:
        path = folder / name
        shutil.copytree(source, path)
        return path

    listed = copy("listed")
    (listed / INFO_FILE).write_text("[1, 2]")
    deep = copy("deep")
    (deep / INFO_FILE).write_text("[" * 100_000 + "]" * 100_000)
    strings = copy("strings")
    pq.write_table(pa.table({c: ["0"] for c in QUERY_TABLE_COLUMNS[:7]}),
                   strings / QUERIES_FILE)
    truncated = copy("truncated")
    part = truncated / "data" / "1" / "part-0.arrow"
    part.write_bytes(part.read_bytes()[:200])
    gone = copy("gone")
    shutil.rmtree(gone / "data" / "2")
    return {
        "long name": (folder / ("x" * 300), "cannot be read"),
        "sepoa.json a list": (listed, "sepoa.json: not a JSON object"),
        "sepoa.json too deep": (deep, "sepoa.json: not readable JSON"),
        "string columns": (strings, "queries.parquet: column query_id holds string values"),
        "truncated part": (truncated, "episode 1 cannot be read"),
        "missing episode": (gone, "episode 2 cannot be read"),
    }
