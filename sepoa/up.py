"""`sepoa up` and `sepoa serve`. `up` is the embedded default: one SQLite file and a clips folder
under a data folder, the web server and a trainer worker as child processes, and (on a fresh
database) a demo run on dmc:cheetah_run taught by people, so the label page shows real clips
within about a minute.

Tokens: on first start an operator and a labeller are created and their tokens kept in
`<data dir>/credentials.json` (readable by the owner only), with the key that signs clip URLs,
so later starts print the same links. The children are held by `sepoa.supervisor`: Ctrl-C or
SIGTERM stops them all (exit status 130 or 143), and one that ends stops the others.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import time
from pathlib import Path
from typing import Any

from labelqueue import (
    Run,
    check_database,
    create_labeller,
    create_run,
    make_engine,
    session_factory,
)
from sepoa.parser import PORT, Command, fail, refusing
from sepoa.queue_commands import database_args, database_url
from sepoa.supervisor import Supervisor
from trainer.threads import default_threads, describe

DEMO_RUN: dict[str, Any] = {
    "name": "demo: cheetah run, taught in the browser",
    "task": "dmc:cheetah_run",
    "algo": "pebble",
    "preset": "small",
    "budget": 200,
    "teacher": "human",
    # The scripted shadow teacher whose answers the dashboard compares with people's.
    "teacher_params": {"eps": 0.0},
    # A shorter pretraining than the small preset's, so the first round comes within a minute;
    # rounds of 10 pairs suit a person.
    "config": {"steps": 100_000, "unsup_steps": 2000, "feedback.per_round": 10},
}


def _credentials(path: Path, url: str) -> dict[str, str]:
    if path.exists():
        stored: dict[str, str] = json.loads(path.read_text())
        if stored.get("database_url") == url:
            return stored
    engine = make_engine(url)
    with session_factory(engine)() as session:
        suffix = f"-{int(time.time())}" if path.exists() else ""  # a new database URL
        _, operator = create_labeller(session, name=f"operator{suffix}", role="operator")
        _, labeller = create_labeller(session, name=f"labeller{suffix}", role="labeller")
    engine.dispose()
    creds = {"database_url": url, "operator_token": operator, "labeller_token": labeller,
             "secret_key": os.urandom(24).hex()}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.touch(mode=0o600)
    path.write_text(json.dumps(creds, indent=2))
    return creds


def _queue_demo_run(url: str) -> int | None:
    engine = make_engine(url)
    with session_factory(engine)() as session:
        has_runs = session.query(Run.id).first() is not None
        session.commit()
        run = None if has_runs else create_run(session, **DEMO_RUN)
    engine.dispose()
    return None if run is None else run.id


def port_free(host: str, port: int) -> bool:
    with socket.socket() as sock:
        return sock.connect_ex((host, port)) != 0



STOP_GRACE_S = 20.0
"""how long the server and each worker have to end after `sepoa up` is stopped"""


def up(*, database_url: str, data_dir: str, host: str, port: int, workers: int,
       demo: bool, threads: int | None = None, public_url: str | None = None) -> int:
    if not port_free(host, port):
        return fail(f"{host}:{port} is in use; pick another with --port")
    chosen = threads is not None
    threads = threads or default_threads(workers=workers, server=True)
    print(describe(threads, workers=workers, server=True, chosen=chosen), flush=True)
    check_database(database_url, writable=True)  # damaged, read-only: one line, no traceback
    creds = _credentials(Path(data_dir) / "credentials.json", database_url)
    demo_run = _queue_demo_run(database_url) if demo else None

    env = os.environ | {"SEPOA_DATABASE_URL": database_url, "SEPOA_DATA_DIR": data_dir,
                        "SEPOA_SECRET_KEY": creds["secret_key"]}
    if public_url is not None:
        env["SEPOA_PUBLIC_URL"] = public_url
    env.setdefault("MUJOCO_GL", "egl")
    python = sys.executable
    with Supervisor(grace_s=STOP_GRACE_S) as children:
        children.start("the server", [python, "-m", "uvicorn", "server.app:app", "--host", host,
                                      "--port", str(port), "--log-level", "warning"], env=env)
        for i in range(workers):
            # A stable id: a worker restarted by the next `sepoa up` takes its runs back at once.
            # The URL reaches workers in their environment (SEPOA_DATABASE_URL), never on a
            # command line that `ps` shows.
            children.start(f"worker {i}", [
                python, "-m", "sepoa", "worker", "--data-dir", data_dir,
                "--worker-id", f"{socket.gethostname()}-up-{i}", "--threads", str(threads)],
                env=env)
        if not children.stopping:
            print(_banner(host, port, public_url, data_dir, creds, demo_run), flush=True)
        outcome = children.wait(until="any")
        if outcome.signal is not None:
            print("\nstopping the server and the workers…", file=sys.stderr, flush=True)
        elif outcome.exited is not None:
            print(f"error: {outcome.exited.name} exited with {outcome.exited.returncode}",
                  file=sys.stderr)
    return outcome.status


def _banner(host: str, port: int, public_url: str | None, data_dir: str,
            creds: dict[str, str], demo_run: int | None) -> str:
    base = public_url or f"http://{host}:{port}"
    return (f"\nS-EPOA labelling is up at {base}\n"
            f"  label clips:  {base}/label#token={creds['labeller_token']}\n"
            f"  runs:         {base}/runs#token={creds['operator_token']}\n"
            f"  API docs:     {base}/docs  (operator token: {creds['operator_token']})\n"
            f"  data:         {os.path.abspath(data_dir)}  (tokens in credentials.json)\n"
            + (f"  demo run {demo_run} queued: dmc:cheetah_run, first clips in about a minute\n"
               if demo_run else "")
            + (f"  (serving {host}:{port} behind {public_url})\n" if public_url else "")
            + "Ctrl-C stops everything.\n")


def _public_url_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--public-url", default=os.environ.get("SEPOA_PUBLIC_URL"),
                   help="the address people outside reach the server at (https://label.example."
                   "org, behind a reverse proxy): invite links and clip URLs use it (env "
                   "SEPOA_PUBLIC_URL)")


def _settings(args: argparse.Namespace, **given: str) -> str | None:
    """The server's settings, checked before anything is created as the server will read them:
    --public-url (returned as the server will use it) and every SEPOA_ variable, with the
    values `given` (those the command sets itself) in place of theirs. ValueError naming the
    flag, or each variable that is wrong, in one line."""
    from pydantic import ValidationError

    from server.settings import Settings, described

    public = {"public_url": args.public_url} if args.public_url else {}
    try:
        return Settings(**given, **public).public_url  # type: ignore[arg-type]
    except ValidationError as err:
        errors = err.errors()
    url = [e["msg"] for e in errors if e["loc"] == ("public_url",)]
    if url:
        raise ValueError(f"--public-url {args.public_url!r}: {url[0]}")
    raise ValueError(described(errors))


def _up_arguments(p: argparse.ArgumentParser) -> None:
    database_args(p)
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=PORT, default=8000)
    p.add_argument("--workers", type=int, default=1, help="trainer worker processes")
    p.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads per worker; default: the cores divided among the "
                   "workers and the server")
    p.add_argument("--no-demo", action="store_true",
                   help="do not queue the demo run on a fresh database")
    _public_url_arg(p)


@refusing(ValueError)
def _run_up(args: argparse.Namespace) -> int:
    if args.workers < 1 or (args.threads is not None and args.threads < 1):
        return fail("--workers and --threads must be at least 1")
    url = database_url(args)
    # The server gets the credentials' secret key (one of this form on a fresh database), not
    # SEPOA_SECRET_KEY's.
    public_url = _settings(args, database_url=url, data_dir=args.data_dir,
                           secret_key=os.urandom(24).hex())
    return up(database_url=url, data_dir=args.data_dir, host=args.host, port=args.port,
              workers=args.workers, demo=not args.no_demo, threads=args.threads,
              public_url=public_url)


def _serve_arguments(p: argparse.ArgumentParser) -> None:
    database_args(p)
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=PORT, default=8000)
    _public_url_arg(p)


@refusing(ValueError)
def _run_serve(args: argparse.Namespace) -> int:
    import uvicorn

    # Before anything is created or migrated: a busy port leaves no new database behind.
    if not port_free(args.host, args.port):
        return fail(f"{args.host}:{args.port} is in use; pick another with --port")
    url = database_url(args)
    # Checked before the database is made or migrated, and before the environment the server
    # reads is set.
    public_url = _settings(args, database_url=url, data_dir=args.data_dir)
    check_database(url, writable=True)  # damaged, read-only: one line here, not a traceback
    os.environ["SEPOA_DATABASE_URL"] = url
    os.environ["SEPOA_DATA_DIR"] = args.data_dir
    if public_url is not None:
        os.environ["SEPOA_PUBLIC_URL"] = public_url
    uvicorn.run("server.app:app", host=args.host, port=args.port)
    return 0


COMMANDS = {
    "up": Command(_up_arguments, _run_up),
    "serve": Command(_serve_arguments, _run_serve),
}
