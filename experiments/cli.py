"""`sepoa experiment` and `sepoa report`: a spec's grid through the queue, and its report.

    sepoa experiment run SPEC [--results results] [--workers N | --no-workers]
                              [--database-url URL] [--threads N] [--force] [--dry-run]
    sepoa experiment status SPEC [--results results] [--database-url URL]
    sepoa experiment slurm SPEC --workers N --database-url URL [--results DIR] ...
    sepoa report <results>/<spec name>           # figures + tables -> <folder>/report
    sepoa report --calibration labels.jsonl      # match ratio and fitted eps per labeller

The database defaults to SEPOA_DATABASE_URL, else `<results>/queue.db` (SQLite).
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
from typing import NoReturn


class OneLineParser(argparse.ArgumentParser):
    """An argument error is one line on stderr, naming what is wrong (and where help is), with
    exit status 2; not the whole usage. `sepoa`'s own commands use it too."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def fail(message: str) -> int:
    """Print `error: message` on stderr; the exit status of a user's mistake."""
    print(f"error: {message}", file=sys.stderr)
    return 2


def _database(p: argparse.ArgumentParser) -> None:
    p.add_argument("--database-url", default=os.environ.get("SEPOA_DATABASE_URL"),
                   help="the queue database (env SEPOA_DATABASE_URL; default "
                   "sqlite:///<results>/queue.db)")


def _experiment_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("experiment", help="a spec's grid of runs in the queue "
                       "(docs/EXPERIMENTS.md)")
    actions = p.add_subparsers(dest="action", required=True)
    run = actions.add_parser("run", help="enqueue the spec's runs and train them with local "
                             "workers; finished runs stay, failed ones are queued again",
                             formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    run.add_argument("spec", help="the spec file (TOML)")
    run.add_argument("--results", default="results",
                     help="runs go to <results>/<spec name>/<run>")
    _database(run)
    run.add_argument("--workers", type=int, default=1, help="local worker processes")
    run.add_argument("--no-workers", action="store_true",
                     help="only enqueue; workers elsewhere train the runs")
    run.add_argument("--threads", type=int, default=None,
                     help="torch threads per worker, instead of the spec's threads")
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
    slurm = actions.add_parser("slurm", help="print an sbatch array script of N workers",
                               formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    slurm.add_argument("spec", help="the spec file (TOML)")
    slurm.add_argument("--workers", type=int, required=True, help="array tasks, one worker each")
    slurm.add_argument("--database-url", required=True,
                       help="a database every node reaches (PostgreSQL)")
    slurm.add_argument("--results", default="results",
                       help="a results folder every node reaches (shared filesystem)")
    slurm.add_argument("--threads", type=int, default=None,
                       help="CPUs and torch threads per task (default: the spec's threads)")
    slurm.add_argument("--time", default="24:00:00", help="each task's time limit")
    slurm.add_argument("--partition", default=None)
    slurm.add_argument("--gpus", type=int, default=0, help="GPUs per task (--gres=gpu:N)")
    slurm.add_argument("--mem", default="16G", help="memory per task")
    slurm.add_argument("--sepoa", default="sepoa", help="the sepoa command on the nodes")


def _report_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("report", help="figures and tables of a spec's results, or the "
                       "teacher-calibration report of a label export")
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

    from experiments.spec import SpecError, load_spec
    from labelqueue import check_url

    results = pathlib.Path(args.results)
    try:
        if args.action == "slurm":
            return _slurm(args)
        spec = load_spec(args.spec, check=args.action == "run")
        if args.action == "run" and (args.variant or args.seed):
            spec = spec.only(args.variant, args.seed)
        url = check_url(args.database_url) if args.database_url else None
        if args.action == "status":
            return _status(spec, results, url)
        from experiments.launch import check_counts, run_experiment

        check_counts(args.workers, args.threads)
        workers = 0 if args.no_workers else args.workers
        return run_experiment(spec, results=results, database_url=url, workers=workers,
                              threads=args.threads, force=args.force, dry_run=args.dry_run,
                              echo=lambda line: print(line, flush=True))
    except (SpecError, ValueError) as err:
        return fail(str(err))
    except DBAPIError as err:
        first = str(err.orig or err).strip().splitlines()[0]
        return fail(f"queue database: {first}")
    except OSError as err:
        return fail(f"{err.filename or results}: {err.strerror or err}")


def _status(spec, results: pathlib.Path, url: str | None) -> int:  # type: ignore[no-untyped-def]
    from sqlalchemy.engine import make_url

    from experiments.launch import default_database
    from experiments.queue import status_table
    from labelqueue import make_engine, session_factory

    url = url or default_database(results)
    parsed = make_url(url)
    if parsed.get_backend_name() == "sqlite" and not os.path.exists(parsed.database or ""):
        return fail(f"no queue database at {parsed.database}: nothing enqueued yet "
                     "(sepoa experiment run), or give --database-url / --results")
    engine = make_engine(url)
    try:
        print(status_table(spec, session_factory(engine), results))
    finally:
        engine.dispose()
    return 0


def _slurm(args: argparse.Namespace) -> int:
    from experiments.slurm import sbatch_script
    from experiments.spec import load_spec
    from labelqueue import check_url

    if args.workers < 1 or (args.threads is not None and args.threads < 1) or args.gpus < 0:
        return fail("--workers and --threads must be at least 1, --gpus at least 0")
    url = check_url(args.database_url)
    if url.startswith("sqlite"):
        return fail("--database-url: workers on other nodes need a database server "
                     "(postgresql+psycopg://...), not a SQLite file")
    spec = load_spec(args.spec, check=False)
    print(sbatch_script(spec, workers=args.workers, database_url=url,
                        results=pathlib.Path(args.results).absolute(), threads=args.threads,
                        time_limit=args.time, partition=args.partition, gpus=args.gpus,
                        memory=args.mem, python=args.sepoa), end="")
    return 0


def _run_calibration_report(args: argparse.Namespace) -> int:
    from figures.calibration import (
        default_folder,
        read_calibration_rows,
        write_calibration_report,
    )
    from labelqueue.calibration import DEFAULT_EDGES, parse_edges

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
    print("\n".join(str(f) for f in files))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog="sepoa", description=__doc__,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    _experiment_parser(sub)
    _report_parser(sub)
    args = parser.parse_args(argv)
    if args.command == "experiment":
        return _run_experiment(args)
    return _run_report(args)


if __name__ == "__main__":
    sys.exit(main())
