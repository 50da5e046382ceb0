"""The `sepoa` command line. Trainer commands are handed to `trainer.cli` (they import torch);
the others import only the server or the queue package, so they start fast.

    sepoa up                          # server + worker on SQLite under ./data, and a demo run
    sepoa serve --port 8000           # the web server only (settings from SEPOA_* variables)
    sepoa worker                      # a trainer worker only
    sepoa train --task dmc:cheetah_run --algo pebble --preset small   # one run, no server
    sepoa pretrain --task dmc:cheetah_run --skills aps --preset small # skill snapshot
    sepoa experiment run specs/small/dmc-curves.toml --parallel 2    # a grid of runs
    sepoa report results/dmc-curves-small                            # its figures and tables
    sepoa export --format parquet --run 3 --out labels.parquet
    sepoa labeller create alice [--role operator]
    sepoa tasks | presets
"""

from __future__ import annotations

import argparse
import os
import sys

TRAINER_COMMANDS = {
    "train": "train one run standalone, answered by a scripted teacher",
    "pretrain": "pretrain skills (APS, DIAYN, CIC) for a task; writes a reusable snapshot",
    "worker": "train the runs queued in the queue database",
    "experiment": "run a spec's grid of runs as resumable processes (docs/EXPERIMENTS.md)",
    "report": "figures and tables of an experiment's results",
    "tasks": "list valid task names",
    "presets": "print the presets",
}


def _database_args(p: argparse.ArgumentParser, inherit: bool = False) -> None:
    """`inherit`: on a sub-action, where an absent flag keeps the parent parser's value (so
    `sepoa labeller --data-dir D create x` and `sepoa labeller create x --data-dir D` agree)."""
    url = argparse.SUPPRESS if inherit else os.environ.get("SEPOA_DATABASE_URL")
    data = argparse.SUPPRESS if inherit else os.environ.get("SEPOA_DATA_DIR", "data")
    p.add_argument("--database-url", default=url,
                   help="the queue database (env SEPOA_DATABASE_URL; default: "
                   "sqlite:///<data-dir>/queue.db)")
    p.add_argument("--data-dir", default=data,
                   help="where the SQLite file, runs and clips live (env SEPOA_DATA_DIR)")


def _database_url(args: argparse.Namespace) -> str:
    from labelqueue import sqlite_url

    return args.database_url or sqlite_url(args.data_dir)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sepoa", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    up = sub.add_parser("up", help="start the server and a worker on SQLite, with a demo run")
    _database_args(up)
    up.add_argument("--host", default="127.0.0.1")
    up.add_argument("--port", type=int, default=8000)
    up.add_argument("--workers", type=int, default=1, help="trainer worker processes")
    up.add_argument("--no-demo", action="store_true",
                    help="do not queue the demo run on a fresh database")

    serve = sub.add_parser("serve", help="run the web server (API, label page, dashboard)")
    _database_args(serve)
    serve.add_argument("--host", default="127.0.0.1")
    serve.add_argument("--port", type=int, default=8000)

    export = sub.add_parser("export", help="write the labels as JSONL, CSV or Parquet")
    _database_args(export)
    export.add_argument("--format", choices=("jsonl", "csv", "parquet"), default="jsonl")
    export.add_argument("--run", type=int, default=None, help="one run's labels only")
    export.add_argument("--out", default="-", help="file to write; - for standard output")

    labeller = sub.add_parser("labeller", help="create or list labellers")
    _database_args(labeller)
    labeller_sub = labeller.add_subparsers(dest="action", required=True)
    create = labeller_sub.add_parser("create", help="a new labeller; prints its token once")
    create.add_argument("name")
    create.add_argument("--role", choices=("labeller", "operator"), default="labeller")
    _database_args(create, inherit=True)
    _database_args(labeller_sub.add_parser("list", help="list labellers"), inherit=True)

    for name, text in TRAINER_COMMANDS.items():
        sub.add_parser(name, help=text, add_help=False)  # parsed by trainer.cli
    return parser


def _serve(args: argparse.Namespace) -> int:
    import uvicorn

    os.environ["SEPOA_DATABASE_URL"] = _database_url(args)
    os.environ["SEPOA_DATA_DIR"] = args.data_dir
    uvicorn.run("server.app:app", host=args.host, port=args.port)
    return 0


def _export(args: argparse.Namespace) -> int:
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import DBAPIError

    from labelqueue import NotFound, make_engine, session_factory
    from labelqueue.export import write_export

    url = _database_url(args)
    parsed = make_url(url)
    if parsed.get_backend_name() == "sqlite" and not os.path.exists(parsed.database or ""):
        print(f"error: no queue database at {parsed.database} (--data-dir / --database-url)",
              file=sys.stderr)
        return 2
    engine = make_engine(url)
    tmp = f"{args.out}.partial"
    try:
        with session_factory(engine)() as session:
            if args.out == "-":
                rows = write_export(session, fmt=args.format, out=sys.stdout.buffer,
                                    run_id=args.run)
            else:
                with open(tmp, "wb") as f:
                    rows = write_export(session, fmt=args.format, out=f, run_id=args.run)
                os.replace(tmp, args.out)
    except NotFound as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except DBAPIError as err:
        print(f"error: cannot read labels from {url}: {err.orig}", file=sys.stderr)
        return 2
    finally:
        engine.dispose()
        if os.path.exists(tmp):
            os.remove(tmp)
    print(f"{rows} labels exported", file=sys.stderr)
    return 0


def _labeller(args: argparse.Namespace) -> int:
    from sqlalchemy import select

    from labelqueue import (
        Conflict,
        Labeller,
        create_labeller,
        make_engine,
        migrate,
        session_factory,
    )

    url = _database_url(args)
    migrate(url)
    engine = make_engine(url)
    with session_factory(engine)() as session:
        if args.action == "create":
            try:
                labeller, token = create_labeller(session, name=args.name, role=args.role)
            except Conflict as err:
                print(f"error: {err}", file=sys.stderr)
                return 2
            print(f"{labeller.role} {labeller.name!r} created; its token (shown once):")
            print(token)
        else:
            for lab in session.scalars(select(Labeller).order_by(Labeller.id)):
                print(f"{lab.id}\t{lab.name}\t{lab.role}\t{'active' if lab.active else 'revoked'}")
    engine.dispose()
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in TRAINER_COMMANDS:
        from trainer.cli import main as trainer_main

        return trainer_main(argv)
    args = _parser().parse_args(argv)
    if args.command == "up":
        from sepoa.up import up

        return up(database_url=_database_url(args), data_dir=args.data_dir, host=args.host,
                  port=args.port, workers=args.workers, demo=not args.no_demo)
    if args.command == "serve":
        return _serve(args)
    if args.command == "export":
        return _export(args)
    return _labeller(args)


if __name__ == "__main__":
    sys.exit(main())
