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
The workers die with their launcher (SIGTERM), leaving each run to be resumed.
"""

from __future__ import annotations

import ctypes
import fcntl
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import IO, Any

from experiments.queue import enqueue_spec, grid_key, spec_rows
from experiments.spec import Spec, SpecError
from labelqueue import RunStatus, make_engine, migrate, session_factory

STOP_GRACE_S = 30.0
PR_SET_PDEATHSIG = 1


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


def _die_with_parent() -> None:  # pragma: no cover - runs in the child before exec
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


def _missing_sqlite(url: str) -> bool:
    from sqlalchemy.engine import make_url

    parsed = make_url(url)
    return parsed.get_backend_name() == "sqlite" and not Path(parsed.database or "").exists()


def worker_argv(database_url: str, results: Path, worker_id: str, threads: int) -> list[str]:
    return [sys.executable, "-m", "trainer.cli", "worker", "--database-url", database_url,
            "--data-dir", str(results), "--results", str(results), "--worker-id", worker_id,
            "--threads", str(threads), "--once", "--poll-seconds", "1"]


def run_experiment(spec: Spec, *, results: Path, database_url: str | None = None,
                   workers: int = 1, threads: int | None = None, force: bool = False,
                   dry_run: bool = False, echo: Callable[[str], None] = print) -> int:
    """Enqueue the grid and train it with `workers` local workers (0: enqueue only). The exit
    status: 0 every run of the spec finished (or, without workers, enqueued), 1 some did not,
    128 + signal when stopped. SpecError for a redefined grid without `force`."""
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
        done = enqueue_spec(spec, sessions, results, force=force, dry_run=dry_run)
        where = url.split("@")[-1]
        finished = sum(s is RunStatus.FINISHED for s in done.present.values())
        echo(f"{spec.name}: {len(spec.runs())} runs; {len(done.created)} enqueued, "
             f"{len(done.requeued)} queued again, {len(done.replaced)} redefined, "
             f"{finished} finished, {len(done.present) - finished} queued or running"
             + (f", {len(done.adopted)} finished before (their folders' results kept)"
                if done.adopted else "") + " "
             f"({where}{'; dry run, nothing written' if dry_run else ''})")
        if dry_run:
            return 0
        folder = results / spec.name
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "spec.toml").write_text(spec.source)  # the report reads the grid from it
        if workers == 0:
            echo(f"no local workers: start `sepoa worker --database-url {url} --results "
                 f"{results}` on hosts that reach the database and the results folder")
            return 0
        echo(f"{workers} local worker(s), {threads} torch thread(s) each -> {folder}")
        stopped = _train(url, results, workers, threads, echo)
        return _summary(spec, sessions, echo, stopped)
    finally:
        engine.dispose()


def _train(url: str, results: Path, workers: int, threads: int,
           echo: Callable[[str], None]) -> int | None:
    """Run the local workers to their end; the signal that stopped the launcher, if any."""
    stop: list[int] = []
    handlers: dict[int, Any] = {}

    def on_signal(signum: int, _frame: Any) -> None:
        stop.append(signum)

    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            handlers[sig] = signal.signal(sig, on_signal)
        except ValueError:  # not the main thread
            pass
    env = os.environ | {"OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads),
                        "PYTHONUNBUFFERED": "1"}
    log = (results / "workers.log").open("a")
    children: list[subprocess.Popen[bytes]] = []
    try:
        with worker_slots(results, workers) as names:
            for name in names:
                # Own session: a Ctrl-C reaches the launcher, which stops its workers itself.
                children.append(subprocess.Popen(
                    worker_argv(url, results, name, threads), stdout=log,
                    stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                    start_new_session=True, preexec_fn=_die_with_parent))
                echo(f"worker {name} started (pid {children[-1].pid}; log {log.name})")
            while not stop and any(c.poll() is None for c in children):
                time.sleep(0.2)
            if stop:
                echo(f"stopping {sum(c.poll() is None for c in children)} worker(s); their "
                     "runs resume from their checkpoints on the next call")
            for child in children:
                if child.poll() is None:
                    child.terminate()
            deadline = time.time() + STOP_GRACE_S
            for child in children:
                try:
                    child.wait(max(0.1, deadline - time.time()))
                except subprocess.TimeoutExpired:
                    child.kill()
                    child.wait()
            for name, child in zip(names, children, strict=True):
                if child.returncode not in (0, -signal.SIGTERM, -signal.SIGKILL) and not stop:
                    echo(f"worker {name} exited with status {child.returncode}; see {log.name}")
    finally:
        log.close()
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    return stop[0] if stop else None


def _summary(spec: Spec, sessions: Any, echo: Callable[[str], None],
             stopped: int | None) -> int:
    rows = spec_rows(spec, sessions)
    keys = [grid_key(spec, run) for run in spec.runs()]
    by_status: dict[str, list[str]] = {}
    for key in keys:
        row = rows.get(key)
        by_status.setdefault(str(row.status) if row else "not queued", []).append(key)
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
