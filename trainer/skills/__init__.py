"""Unsupervised skill discovery with a SAC backbone: APS (S-EPOA's choice), DIAYN and CIC
behind one interface (`SkillBackend`), the skill-conditioned agent pi(a|s,z) they train
(`SkillAgent`), and, in `trainer.skills.pretrain`, the pretraining run and its snapshots."""

from __future__ import annotations

import dataclasses

import torch

from runvocab.config import SkillConfig
from runvocab.names import unknown
from trainer.skills.agent import SFCritic, SkillAgent, SkillReplayBuffer
from trainer.skills.aps import APS
from trainer.skills.cic import CIC
from trainer.skills.common import SkillBackend, SkillBatch, particle_entropy
from trainer.skills.diayn import DIAYN

SKILL_BACKENDS: dict[str, type[SkillBackend]] = {"aps": APS, "diayn": DIAYN, "cic": CIC}

__all__ = [
    "APS", "CIC", "DIAYN", "SKILL_BACKENDS", "SFCritic", "SkillAgent", "SkillBackend",
    "SkillBatch", "SkillReplayBuffer", "make_skill_backend", "particle_entropy",
    "resolve_skill_config",
]


def resolve_skill_config(cfg: SkillConfig) -> SkillConfig:
    """`cfg` with the backend's own values filled in where it says 0 (skill_dim,
    update_skill_every); a ValueError naming the valid backends for an unknown one."""
    if cfg.backend not in SKILL_BACKENDS:
        raise ValueError(unknown("skill.backend", cfg.backend, SKILL_BACKENDS))
    cls = SKILL_BACKENDS[cfg.backend]
    return dataclasses.replace(
        cfg,
        skill_dim=cfg.skill_dim or cls.default_skill_dim,
        update_skill_every=cfg.update_skill_every or cls.default_update_skill_every,
    )


def make_skill_backend(name: str, obs_dim: int, cfg: SkillConfig,
                       device: torch.device) -> SkillBackend:
    """The backend `name` (aps | diayn | cic) for observations of size `obs_dim`."""
    cfg = resolve_skill_config(dataclasses.replace(cfg, backend=name))
    return SKILL_BACKENDS[name](obs_dim, cfg, device)
