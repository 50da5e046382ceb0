"""`sepoa experiment run`: enqueue a spec's grid, then (by default) train it with local workers.

The one-host case stays one command: the launcher starts `workers` processes of `sepoa worker
--once` on the same database and results folder and waits for them; each claims runs until
none is waiting, so the grid is done when the last one exits (runs of other specs in the same
database are trained too). With no workers it only enqueues, for workers started elsewhere
(`sepoa experiment slurm`, `docker-compose up --scale worker=N`, or by hand).

Local workers get stable names, `<host>-exp-<slot>`, each slot held by a lock file under
`<results>/.workers/` while its launcher lives: a launcher started again after a kill takes the
same names, so its workers take their unfinished runs back at once and resume them from their
checkpoints; a second launcher on the same host gets other slots, never a live worker's name.
The workers die with their launcher (SIGTERM): each checkpoints its run and releases it, to
be resumed by the next launch. The database URL reaches them in their environment, never on
their command line (where `ps` would show a password). Starting and stopping them is the
caller's `train` (`sepoa experiment run` passes `sepoa.experiment_commands.train_locally`, which
holds them with the supervisor `sepoa up` uses), so this package starts no process itself.
"""

from __future__ import annotations

import fcntl
import socket
import sys
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import IO, Any

from experiments.queue import enqueue_spec, grid_key, shown_status, spec_rows
from experiments.sessions import recorded_session
from experiments.spec import Spec, SpecError
from experiments.stop_rule import apply_stop_rule, recorded_stop_rule, stop_rule_watch
from labelqueue import (
    RunStatus,
    make_engine,
    mask_url,
    migrate,
    session_factory,
    url_has_secret,
)

TrainLocally = Callable[[str, Path, int, int, Callable[[str], None]], "int | None"]
"""runs `workers` local workers on (url, results, workers, threads, echo) to their end; returns
the signal that stopped them, if one did"""


def default_database(results: Path) -> str:
    """The launcher's default queue: a SQLite file beside the results."""
    return f"sqlite:///{(results / 'queue.db').absolute()}"


@contextmanager
def worker_slots(results: Path, count: int) -> Iterator[list[str]]:
    """`count` worker names `<host>-exp-<slot>`, the lowest slots no live launcher holds."""
    folder = results / ".workers"
    folder.mkdir(parents=True, exist_ok=True)
    host = socket.gethostname()
    names: list[str] = []
    with ExitStack() as stack:
        slot = 0
        while len(names) < count:
            name = f"{host}-exp-{slot}"
            handle: IO[str] = stack.enter_context(open(folder / f"{name}.lock", "a"))
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                names.append(name)
            except BlockingIOError:
                pass
            slot += 1
        yield names


def _missing_sqlite(url: str) -> bool:
    from sqlalchemy.engine import make_url

    parsed = make_url(url)
    return parsed.get_backend_name() == "sqlite" and not Path(parsed.database or "").exists()


def worker_argv(results: Path, worker_id: str, threads: int,
                device: str | None = None) -> list[str]:
    """A local worker's command line; the database URL goes in its environment
    (SEPOA_DATABASE_URL)."""
    return [sys.executable, "-m", "sepoa", "worker", "--data-dir", str(results),
            "--results", str(results), "--worker-id", worker_id, "--threads", str(threads),
            "--once", "--poll-seconds", "1", *(["--device", device] if device else [])]


def run_experiment(spec: Spec, *, results: Path, database_url: str | None = None,
                   workers: int = 1, threads: int | None = None, force: bool = False,
                   dry_run: bool = False, echo: Callable[[str], None] = print,
                   train: TrainLocally | None = None) -> int:
    """Enqueue the grid and train it with `workers` local workers run by `train` (0: enqueue
    only). The exit status: 0 every run of the spec finished (or, without workers, enqueued),
    1 some did not, 128 + signal when stopped. SpecError for a redefined grid without
    `force`."""
    if workers and train is None:
        raise ValueError("local workers need `train`, which runs them")
    results = Path(results)
    url = database_url or default_database(results)
    threads = threads or spec.threads
    if dry_run and _missing_sqlite(url):  # nothing enqueued yet, and nothing to create
        echo(f"{spec.name}: {len(spec.runs())} runs; {len(spec.runs())} enqueued (no database "
             f"yet at {url}; dry run, nothing written)")
        return 0
    if not dry_run:
        results.mkdir(parents=True, exist_ok=True)
    migrate(url)
    engine = make_engine(url)
    sessions = session_factory(engine)
    try:
        recorded = recorded_stop_rule(spec.whole, results / spec.name)
        done = enqueue_spec(spec, sessions, results, force=force, dry_run=dry_run,
                            left_out=recorded.seeds_not_started
                            if recorded is not None and recorded.recorded else ())
        where = mask_url(url)
        finished = sum(s is RunStatus.FINISHED for s in done.present.values())
        echo(f"{spec.name}: {len(spec.runs())} runs; {len(done.created)} enqueued, "
             f"{len(done.requeued)} queued again, {len(done.replaced)} redefined, "
             f"{finished} finished, {len(done.present) - finished} queued or running"
             + (f", {len(done.adopted)} finished before (their folders' results kept)"
                if done.adopted else "")
             + (f", {len(done.left_out)} left out by the stop rule (stopped)"
                if done.left_out else "") + " "
             f"({where}{'; dry run, nothing written' if dry_run else ''})")
        if dry_run:
            return 0
        folder = results / spec.name
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "spec.toml").write_text(spec.source)  # the report reads the grid from it
        if workers == 0:
            # Workers elsewhere may claim a run at once: the runs of seeds the rule leaves out
            # are stopped now, not by a launcher that may never run here.
            apply_stop_rule(spec, sessions, results, echo)
            if url_has_secret(url):  # the hint must not print the password
                echo(f"no local workers: start `sepoa worker --results {results}` on hosts that "
                     f"reach the database and the results folder, with the queue's URL "
                     f"({where}) in SEPOA_DATABASE_URL or in a file named by "
                     "--database-url-file; or `sepoa experiment slurm` for a Slurm array")
            else:
                echo(f"no local workers: start `sepoa worker --database-url {url} --results "
                     f"{results}` on hosts that reach the database and the results folder; or "
                     "`sepoa experiment slurm` for a Slurm array")
            return 0
        echo(f"{workers} local worker(s), {threads} torch thread(s) each -> {folder}")
        assert train is not None
        with recorded_session(folder, workers=workers, threads=threads, echo=echo) as period, \
                stop_rule_watch(spec, sessions, results, echo):
            # Spent hours stop the runs of seeds not started before any worker can claim them
            # (checked once this session's row is written, so that a session killed moments
            # ago counts up to its last sign of life, not to now).
            apply_stop_rule(spec, sessions, results, echo)
            stopped = train(url, results, workers, threads, echo)
            period.end("finished" if stopped is None else f"signal {stopped}")
        return _summary(spec, sessions, results, echo, stopped)
    finally:
        engine.dispose()


def _summary(spec: Spec, sessions: Any, results: Path, echo: Callable[[str], None],
             stopped: int | None) -> int:
    rows = spec_rows(spec, sessions)
    keys = [grid_key(spec, run) for run in spec.runs()]
    by_status: dict[str, list[str]] = {}
    for key, run in zip(keys, spec.runs(), strict=True):
        by_status.setdefault(shown_status(rows.get(key), results, spec, run), []).append(key)
    for key in by_status.get("failed", []):
        echo(f"FAILED   {key}: {rows[key].error}")
    for key in by_status.get("running", []) + by_status.get("paused", []):
        echo(f"running  {key} on worker {rows[key].worker_id}")
    counts = ", ".join(f"{len(v)} {k}" for k, v in sorted(by_status.items()))
    echo(f"{spec.name}: {counts}"
         + (f"; stopped by signal {stopped}" if stopped is not None else ""))
    if stopped is not None:
        return 128 + stopped
    return 0 if len(by_status.get("finished", [])) == len(keys) else 1


def check_counts(workers: int | None, threads: int | None) -> None:
    for flag, value in (("workers", workers), ("threads", threads)):
        if value is not None and value < 1:
            raise SpecError(f"--{flag} must be at least 1")
