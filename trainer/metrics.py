"""Metrics sinks: one CSV file per stream (episodes, evaluation, rounds) and TensorBoard."""

from __future__ import annotations

import csv
import os
from collections.abc import Callable
from typing import Any

from torch.utils.tensorboard import SummaryWriter


class CSVStream:
    """Appends rows to a CSV file. A row with a column the file lacks widens the file (rare:
    a metric that appears mid-run); a missing column is written empty."""

    def __init__(self, path: str):
        self.path = path
        self.fields: list[str] | None = None
        if os.path.exists(path) and os.path.getsize(path) > 0:
            with open(path, newline="") as f:
                self.fields = next(csv.reader(f))

    def write(self, row: dict[str, Any]) -> None:
        new = self.fields is None
        fields = self.fields
        if fields is None:
            fields = self.fields = list(row)
        elif any(k not in fields for k in row):
            fields += [k for k in row if k not in fields]
            self.keep_rows(lambda r: True)
        with open(self.path, "a", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=fields, restval="")
            if new:
                writer.writeheader()
            writer.writerow(row)

    def keep_rows(self, keep: Callable[[dict[str, str]], bool]) -> None:
        """Rewrite the file with only the rows `keep` accepts (used when a run resumes)."""
        if self.fields is None:
            return
        with open(self.path, newline="") as f:
            rows = [r for r in csv.DictReader(f) if keep(r)]
        tmp = self.path + ".tmp"
        with open(tmp, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.fields)
            writer.writeheader()
            writer.writerows(rows)
        os.replace(tmp, self.path)


class Metrics:
    """The run's metric streams; `purge_step` drops TensorBoard events after a resume point."""

    STREAMS = ("episodes", "eval", "rounds")

    def __init__(self, run_dir: str, purge_step: int | None = None):
        self.streams = {
            name: CSVStream(os.path.join(run_dir, f"{name}.csv")) for name in self.STREAMS
        }
        self.tb = SummaryWriter(os.path.join(run_dir, "tb"), purge_step=purge_step)

    def log(self, stream: str, row: dict[str, Any]) -> None:
        self.streams[stream].write(row)
        step = int(row["step"])
        for key, value in row.items():
            if key != "step" and isinstance(value, int | float):
                self.tb.add_scalar(f"{stream}/{key}", value, step)

    def close(self) -> None:
        self.tb.close()
