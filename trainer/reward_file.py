"""A fitted reward ensemble on disk: what `sepoa reward fit` saves and `reward.init_from` starts
a run's reward model from."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import torch
from torch import nn

from runvocab.config import RewardConfig

MODEL_FORMAT = "sepoa.reward_model"
MODEL_VERSION = 1


def save_ensemble(path: str, ensemble: nn.Module, cfg: RewardConfig, *, task: str, obs_dim: int,
                  action_dim: int, dataset: str, fit: dict[str, Any]) -> None:
    """Write the ensemble's weights with what they were fitted on, under a temporary name first."""
    state: dict[str, Any] = {
        "format": MODEL_FORMAT, "version": MODEL_VERSION, "task": task,
        "obs_dim": obs_dim, "action_dim": action_dim, "reward": dataclasses.asdict(cfg),
        "ensemble": ensemble.state_dict(), "dataset": dataset, "fit": fit,
    }
    tmp = f"{path}.partial"
    try:
        torch.save(state, tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def load_saved(path: str | Path) -> dict[str, Any]:
    """A saved reward model's contents; ValueError naming what is wrong with the file."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise ValueError(f"reward.init_from: no file {path}") from None
    except Exception as err:  # noqa: BLE001 - torch raises several kinds for a bad file
        raise ValueError(f"reward.init_from: {path} is not a saved reward model ({err})") \
            from None
    if not isinstance(state, dict) or state.get("format") != MODEL_FORMAT:
        raise ValueError(f"reward.init_from: {path} is not a reward model from sepoa reward fit")
    return state


def load_ensemble(ensemble: nn.Module, cfg: RewardConfig, path: str, obs_dim: int,
                  action_dim: int) -> None:
    """Start `ensemble` from the weights saved at `path`; ValueError when their shape differs
    from the run's."""
    state = load_saved(path)
    saved = state["reward"]
    want = (obs_dim, action_dim, cfg.ensemble_size, cfg.hidden_layers, cfg.hidden_dim)
    have = (state["obs_dim"], state["action_dim"], saved["ensemble_size"],
            saved["hidden_layers"], saved["hidden_dim"])
    if have != want:
        def shape(s: tuple) -> str:
            return (f"{s[2]} members of {s[3]} x {s[4]} on {s[0]} observations and {s[1]} "
                    "actions")
        raise ValueError(f"reward.init_from: {path} holds {shape(have)} ({state['task']}); "
                         f"this run's reward model is {shape(want)}")
    ensemble.load_state_dict(state["ensemble"])
