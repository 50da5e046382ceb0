"""A run as its checkpoint left it, resumed from a copy of its files: what the measuring scripts
(`skill_choice`, `reward_crosscheck`) act with, so that the run's own folder is only read."""

from __future__ import annotations

import dataclasses
import glob
import os
import shutil

from runvocab.config import RunConfig, load_json
from runvocab.snapshot_names import snapshot_path
from trainer.loop import CHECKPOINT, TrainingRun

RUN_FILES = (CHECKPOINT, "config.json", "labels.jsonl", "episodes.csv", "eval.csv", "rounds.csv")
"""what a resumed run reads; copied, so that the run's own folder is only read"""


def find_snapshot(cfg: RunConfig, run_dir: str) -> str:
    """The run's skill snapshot (the agent is built from it, then the checkpoint loaded): by its
    name, or else the one snapshot of its task, backend, length and seed (the name's digest
    covers configuration fields that other commits may name differently)."""
    path = snapshot_path(cfg)
    if os.path.exists(path):
        return path
    stem = os.path.basename(path).rsplit("-", 1)[0]
    found = glob.glob(os.path.join(glob.escape(cfg.skill.snapshot_dir), f"{stem}-*.pt"))
    if len(found) != 1:
        raise SystemExit(f"{run_dir}: its skill snapshot {path} is missing and "
                         f"{len(found)} others match {stem}-*.pt: name one with --snapshot")
    return found[0]


def resume_copy(run_dir: str, into: str, threads: int, snapshot: str = "") -> TrainingRun:
    """The run as its checkpoint left it, from a copy of its files in `into`, on the CPU."""
    if not os.path.exists(os.path.join(run_dir, CHECKPOINT)):
        raise SystemExit(f"{run_dir}: no {CHECKPOINT} (a finished run's is removed); give the "
                         "folder of a run that is training or was stopped")
    for name in RUN_FILES:
        if os.path.exists(os.path.join(run_dir, name)):
            shutil.copy(os.path.join(run_dir, name), into)
    cfg = load_json(os.path.join(into, "config.json"))
    cfg = dataclasses.replace(cfg, run_dir=into, threads=threads, device="cpu")
    if cfg.algo == "sepoa" and cfg.skill.pretrain_steps:
        cfg = dataclasses.replace(cfg, skill=dataclasses.replace(
            cfg.skill, snapshot=snapshot or find_snapshot(cfg, run_dir)))
    return TrainingRun(cfg, resume=True, progress=False)
