"""Loads a dataset export with d3rlpy and TorchRL, as their users would, and prints what they
read as one JSON object. Run by tests/test_dataset_readers.py in the readers' own environment
(scripts/readers_env.sh), where nothing of this project is installed:

    python dataset_readers_check.py ARROW_ROOT HDF5_ROOT DATASET_ID TORCHRL_ROOT
"""

from __future__ import annotations

import json
import os
import sys
import warnings

import numpy as np


def main() -> None:
    arrow_root, hdf5_root, dataset_id, torchrl_root = sys.argv[1:5]
    out: dict[str, object] = {}

    import minari
    from d3rlpy.datasets import get_minari

    os.environ["MINARI_DATASETS_PATH"] = arrow_root
    buffer, _ = get_minari(dataset_id)
    out["d3rlpy_episodes"] = len(buffer.episodes)
    out["d3rlpy_transitions"] = buffer.transition_count

    # The environment Minari recovers from the export's env_spec, replayed from each episode's
    # first physics state with its actions: its observations must be the dataset's.
    dataset = minari.load_dataset(dataset_id)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        env = dataset.recover_environment()
    out["recover_warnings"] = [str(w.message) for w in caught
                               if "requirement" in str(w.message)
                               or "not installed" in str(w.message)]
    out["env_observation_shape"] = list(env.observation_space.shape)
    physics = env.unwrapped._env.physics
    worst, ends = 0.0, []
    for episode in dataset:
        env.reset(seed=0)
        with physics.reset_context():
            physics.set_state(episode.infos["state"][0][:physics.get_state().size])
        for t, action in enumerate(episode.actions):
            obs, _, terminated, truncated, _ = env.step(action)
            worst = max(worst, float(np.abs(obs - episode.observations[t + 1]).max()))
            if terminated or truncated:
                break
        ends.append([t + 1, bool(truncated)])
    out["replay_max_abs_diff"] = worst
    out["episode_ends"] = ends

    from torchrl.data.datasets.minari_data import MinariExperienceReplay

    os.environ["MINARI_DATASETS_PATH"] = hdf5_root
    replay = MinariExperienceReplay(dataset_id, batch_size=8, root=torchrl_root,
                                    download=False, load_from_local_minari=True)
    batch = replay.sample()
    out["torchrl_steps"] = len(replay)
    out["torchrl_observation_shape"] = list(batch["observation"].shape)
    out["torchrl_state_shape"] = list(batch["info", "state"].shape)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
