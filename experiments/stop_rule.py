"""A grid's stop rule in wall time (`stop_after_hours` in its spec): no seed starts once the
grid's workers have trained that long, summed over its sessions (`experiments.sessions`).

A seed has started once any run of it has (its status is no longer queued, or its folder
exists); its other runs still train, so that every started seed can finish all its arms. Once
the hours are spent, the launcher stops each queued run of a seed not started (an operator's
stop: queued to stopped), at launch and while its workers train, and records the seeds it left
out in `<results>/<spec name>/stop_rule.json`, which the report reads. Running the spec again
leaves the stopped runs of the recorded seeds stopped (`experiments.queue.enqueue_spec`), and
the launcher applies the rule before its workers start, or before it returns without workers.
The rule is the whole grid's: a part launched alone (`Spec.only`: --seed, --variant) reads,
decides and records it over all the grid's runs.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from sqlalchemy.orm import Session, sessionmaker

from experiments.queue import grid_key, spec_rows, started_seeds
from experiments.sessions import worked
from experiments.spec import Spec
from labelqueue import InvalidTransition, Run, RunStatus, set_run_status

FILE = "stop_rule.json"


@dataclass(frozen=True)
class StopRule:
    hours: float
    worked_s: float
    seeds_not_started: tuple[int, ...]
    """seeds none of whose runs had started when the hours were spent (empty before)"""
    recorded: bool = False
    """the seeds come from the grid's stop_rule.json (fixed when the hours were first spent)"""

    @property
    def reached(self) -> bool:
        return self.worked_s >= self.hours * 3600

    def text(self, duration: Callable[[float], str]) -> str:
        """One line for status and the report."""
        rule = f"stop rule: no seed starts after {self.hours:g} h of the workers' training"
        if not self.reached:
            return f"{rule}; {duration(self.worked_s)} spent"
        left_out = ", ".join(map(str, self.seeds_not_started)) or "none"
        return f"{rule}; reached ({duration(self.worked_s)} spent): seeds not started: {left_out}"


def recorded_stop_rule(spec: Spec, folder: Path, now: datetime | None = None
                       ) -> StopRule | None:
    """The spec's stop rule as the grid's folder records it (its sessions and the seeds left
    out once the hours were spent), without the database; None for a spec without one."""
    if spec.stop_after_hours is None:
        return None
    period = worked(folder, now)
    spent = period.seconds if period else 0.0
    record = folder / FILE
    kept = json.loads(record.read_text()) if record.exists() else None
    if kept is not None and kept["hours"] == spec.stop_after_hours:  # a spec given other
        # hours since starts afresh
        return StopRule(spec.stop_after_hours, max(spent, spec.stop_after_hours * 3600),
                        tuple(kept["seeds_not_started"]), recorded=True)
    return StopRule(spec.stop_after_hours, spent, ())


def stop_rule(spec: Spec, sessions: sessionmaker[Session], results: Path,
              now: datetime | None = None) -> StopRule | None:
    """Where the spec's stop rule stands: the seeds it leaves out are those not started when
    the hours were first found spent; None for a spec without one."""
    spec = spec.whole
    rule = recorded_stop_rule(spec, results / spec.name, now)
    if rule is None or not rule.reached or rule.recorded:
        return rule
    return _leaving_out(rule, spec, spec_rows(spec, sessions), results)


def _leaving_out(rule: StopRule, spec: Spec, rows: dict[str, Run], results: Path) -> StopRule:
    """`rule`, just reached, with the seeds not started by now (`rows`: the spec's runs in the
    queue)."""
    started = started_seeds(spec, rows, results)
    return StopRule(rule.hours, rule.worked_s,
                    tuple(sorted({run.seed for run in spec.runs()} - started)))


def apply_stop_rule(spec: Spec, sessions: sessionmaker[Session], results: Path,
                    echo: Callable[[str], None]) -> StopRule | None:
    """Once the spec's hours are spent: stop every queued run of the seeds not started, and
    record them (the first time, with when). The rule as it stands; None without one."""
    spec = spec.whole  # a seed started in another part of the grid has started
    rule = recorded_stop_rule(spec, results / spec.name)  # the hours read once per check
    if rule is None or not rule.reached:
        return rule
    rows = spec_rows(spec, sessions)
    if not rule.recorded:
        rule = _leaving_out(rule, spec, rows, results)
    stopped, raced = 0, set()
    for seed in rule.seeds_not_started:
        queued = [row for run in spec.runs() if run.seed == seed
                  and (row := rows.get(grid_key(spec, run))) is not None
                  and row.status is RunStatus.QUEUED]
        done = []
        with sessions() as session:
            try:
                for row in queued:
                    set_run_status(session, run_id=row.id, status=RunStatus.STOPPED)
                    done.append(row)
            except InvalidTransition:  # a worker claimed one meanwhile: the seed started, and
                raced.add(seed)  # its other runs are queued again to finish it
                for row in done:
                    set_run_status(session, run_id=row.id, status=RunStatus.QUEUED)
                continue
        stopped += len(done)
    if raced and not rule.recorded:
        rule = StopRule(rule.hours, rule.worked_s,
                        tuple(s for s in rule.seeds_not_started if s not in raced))
    if not rule.recorded:
        (results / spec.name / FILE).write_text(json.dumps({
            "hours": rule.hours, "reached_at": datetime.now(UTC).isoformat(timespec="seconds"),
            "worked_s": round(rule.worked_s), "seeds_not_started": list(rule.seeds_not_started),
        }, indent=1) + "\n")
    if stopped:
        echo(f"{spec.name}: the stop rule's {rule.hours:g} h are spent: {stopped} queued run(s) "
             f"of seeds not started stopped ({', '.join(map(str, rule.seeds_not_started))})")
    return rule


WATCH_S = 60.0
"""how often the launcher checks the hours while its workers train"""


@contextmanager
def stop_rule_watch(spec: Spec, sessions: sessionmaker[Session], results: Path,
                    echo: Callable[[str], None], every_s: float = WATCH_S) -> Iterator[None]:
    """While the block runs (the launcher's workers train), apply the spec's stop rule every
    `every_s`; nothing for a spec without one."""
    if spec.stop_after_hours is None:
        yield
        return
    done = threading.Event()

    def watch() -> None:
        while not done.wait(every_s):
            try:
                apply_stop_rule(spec, sessions, results, echo)
            except Exception as error:  # a locked database or a full disk must not end the
                # watch, or the workers would train past the rule unnoticed
                echo(f"{spec.name}: the stop rule could not be checked ({type(error).__name__}: "
                     f"{error}); checking again in {every_s:g} s")

    watcher = threading.Thread(target=watch, name="stop-rule", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        done.set()
        watcher.join()
