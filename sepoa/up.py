"""`sepoa up`: the embedded default. One SQLite file and a clips folder under a data folder, the
web server and a trainer worker as child processes, and (on a fresh database) a demo run on
dmc:cheetah_run taught by people, so the label page shows real clips within about a minute.

Tokens: on first start an operator and a labeller are created and their tokens kept in
`<data dir>/credentials.json` (readable by the owner only), with the key that signs clip URLs,
so later starts print the same links.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
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


def up(*, database_url: str, data_dir: str, host: str, port: int, workers: int,
       demo: bool, threads: int | None = None, public_url: str | None = None) -> int:
    if not port_free(host, port):
        print(f"error: {host}:{port} is in use; pick another with --port", file=sys.stderr)
        return 2
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
    children: list[subprocess.Popen[bytes]] = []
    # Ctrl-C while the children start is noted, not raised: an exception inside Popen would
    # leave a started child out of `children`, running on after this process.
    interrupted = False

    def note_interrupt(signum: int, _frame: object) -> None:
        nonlocal interrupted
        interrupted = True

    previous = signal.signal(signal.SIGINT, note_interrupt)
    try:
        # Each child in a process group of its own: Ctrl-C reaches this process only, which
        # stops them in turn (SIGTERM), so none is cut off mid-import with a traceback.
        children.append(subprocess.Popen(
            [python, "-m", "uvicorn", "server.app:app", "--host", host, "--port", str(port),
             "--log-level", "warning"], env=env, process_group=0))
        for i in range(workers):
            # A stable id: a worker restarted by the next `sepoa up` takes its runs back at once.
            worker_id = f"{socket.gethostname()}-up-{i}"
            # The URL reaches workers in their environment (SEPOA_DATABASE_URL), never on a
            # command line that `ps` shows.
            children.append(subprocess.Popen(
                [python, "-m", "trainer.cli", "worker",
                 "--data-dir", data_dir, "--worker-id", worker_id, "--threads", str(threads)],
                env=env, process_group=0))
            if interrupted:
                break
    finally:
        signal.signal(signal.SIGINT, previous)
    if interrupted:
        _stop(children)
        raise KeyboardInterrupt

    base = public_url or f"http://{host}:{port}"
    print(f"\nS-EPOA labelling is up at {base}\n"
          f"  label clips:  {base}/label#token={creds['labeller_token']}\n"
          f"  runs:         {base}/runs#token={creds['operator_token']}\n"
          f"  API docs:     {base}/docs  (operator token: {creds['operator_token']})\n"
          f"  data:         {os.path.abspath(data_dir)}  (tokens in credentials.json)\n"
          + (f"  demo run {demo_run} queued: dmc:cheetah_run, first clips in about a minute\n"
             if demo_run else "")
          + (f"  (serving {host}:{port} behind {public_url})\n" if public_url else "")
          + "Ctrl-C stops everything.\n", flush=True)
    return _supervise(children)


def _supervise(children: list[subprocess.Popen[bytes]]) -> int:
    """Wait until Ctrl-C / SIGTERM or until a child dies; then stop the others."""
    stop = False

    def on_signal(signum: int, _frame: object) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, on_signal)
    code = 0
    try:
        while not stop:
            dead = [c for c in children if c.poll() is not None]
            if dead:
                code = dead[0].returncode or 1
                print(f"error: {' '.join(map(str, dead[0].args[:4]))} exited with {code}",
                      file=sys.stderr)
                break
            time.sleep(0.5)
    except KeyboardInterrupt:
        print("\nstopping the server and the workers…", file=sys.stderr, flush=True)
    _stop(children)
    return code


def _stop(children: list[subprocess.Popen[bytes]]) -> None:
    """SIGTERM to each child, then up to 20 s for it to end (a second Ctrl-C kills them)."""
    for child in children:
        if child.poll() is None:
            child.terminate()
    try:
        for child in children:
            try:
                child.wait(timeout=20)
            except subprocess.TimeoutExpired:
                child.kill()
    except KeyboardInterrupt:
        for child in children:
            if child.poll() is None:
                child.kill()
