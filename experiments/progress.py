"""How fast a grid's runs train, and about how long the rest will take (`sepoa experiment status`).

A run's rate is environment steps per second of wall time, read from its own episodes.csv. A
run's late steps cost more than its early ones (each feedback round trains on every label so
far), so the time a run has left is, in this order of preference:
- the median, over the finished runs of its task and variant whose every episode row carries
  the phase clock's seconds, of the time those runs took from the step it has reached to their
  end;
- its steps to go at the median rate of the finished runs of its task and variant;
- its steps to go at its own rate so far, else at the median rate of its task and variant's
  started runs.
An S-EPOA run whose skill snapshot is not pretrained yet waits for its pretraining first
(`pretraining_left`), which its episode rows do not count; that time is added to the first run
of the grid that needs the snapshot.
An estimate: runs on another machine, or beside other work, train at other rates.
"""

from __future__ import annotations

import csv
import heapq
import json
import pickle
import statistics
from collections.abc import Iterable, Mapping
from pathlib import Path

from runvocab.config import RunConfig
from runvocab.snapshot_names import longer_pattern, name_prefix, snapshot_path, snapshot_seed


def episode_rows(folder: Path) -> list[dict[str, str]] | None:
    """The run's episodes.csv rows (the last may be cut short, being appended); None before
    the file exists."""
    path = folder / "episodes.csv"
    if not path.exists():
        return None
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def training_rate(folder: Path, rows: list[dict[str, str]] | None = None) -> float | None:
    """Steps per second over the run's episode rows (`rows`, else read from its folder): by
    their phase-clock `seconds_total` (every phase since the row before) where the rows carry
    it, else the last row's `fps` (the rate since its process started: after a resume, since
    the resume). None before the first row."""
    rows = episode_rows(folder) if rows is None else rows
    steps = seconds = 0.0
    previous, last_fps = 0, None
    for row in rows or []:
        try:  # the row being appended may be cut short
            step = int(float(row["step"]))
            total, fps = row.get("seconds_total"), row.get("fps")
            if total:
                steps, seconds = steps + step - previous, seconds + float(total)
            if fps:
                last_fps = float(fps)
        except (KeyError, TypeError, ValueError):
            continue
        previous = step
    if seconds > 0:
        return steps / seconds
    return last_fps if last_fps is not None and last_fps > 0 else None


ROUND_PROGRESS = "round-progress.pt"
"""trainer.round_progress's file, named here so that status needs no torch outside a round"""


def reward_epochs(folder: Path) -> tuple[int, int] | None:
    """Where the run's open round stands in its reward training: (epochs done, the run's
    `reward.max_epochs`), from the round's progress file (trainer/round_progress.py). None
    outside a round's training, in its first minute (before its first save), or where the file
    cannot be read (being replaced, say). A long round otherwise looks like a stuck run: its
    step does not move for as long as it trains."""
    path = folder / ROUND_PROGRESS
    if not path.exists():
        return None
    from trainer.checkpoint import load_checkpoint  # torch: imported only inside a round

    try:
        done = int(load_checkpoint(str(path))["state"]["training"]["epochs"])
        most = int(json.loads((folder / "config.json").read_text())["reward"]["max_epochs"])
    except (OSError, EOFError, pickle.UnpicklingError, RuntimeError, KeyError, TypeError,
            ValueError):
        return None
    return done, most


Clock = list[tuple[int, float]]
"""(step, seconds since the run began) at each of a run's episode rows"""


def training_clock(folder: Path, rows: list[dict[str, str]] | None = None) -> Clock | None:
    """The run's clock (from `rows`, else read from its folder), when every episode row
    carries the phase clock's `seconds_total`; None for a run without rows or with rows
    written before the clock."""
    rows = episode_rows(folder) if rows is None else rows
    if not rows:
        return None
    clock: Clock = []
    elapsed = 0.0
    for i, row in enumerate(rows):
        try:
            step, seconds = int(float(row["step"])), float(row["seconds_total"])
        except (KeyError, TypeError, ValueError):
            if i == len(rows) - 1:
                break  # the row being appended, cut short
            return None
        elapsed += seconds
        clock.append((step, elapsed))
    return clock or None


def seconds_after(clock: Clock, step: int) -> float:
    """The seconds a run with this clock took from `step` to its last row (linear between
    rows, from step 0 at 0 s)."""
    before_step, before_s = 0, 0.0
    for at, elapsed in clock:
        if at >= step:
            share = (step - before_step) / (at - before_step) if at > before_step else 1.0
            return clock[-1][1] - (before_s + share * (elapsed - before_s))
        before_step, before_s = at, elapsed
    return 0.0


def _last_rate(csv_path: Path) -> tuple[int, float] | None:
    """(step, steps per second) of a pretraining's metrics file at its last whole row (its `fps`:
    the rate since its process started or resumed); None without one."""
    step_rate = None
    try:
        with csv_path.open(newline="") as f:
            for row in csv.DictReader(f):
                try:
                    step_rate = int(float(row["step"])), float(row["fps"])
                except (KeyError, TypeError, ValueError):
                    continue  # the row being appended
    except OSError:
        return None
    return step_rate if step_rate is not None and step_rate[1] > 0 else None


def pretraining_left(runs: Iterable[tuple[str, RunConfig]]) -> dict[str, float | None]:
    """Per run key (`runs`: key and configuration, its `skill.snapshot_dir` where its worker
    keeps snapshots), the seconds of skill pretraining it waits for before its first step: 0
    for a run that needs none (not S-EPOA, no pretraining, its snapshot there, or a longer
    pretraining's snapshot on the way at its length, which `copy_from_longer` takes when its
    settings agree). A snapshot to pretrain is counted once, for the first run that needs it:
    its steps to go (from its metrics file, `<snapshot>.csv`, where it has begun) at its own
    rate, else at the median final rate of the folder's other pretrainings of the task and
    backend; None when there is none to go by."""
    left: dict[str, float | None] = {}
    counted: set[str] = set()
    for key, cfg in runs:
        left[key] = 0.0
        if cfg.algo != "sepoa" or cfg.skill.pretrain_steps <= 0:
            continue
        path = Path(snapshot_path(cfg))
        if path.exists() or str(path) in counted or (  # or what copy_from_longer would take
                not cfg.skill.snapshot
                and any(path.parent.glob(longer_pattern(cfg, snapshot_seed(cfg))))):
            continue
        counted.add(str(path))
        own = _last_rate(path.with_suffix(".csv"))
        others = [last[1] for other in sorted(path.parent.glob(f"{name_prefix(cfg)}*.csv"))
                  if other != path.with_suffix(".csv") and (last := _last_rate(other))]
        rate = own[1] if own else statistics.median(others) if others else None
        done = own[0] if own else 0
        left[key] = None if rate is None else max(cfg.skill.pretrain_steps - done, 0) / rate
    return left


class TimeLeft(dict[str, float | None]):
    """Per run key, the seconds it has left (0 when done; None when no run of its group has a
    rate); `by_rate` holds the unfinished runs estimated from rates, where no finished run of
    their group has a clock: a rate spreads the late, dearer rounds over every step, so those
    estimates run short for a run past its first steps."""

    def __init__(self) -> None:
        super().__init__()
        self.by_rate: set[str] = set()


def seconds_left(runs: Iterable[tuple[str, int, int, bool, float | None, Clock | None]]
                 ) -> TimeLeft:
    """Each run's time left. `runs`: (key, planned steps, steps reached, done, own rate, own
    clock), keys of the form `<group>/...` are grouped by everything before their last part
    (the seed's folder)."""
    runs = list(runs)
    group = {key: key.rsplit("/", 1)[0] for key, *_ in runs}
    finished: dict[str, list[float]] = {}
    started: dict[str, list[float]] = {}
    clocks: dict[str, list[Clock]] = {}
    for key, _, _, done, rate, clock in runs:
        if rate is not None:
            (finished if done else started).setdefault(group[key], []).append(rate)
        if done and clock is not None:
            clocks.setdefault(group[key], []).append(clock)
    left = TimeLeft()
    for key, planned, reached, done, rate, _ in runs:
        if done:
            left[key] = 0.0
            continue
        if group[key] in clocks:
            left[key] = statistics.median(seconds_after(c, reached) for c in clocks[group[key]])
            continue
        pool = finished.get(group[key]) or ([rate] if rate is not None else
                                            started.get(group[key]))
        left[key] = (max(planned - reached, 0) / statistics.median(pool)) if pool else None
        if pool:
            left.by_rate.add(key)
    return left


def duration_text(seconds: float) -> str:
    """`42s`, `5m07s`, `2h03m`: a duration in a table cell."""
    s = max(0, int(seconds))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{s % 3600 // 60:02d}m"


def summary(left: Mapping[str, float | None], workers: int, by_rate: int = 0,
            left_out: int = 0) -> str:
    """One line: the training time left over the unfinished runs, and over the workers now
    holding runs; `by_rate`: how many of the estimates came from rates (`TimeLeft.by_rate`);
    `left_out`: the runs a stop rule leaves out, which will not train (not in `left`)."""
    known = [s for s in left.values() if s is not None and s > 0]
    unknown = sum(s is None for s in left.values())
    out = f"{left_out} run(s) of seeds the stop rule left out, which will not train"
    if not known and not unknown:
        return "time left: none, every run is done" + (
            f" but {out}" if left_out else "")
    parts = []
    if known:
        total = sum(known)
        part = f"{duration_text(total)} of training over {len(known)} run(s)"
        if workers:
            # No sooner than the longest run alone, however many workers share the rest.
            wall = max(total / workers, max(known))
            part += f", about {duration_text(wall)} with the {workers} worker(s) training now"
        parts.append(part)
    if unknown:
        parts.append(f"{unknown} run(s) without an estimate yet (no run of their task and "
                     "variant has logged an episode)")
    if by_rate:
        parts.append(f"{by_rate} of them from average rates (no finished run of their variant "
                     "has the phase clock): likely short, as late steps hold the largest "
                     "feedback rounds")
    if left_out:
        parts.append(f"not counted: {out}")
    return "time left (estimated): " + "; ".join(parts)


def seeds_before_stop(hours: float, worked_s: float, workers: int, held: Iterable[float],
                      queued: Iterable[tuple[int, float]], started: Iterable[int]) -> str:
    """One line: which queued seeds a wall-time stop rule (`stop_after_hours`,
    `experiments.stop_rule`) lets start, at these estimates. The grid has trained `worked_s`;
    `workers` workers hold runs with `held` seconds left and then claim the `queued` runs
    (seed, seconds left) in the queue's order, each as soon as one comes free. A run of a
    seed already `started`, or started earlier in this replay, goes ahead whenever it comes; a
    seed's first run claimed once `hours` are spent leaves that seed out."""
    free = sorted(held)
    free = free + [0.0] * max(workers - len(free), 0)  # idle workers claim at once
    heapq.heapify(free)
    started = set(started)
    starting: dict[int, float] = {}
    left_out: dict[int, float] = {}
    for seed, seconds in queued:
        if seed in left_out:
            continue
        at = heapq.heappop(free)
        if seed not in started:
            if worked_s + at >= hours * 3600:
                left_out[seed] = worked_s + at
                heapq.heappush(free, at)
                continue
            started.add(seed)
            starting[seed] = worked_s + at
        heapq.heappush(free, at + seconds)
    if not starting and not left_out:
        return "forecast: no queued run of a seed not started"
    said = f"forecast, {workers} worker(s), these estimates: of the seeds not started, "
    rule = f"the stop rule's {hours:g} h"
    if starting:
        last, at = list(starting.items())[-1]
        said += (f"{_seed_list(starting)} {'starts' if len(starting) == 1 else 'start'} "
                 f"before {rule} (the last, {last}, at about {duration_text(at)})")
    else:
        said += f"none starts before {rule}"
    if not left_out:
        return said + ("; none is left out" if starting else "")
    first, at = next(iter(left_out.items()))
    return said + (f"; {_seed_list(left_out)} left out (seed {first} would start at "
                   f"about {duration_text(at)})")


def _seed_list(seeds: Iterable[int]) -> str:
    """`10-14, 16`: seeds in order, in runs of consecutive numbers."""
    spans: list[list[int]] = []
    for seed in sorted(seeds):
        if spans and seed == spans[-1][-1] + 1:
            spans[-1].append(seed)
        else:
            spans.append([seed])
    return ", ".join(f"{s[0]}-{s[-1]}" if len(s) > 1 else str(s[0]) for s in spans)
