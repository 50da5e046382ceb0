"""One worker process's settings (`WorkerConfig`): its database, folders, name and pace."""

from __future__ import annotations

import os
import socket
from dataclasses import dataclass, field
from pathlib import Path

from trainer.clips import ClipConfig


@dataclass(frozen=True)
class WorkerConfig:
    """One worker process."""

    database_url: str
    """the queue database"""
    data_dir: Path
    """runs go to <data_dir>/runs/run-<id>, clips to <data_dir>/clips (or clips_dir)"""
    clips_dir: Path | None = None
    """where clips are written; the server must serve the same folder"""
    worker_id: str = field(default_factory=lambda: f"{socket.gethostname()}-{os.getpid()}")
    """this worker's name in the database"""
    poll_seconds: float = 2.0
    """how often an idle worker looks for a run, and a waiting one for labels"""
    heartbeat_seconds: float = 2.0
    """how often a training worker reports (and reads the operator's commands)"""
    once: bool = False
    """exit when no run is waiting, instead of polling forever"""
    device: str | None = None
    """overrides every run's device (auto | cpu | cuda)"""
    threads: int | None = None
    """overrides every run's torch CPU threads"""
    clip: ClipConfig = field(default_factory=ClipConfig)
    """how clips are rendered; a run's own `clip_size` replaces the width and height"""
    results_dir: Path | None = None
    """experiments' runs go to <results_dir>/<grid key> (default <data_dir>/results)"""

    @property
    def clips_root(self) -> Path:
        return self.clips_dir or self.data_dir / "clips"

    @property
    def results_root(self) -> Path:
        return self.results_dir or self.data_dir / "results"

