"""RUNE's exploration weight: the agent's reward is r_hat + beta_t * (the ensemble's std of
r_hat), an optimism bonus for what the reward model is unsure of, fading as training goes on.

    beta_t = beta_0 * (1 - rho)^t,  t = environment steps since the first feedback round closed

t counts environment steps, not gradient updates, and starts when the agent begins to train on
r_hat: before that there is no r_hat to be unsure of.
"""

from __future__ import annotations

from runvocab.config import RewardConfig


def rune_beta(cfg: RewardConfig, steps: int) -> float:
    """beta_t after `steps` environment steps of training on the learned reward."""
    return cfg.rune_beta0 * (1.0 - cfg.rune_decay) ** max(steps, 0)
