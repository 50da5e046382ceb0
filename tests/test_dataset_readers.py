"""A dataset export read by the libraries docs/EXPORT.md names: the environment its env_spec
names (Shimmy's DMControl ids, Metaworld's MT1), Minari's HDF5 storage (`--format hdf5`), and
d3rlpy's `get_minari` and TorchRL's `MinariExperienceReplay` in an environment of their own
(scripts/readers_env.sh; SEPOA_READERS_PYTHON names its python, as scripts/test.sh does)."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from labelling_helpers import exported_dataset

from rundata.dataset import read_dataset

DATASET_ID = "sepoa/dmc-walker_walk/run-1-v0"
EPISODES, LENGTH = 3, 50
READERS_PYTHON = os.environ.get("SEPOA_READERS_PYTHON")


@pytest.fixture(scope="module")
def walker(tmp_path_factory) -> dict[str, Path]:
    """Three random-action walker_walk episodes (walker's observation parts are not in
    alphabetical order, which Shimmy's own dict space would put them in), exported in both
    storages under two datasets folders."""
    tmp = tmp_path_factory.mktemp("readers")
    return {fmt: exported_dataset(tmp / fmt, task="dmc:walker_walk", episodes=EPISODES,
                                  length=LENGTH, dataset_id=DATASET_ID, data_format=fmt)
            for fmt in ("arrow", "hdf5")}


def _load(path: Path, dataset_id: str):
    import minari

    root = str(path).removesuffix("/" + dataset_id)
    os.environ["MINARI_DATASETS_PATH"] = root
    try:
        return minari.load_dataset(dataset_id)
    finally:
        del os.environ["MINARI_DATASETS_PATH"]


def test_the_export_names_its_environment_and_only_what_that_needs(walker):
    dataset = _load(walker["arrow"], DATASET_ID)
    spec = dataset.env_spec
    assert spec.id == "dm_control/walker-walk-v0" and spec.max_episode_steps == LENGTH
    assert spec.kwargs["environment_kwargs"] == {"flat_observation": True}
    assert [w.name for w in spec.additional_wrappers] == ["FlattenObservation"]
    requirements = dataset.storage.metadata["requirements"]
    assert not [r for r in requirements if r.startswith("metaworld")]
    assert "shimmy[dm-control]>=2.0" in requirements


def test_hdf5_storage_holds_the_same_episodes(walker):
    arrow, hdf5 = (read_dataset(str(walker[f])) for f in ("arrow", "hdf5"))
    assert (hdf5.path / "data" / "main_data.hdf5").is_file()
    assert len(arrow.episodes) == len(hdf5.episodes) == EPISODES
    for a, h in zip(arrow.episodes, hdf5.episodes, strict=True):
        for field in ("observations", "actions", "rewards", "states"):
            np.testing.assert_array_equal(getattr(a, field), getattr(h, field))
        assert a.context == h.context


def test_a_metaworld_export_recovers_metaworlds_own_mt1_environment(tmp_path):
    dataset_id = "sepoa/metaworld-door-open/run-1-v0"
    path = exported_dataset(tmp_path / "datasets", task="metaworld:door-open", episodes=2,
                            length=20, dataset_id=dataset_id)
    dataset = _load(path, dataset_id)
    assert dataset.env_spec.id == "Meta-World/MT1"
    assert dataset.storage.metadata["requirements"] == ["mujoco==3.3.0", "metaworld==3.1.1"]
    env = dataset.recover_environment()
    assert env.observation_space.shape == dataset.observation_space.shape == (39,)
    env.reset(seed=0)
    for step in range(1, 21):
        *_, terminated, truncated, _ = env.step(env.action_space.sample())
        assert not terminated and truncated == (step == 20)


@pytest.mark.skipif(READERS_PYTHON is None,
                    reason="SEPOA_READERS_PYTHON unset (scripts/test.sh makes the readers' "
                    "environment with scripts/readers_env.sh and sets it)")
def test_d3rlpy_and_torchrl_read_the_export(walker, tmp_path):
    assert READERS_PYTHON is not None
    roots = [str(walker[f]).removesuffix("/" + DATASET_ID) for f in ("arrow", "hdf5")]
    script = Path(__file__).with_name("dataset_readers_check.py")
    done = subprocess.run(
        [READERS_PYTHON, str(script), *roots, DATASET_ID, str(tmp_path / "torchrl")],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
        env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"})
    assert done.returncode == 0, done.stderr[-3000:]
    read = json.loads(done.stdout.strip().splitlines()[-1])
    assert read["d3rlpy_episodes"] == EPISODES and read["d3rlpy_transitions"] > 0
    assert read["recover_warnings"] == []
    assert read["env_observation_shape"] == [24]
    assert read["replay_max_abs_diff"] < 1e-5  # float32 rounding of the same values
    assert read["episode_ends"] == [[LENGTH, True]] * EPISODES
    assert read["torchrl_steps"] == EPISODES * LENGTH
    assert read["torchrl_observation_shape"] == [8, 24]
    assert read["torchrl_state_shape"] == [8, 18]
