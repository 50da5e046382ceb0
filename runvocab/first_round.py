"""When a run's first feedback round opens, worked out from its configuration: what the server
tells an operator before a run starts, and what the training loop does.

Rounds open at episode ends. The PEBBLE family asks after its random and unsupervised steps
(at least two finished episodes); S-EPOA after its initial rollouts, each an episode of its
own (or at step 0 when they are played before it, uncounted: `skill.free_initial_rollouts`);
the SAC oracle never asks (0).
"""

from __future__ import annotations

from runvocab.config import RunConfig
from runvocab.names import task_family

EPISODE_LENGTH = {"dmc": 1000, "metaworld": 500}
"""each task family's own episode length, in steps"""


def episode_length(cfg: RunConfig) -> int:
    """Steps per episode of the run: its own, or its task family's."""
    return cfg.episode_length or EPISODE_LENGTH[task_family(cfg.task)]


def first_round_step(cfg: RunConfig) -> int:
    """The step at which the run's first round opens (with its budget unspent)."""
    if cfg.algo == "sac":
        return 0
    length = episode_length(cfg)
    if cfg.algo == "sepoa":
        if cfg.skill.free_initial_rollouts:
            return 0
        episodes = max(2, cfg.skill.initial_rollouts)
        return max(_episode_end(cfg.seed_steps, length), episodes * length)
    return max(_episode_end(cfg.seed_steps + cfg.unsup_steps, length), 2 * length)


def _episode_end(step: int, length: int) -> int:
    """The first episode end at or after `step`."""
    return -(-step // length) * length
