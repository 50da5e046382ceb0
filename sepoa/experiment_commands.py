"""`sepoa experiment` and `sepoa report`: a spec's grid through the queue, trained by local
workers that `sepoa.supervisor` holds, or by workers elsewhere; and its report.

    sepoa experiment run SPEC [--results results] [--workers N | --no-workers]
                              [--database-url URL] [--threads N] [--device D [--mps]]
                              [--force] [--dry-run]
    sepoa experiment status SPEC [--results results] [--database-url URL]
    sepoa experiment pack SPEC --out FILE.tar.gz [--results results] [--unfinished-only]
                               [--database-url URL]
    sepoa experiment keep SPEC --out DIR [--results results]   # finished runs, to commit
    sepoa experiment slurm SPEC --workers N [--results DIR] ...   # an sbatch array script
    sepoa report <results>/<spec name>           # figures + tables -> <folder>/report
    sepoa report --calibration labels.jsonl      # match ratio and fitted eps per labeller

The database: --database-url or --database-url-file, else SEPOA_DATABASE_URL, else the file
named by SEPOA_DATABASE_URL_FILE, else `<results>/queue.db` (SQLite; not for `slurm`). A URL
is shown with its password masked wherever it is printed. A closed standard output (`| head`)
is not an error: the command does its work without printing.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
import pathlib
import shlex
import signal
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

from sepoa.parser import (
    Command,
    DefaultsHelpFormatter,
    database_url_file_argument,
    fail,
    file_in_the_way,
)
from sepoa.supervisor import Supervisor

STOP_GRACE_S = 120.0
"""how long a local worker has to checkpoint and release its run once the launcher is stopped:
the rest of an episode, or of a reward epoch inside a round (about a minute for a late
small-preset S-EPOA round on a busy core); a second Ctrl-C ends the workers at once"""


def _database(p: argparse.ArgumentParser, default: str = "sqlite:///<results>/queue.db") -> None:
    p.add_argument("--database-url", default=None,
                   help=f"the queue database (env SEPOA_DATABASE_URL; default {default})")
    database_url_file_argument(p)


def say(line: str) -> None:
    """Print a line of the command's output; once the reader has gone (`| head -1`), the rest
    goes nowhere and the command carries on."""
    try:
        print(line, flush=True)
    except BrokenPipeError:
        # Whatever is still buffered, and every later line, goes to /dev/null.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)


def _experiment_arguments(p: argparse.ArgumentParser) -> None:
    actions = p.add_subparsers(dest="action", required=True)
    run = actions.add_parser("run", help="enqueue the spec's runs and train them with local "
                             "workers; finished runs stay, failed ones are queued again",
                             formatter_class=DefaultsHelpFormatter)
    run.add_argument("spec", help="the spec file (TOML)")
    run.add_argument("--results", default="results",
                     help="runs go to <results>/<spec name>/<run>")
    _database(run)
    run.add_argument("--workers", type=int, default=1, help="local worker processes")
    run.add_argument("--no-workers", action="store_true",
                     help="only enqueue; workers elsewhere train the runs")
    run.add_argument("--threads", type=int, default=None,
                     help="torch threads per worker, instead of the spec's threads")
    run.add_argument("--device", default=None,
                     help="the device every local worker trains on (auto | cpu | cuda | "
                     "cuda:N), instead of each run's own; the workers may share one GPU")
    run.add_argument("--mps", action="store_true",
                     help="with --device cuda: start CUDA's Multi-Process Service for the "
                     "local workers and stop it afterwards, so that the runs' kernels share "
                     "the GPU instead of taking turns (4 runs: 2.9x one run's steps/s with it, "
                     "1.3x without, on an H200)")
    run.add_argument("--variant", action="append", default=None, metavar="LABEL",
                     help="only this variant's runs (repeat for more): part of a grid for "
                     "another host, whose finished run folders, copied into these results, "
                     "count as finished here")
    run.add_argument("--seed", action="append", type=int, default=None, metavar="N",
                     help="only runs of this seed (repeat for more)")
    run.add_argument("--dry-run", action="store_true",
                     help="say what would be enqueued; write nothing")
    run.add_argument("--force", action="store_true", help="delete and retrain runs whose "
                     "stored definition differs from the spec's")
    status = actions.add_parser("status", help="a table of the spec's runs and their state")
    status.add_argument("spec", help="the spec file (TOML)")
    status.add_argument("--results", default="results")
    _database(status)
    pack = actions.add_parser(
        "pack", help="one archive of what the grid needs to go on on another machine: "
        "unfinished runs with their checkpoints, finished runs' results and episode stores, "
        "skill snapshots and a SQLite queue; a PostgreSQL queue stays on its server (there: "
        "tar -xzf FILE -C <results>, then experiment run)")
    pack.add_argument("spec", help="the spec file (TOML)")
    pack.add_argument("--results", default="results")
    pack.add_argument("--out", required=True, metavar="FILE.tar.gz", help="the archive to write")
    pack.add_argument("--unfinished-only", action="store_true",
                      help="leave finished runs out (they travel another way)")
    _database(pack)
    kept = actions.add_parser(
        "keep", help="copy the grid's finished runs (no checkpoints or TensorBoard files) and "
        "its spec, sessions and stop rule into a folder small enough to commit beside its "
        "report; `sepoa report DIR` reads it, and copied back into <results>/<name> the "
        "launcher counts those runs as finished")
    kept.add_argument("spec", help="the spec file (TOML)")
    kept.add_argument("--results", default="results")
    kept.add_argument("--out", required=True, metavar="DIR", help="the folder to copy into")
    slurm = actions.add_parser("slurm", help="print an sbatch array script of N workers",
                               formatter_class=DefaultsHelpFormatter)
    slurm.add_argument("spec", help="the spec file (TOML)")
    slurm.add_argument("--workers", type=int, required=True, help="array tasks, one worker each")
    _database(slurm, default="none: a PostgreSQL server every node reaches")
    slurm.add_argument("--results", default="results",
                       help="a results folder every node reaches (shared filesystem)")
    slurm.add_argument("--threads", type=int, default=None,
                       help="CPUs and torch threads per task (default: the spec's threads)")
    slurm.add_argument("--mem", default=None, help="memory per task, such as 4G or 4000M "
                       "(default by the spec's preset: tiny 2G, small 3G, paper 8G)")
    slurm.add_argument("--time", default="24:00:00", help="each task's time limit")
    slurm.add_argument("--signal-before", type=int, default=None, metavar="SECONDS",
                       help="warn each worker (SIGUSR1) this long before the time limit, to "
                       "checkpoint and release its run (default 300, at most a quarter of --time)")
    slurm.add_argument("--requeue", action="store_true",
                       help="let Slurm requeue a task on preemption or node failure (and allow "
                       "`scontrol requeue`); the requeued task takes its run back at once")
    slurm.add_argument("--partition", default=None,
                       help="a Slurm partition, or several separated by commas")
    slurm.add_argument("--gpus", type=int, default=0, help="GPUs per task (--gres=gpu:N)")
    slurm.add_argument("--node", default=None, help="run every task on this node "
                       "(--nodelist); allows a SQLite queue on that node's own disk")
    slurm.add_argument("--sepoa", default=None, help="the sepoa command on the nodes "
                       "(default: this one, by absolute path)")


def _report_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("folder", nargs="?", default=None,
                   help="<results>/<spec name>, the folder holding spec.toml")
    p.add_argument("--calibration", metavar="EXPORT_FILE", default=None,
                   help="a label export (sepoa export: .jsonl, .csv or .parquet): match ratio, "
                   "can't-tell rate and fitted eps per labeller (docs/QUALITY.md)")
    p.add_argument("--bins", default=None, metavar="EDGES",
                   help="with --calibration: gap bin edges, e.g. 0,0.1,0.2,0.5,1,inf")
    p.add_argument("--out", default=None, help="default <folder>/report; with --calibration "
                   "<export file without its suffix>-calibration")


def _run_experiment(args: argparse.Namespace) -> int:
    from sqlalchemy.exc import DBAPIError

    from experiments.mps import MpsError
    from experiments.spec import SpecError, load_spec
    from labelqueue import check_url, database_url
    from labelqueue.errors import database_reason

    results = pathlib.Path(args.results)
    try:
        if args.action == "keep":
            return _keep(args, results)
        url = database_url(args.database_url, args.database_url_file)
        url = check_url(url) if url else None
        if args.action == "pack":
            return _pack(args, results, url)
        if args.action == "slurm":
            return _slurm(args, url)
        spec = load_spec(args.spec, check=args.action == "run")
        if args.action == "run" and (args.variant or args.seed):
            spec = spec.only(args.variant, args.seed)
        if args.action == "status":
            return _status(spec, results, url)
        from experiments.launch import check_counts, run_experiment

        check_counts(args.workers, args.threads)
        workers = 0 if args.no_workers else args.workers
        if args.device is not None:
            if not workers:
                return fail("--device is for local workers: give it to `sepoa worker` where "
                            "the workers run")
            check_device(args.device)
        if args.mps:
            from experiments.mps import check_available

            if not workers or not (args.device or "").startswith("cuda"):
                return fail("--mps is for local workers on a GPU: give --device cuda "
                            "(or cuda:N) and --workers N")
            check_available()
        return run_experiment(spec, results=results, database_url=url, workers=workers,
                              threads=args.threads, force=args.force, dry_run=args.dry_run,
                              echo=say, train=functools.partial(train_locally,
                                                                device=args.device,
                                                                mps=args.mps))
    except (SpecError, ValueError, MpsError) as err:
        return fail(str(err))
    except DBAPIError as err:
        return fail(f"queue database: {database_reason(err)}")
    except OSError as err:
        return fail(f"{err.filename or results}: {err.strerror or err}")


def _status(spec, results: pathlib.Path, url: str | None) -> int:  # type: ignore[no-untyped-def]
    from sqlalchemy.engine import make_url

    from experiments.launch import default_database
    from experiments.progress import duration_text
    from experiments.queue import status_table
    from experiments.stop_rule import stop_rule
    from labelqueue import check_url, make_engine, mask_url, schema_revisions, session_factory

    url = check_url(url or default_database(results))
    parsed = make_url(url)
    if parsed.get_backend_name() == "sqlite" and not os.path.exists(parsed.database or ""):
        return fail(f"no queue database at {parsed.database}: nothing enqueued yet "
                     "(sepoa experiment run), or give --database-url / --results")
    current, head = schema_revisions(url)
    if current is None:
        return fail(f"the queue database {mask_url(url)} has no schema yet: nothing enqueued "
                    "(sepoa experiment run)")
    if current != head and parsed.get_backend_name() != "sqlite":
        return fail(  # reading it would fail on a column one side lacks
            f"the queue database's schema is at revision {current}, this sepoa's at {head}: "
            "run `experiment status` with the sepoa its workers run, or migrate the database "
            "with this version's `sepoa experiment run --no-workers` (workers of the older "
            "version may then fail)")
    with tempfile.TemporaryDirectory() as tmp:
        if current != head:
            # An older sepoa's workers may still use the file: read a migrated copy of it.
            url = _migrated_copy(parsed.database or "", Path(tmp) / "queue.db")
        engine = make_engine(url)
        try:
            sessions = session_factory(engine)
            rule = stop_rule(spec, sessions, results)
            say(status_table(spec, sessions, results,
                             rule.text(duration_text) if rule is not None else None,
                             rule.worked_s if rule is not None and not rule.reached else None,
                             rule.seeds_not_started if rule is not None else ()))
        finally:
            engine.dispose()
    if current != head:
        say(f"(read from a migrated copy: the database's schema is at revision {current}, "
            f"this sepoa's at {head}; the database itself is left as it is)")
    return 0


def _migrated_copy(database: str, copy: Path) -> str:
    """A copy of a SQLite queue (SQLite's backup: consistent while workers write to it),
    migrated to this sepoa's schema; its URL."""
    from experiments.carry import copy_sqlite
    from labelqueue import migrate

    copy_sqlite(database, copy)
    url = f"sqlite:///{copy}"
    migrate(url)
    return url


def _pack(args: argparse.Namespace, results: pathlib.Path, url: str | None) -> int:
    from experiments.carry import pack
    from experiments.spec import load_spec
    from labelqueue import mask_url

    if not results.is_dir():
        return fail(f"--results {results}: no such folder")
    if os.path.isdir(args.out):
        return fail(f"--out {args.out} is a folder; give the archive's file name, such as "
                    "grid.tar.gz")
    if (file := file_in_the_way(os.path.dirname(os.path.abspath(args.out)))) is not None:
        return fail(f"--out {args.out}: {file} is a file, not a folder")
    spec = load_spec(args.spec, check=False)
    packed = pack(spec, results, pathlib.Path(args.out), unfinished_only=args.unfinished_only,
                  database_url=url)
    there = f"sepoa experiment run {args.spec} --results <results>"
    queue = "the queue database"
    if not packed.database:  # PostgreSQL: it stays on its server, the runs' ids with it
        queue = f"not the queue, which stays at {mask_url(url or '')}"
        there += " with the same --database-url (or SEPOA_DATABASE_URL)"
    say(f"{args.out}: {packed.unfinished} unfinished run(s) with their checkpoints, "
        f"{packed.finished} finished, {packed.episode_stores} episode store(s), "
        f"{packed.snapshots} snapshot file(s), {queue}; {packed.size / 2**20:.1f} MiB. "
        f"There: tar -xzf {args.out} -C <results>, then {there}")
    return 0


def _keep(args: argparse.Namespace, results: pathlib.Path) -> int:
    from experiments.keep import keep
    from experiments.spec import load_spec

    if (file := file_in_the_way(args.out)) is not None:
        return fail(f"--out {args.out}: {file} is a file, not a folder")
    spec = load_spec(args.spec, check=False)
    kept = keep(spec, results, pathlib.Path(args.out))
    say(f"{args.out}: {kept.runs} finished run(s) of {spec.name} and its grid files, "
        f"{kept.size / 2**20:.1f} MiB; {kept.unfinished} run(s) not finished left out. "
        f"`sepoa report {args.out}` reads it; on another machine, copy it into "
        f"<results>/{spec.name} and run the spec there")
    if kept.running:
        say("its last session is still running, so sessions.csv has no end for it: keep again "
            "once the launcher has stopped")
    return 0


SQLITE_ON_SLURM = (
    "a SQLite queue is a file, and the array's tasks are separate jobs that Slurm may place "
    "on any node, where SQLite's locking is not safe on the network filesystem they share "
    "(two workers could take one run, or corrupt the file): use a PostgreSQL server every "
    "node reaches (docs/EXPERIMENTS.md), or --node NAME to run every task on one node with "
    "the file on that node's own disk")


def _slurm(args: argparse.Namespace, url: str | None) -> int:
    from sqlalchemy.engine import make_url

    from experiments.launch import default_database
    from experiments.slurm import (
        QueueAccess,
        check_options,
        check_shown,
        sbatch_path,
        sbatch_script,
        signal_before_for,
        write_url_file,
    )
    from experiments.spec import load_spec
    from labelqueue import mask_url, url_has_secret

    if args.workers < 1 or (args.threads is not None and args.threads < 1) or args.gpus < 0:
        return fail("--workers and --threads must be at least 1, --gpus at least 0")
    signal_before_for(args.time, args.signal_before)  # SlurmError (a ValueError) for a bad
    # --time, or a warning the time limit leaves no room for
    check_options(partition=args.partition, node=args.node, memory=args.mem)
    results = pathlib.Path(args.results).absolute()
    sbatch_path(results)  # before anything is written there
    if url is None:
        if args.node is None:
            return fail("no queue database: give --database-url, --database-url-file or "
                        "SEPOA_DATABASE_URL (a PostgreSQL server every node reaches)")
        url = default_database(results)
    parsed = make_url(url)
    if parsed.get_backend_name() == "sqlite":
        if args.node is None:
            return fail(f"--database-url: {SQLITE_ON_SLURM}")
        url = parsed.set(database=str(pathlib.Path(parsed.database or "").absolute())) \
            .render_as_string(hide_password=False)
    spec = load_spec(args.spec, check=False)
    # The file the URL was read from, if any (labelqueue.database_url's order).
    file = args.database_url_file
    if not (file or args.database_url or os.environ.get("SEPOA_DATABASE_URL")):
        file = os.environ.get("SEPOA_DATABASE_URL_FILE") or None
    check_shown("--database-url", mask_url(url))
    if file:
        check_shown("--database-url-file", str(pathlib.Path(file).absolute()))
        queue = QueueAccess(mask_url(url), url_file=pathlib.Path(file).absolute())
    elif url_has_secret(url):
        queue = QueueAccess(mask_url(url), url_file=write_url_file(results, url))
        print(f"note: the queue's password is not in the script: its tasks read the URL from "
              f"{queue.url_file} (mode 600)", file=sys.stderr)
    else:
        queue = QueueAccess(mask_url(url), url=url)
    say(sbatch_script(spec, workers=args.workers, queue=queue, results=results,
                      threads=args.threads, time_limit=args.time, partition=args.partition,
                      gpus=args.gpus, memory=args.mem,
                      sepoa=shlex.split(args.sepoa) if args.sepoa else None,
                      requeue=args.requeue, node=args.node,
                      signal_before=args.signal_before).rstrip("\n"))
    return 0


def _run_calibration_report(args: argparse.Namespace) -> int:
    from figures.calibration import (
        default_folder,
        read_calibration_rows,
        write_calibration_report,
    )
    from labelstats.calibration import DEFAULT_EDGES, parse_edges

    try:
        edges = DEFAULT_EDGES if args.bins is None else parse_edges(args.bins)
        rows = read_calibration_rows(args.calibration)  # ExportFileError: a ValueError
    except ValueError as err:
        return fail(str(err))
    folder = pathlib.Path(args.out) if args.out else default_folder(args.calibration)
    try:
        files = write_calibration_report(rows, folder, source=os.path.basename(args.calibration),
                                         edges=edges)
    except OSError as err:
        return fail(f"cannot write the report into {folder}: {err.strerror or err}")
    print("\n".join(str(f) for f in files))
    return 0


def _run_report(args: argparse.Namespace) -> int:
    if (args.folder is None) == (args.calibration is None):
        return fail("give a results folder, or --calibration EXPORT_FILE (not both)")
    if args.out is not None and (file := file_in_the_way(args.out)) is not None:
        where = "" if file == os.path.abspath(args.out) else f": {file}"
        return fail(f"--out {args.out}{where} is a file, not a folder: give a folder for the "
                    "report")
    if args.calibration is not None:
        return _run_calibration_report(args)
    if args.bins is not None:
        return fail("--bins goes with --calibration")
    from experiments.report import write_report
    from experiments.spec import SpecError

    try:
        files = write_report(args.folder, args.out)
    except SpecError as err:
        return fail(str(err))
    except OSError as err:  # a folder that cannot be made or written
        return fail(f"cannot write the report: {err.filename}: {err.strerror or err}")
    print("\n".join(str(f) for f in files))
    return 0


def check_device(name: str) -> None:
    """ValueError unless `name` is a device this host's torch can train on."""
    from trainer.utils import pick_device  # torch: only when a device is named

    pick_device(name)


def train_locally(url: str, results: Path, workers: int, threads: int,
                  echo: Callable[[str], None], device: str | None = None,
                  mps: bool = False) -> int | None:
    """Run `workers` local `sepoa worker --once` processes to their end (the grid is done when
    the last one exits), on `device` when one is given, with an MPS daemon of their own when
    `mps` (experiments/mps.py); the signal that stopped the launcher, if one did."""
    from experiments.launch import worker_argv, worker_slots
    from experiments.mps import mps_daemon

    env = os.environ | {"OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads),
                        "PYTHONUNBUFFERED": "1", "SEPOA_DATABASE_URL": url}
    # Left in reverse: the workers stop before their MPS daemon does.
    with contextlib.ExitStack() as stack:
        if mps:
            env |= stack.enter_context(mps_daemon(results / "mps"))
            echo(f"MPS daemon started for the workers (pipe {env['CUDA_MPS_PIPE_DIRECTORY']}, "
                 f"log {results / 'mps'})")
        log = stack.enter_context((results / "workers.log").open("a"))
        names = stack.enter_context(worker_slots(results, workers))
        children = stack.enter_context(Supervisor(grace_s=STOP_GRACE_S))
        for name in names:
            child = children.start(name, worker_argv(results, name, threads, device), stdout=log,
                                   stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
            if child is None:
                break
            echo(f"worker {name} started (pid {child.process.pid}; log {log.name})")
        outcome = children.wait(until="all")
        if outcome.signal is not None:
            echo(f"stopping {len(children.running())} worker(s): each checkpoints its run and "
                 "releases it, at its episode's end or, inside a round, after the current "
                 f"reward epoch (up to {STOP_GRACE_S:.0f} s; Ctrl-C again ends them at once); "
                 "the runs resume from there on the next call")
        children.stop()
        for child in children.children:
            if outcome.signal is None and child.returncode not in (0, -signal.SIGTERM,
                                                                    -signal.SIGKILL):
                echo(f"worker {child.name} exited with status {child.returncode}; "
                     f"see {log.name}")
    return outcome.signal


COMMANDS = {
    "experiment": Command(_experiment_arguments, _run_experiment),
    "report": Command(_report_arguments, _run_report),
}
