"""The command line around a study: `sepoa invite verify CODE` says whose completion code it is
(exit 1 for nobody's), `--public-url` is checked in one line, and Ctrl-C on `sepoa up`, while it
starts or once it runs, stops it and its children without a traceback."""

from __future__ import annotations

import csv
import io
import os
import signal
import socket
import subprocess
import sys
import time
from datetime import timedelta
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import Engine, event

from crowdstudy.completion import labeller_progress
from crowdstudy.invites import create_invite, join_invite
from labelqueue import (
    claim_run,
    create_run,
    lease_next_query,
    make_engine,
    migrate,
    push_queries,
    session_factory,
    sqlite_url,
    submit_label,
)
from labelqueue.models import utcnow
from sepoa.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_invite_verify_says_whose_code_it_is(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    data = tmp_path / "data"
    url = sqlite_url(str(data))
    migrate(url)
    engine = make_engine(url)
    with session_factory(engine)() as session:
        run = create_run(session, name="r", task="dmc:cheetah_run", algo="pebble", budget=10)
        assert claim_run(session, worker_id="w") is not None
        spec = {"round": 0, "position": 0, "step": 1, "segment_length": 50,
                "first_trajectory": 0, "first_start": 0, "second_trajectory": 1,
                "second_start": 0, "first_segment_return": 1.0, "second_segment_return": 2.0,
                "first_trajectory_return": 1.0, "second_trajectory_return": 2.0,
                "first_clip": "a.mp4", "second_clip": "b.mp4"}
        push_queries(session, run_id=run.id, queries=[spec])
        invite = create_invite(session, expires_at=utcnow() + timedelta(days=1), run_id=run.id,
                               target_answers=1, completion_code="PILOT")
        joined = join_invite(session, code=invite.code, participant="P-1").labeller
        query = lease_next_query(session, labeller_id=joined.id, run_id=run.id)
        assert query is not None
        submit_label(session, query_id=query.id, labeller_id=joined.id, choice="right",
                     left_is_first=True)
        code = labeller_progress(session, labeller_id=joined.id).completion_code
    engine.dispose()
    assert code is not None

    assert main(["invite", "verify", code.lower(), "--data-dir", str(data)]) == 0
    line = (f"valid: P-1 (labeller 'P-1', id {joined.id}), invite {invite.id}, run {run.id}: 1 "
            "of 1 decisive answers; complete: reached the target")
    assert capsys.readouterr().out == line + "\n"
    assert main(["invite", "--data-dir", str(data), "verify", "PILOT-AAAA-BBBB-CCCC"]) == 1
    assert "is no participant's completion code" in capsys.readouterr().err
    assert main(["invite", "verify", code, "--data-dir", str(tmp_path / "none")]) == 2
    assert "no queue database" in capsys.readouterr().err
    # A code typed with spaces inside, as several words, is one code.
    spaced = code.replace("-", " - ").split()
    assert main(["invite", "verify", *spaced, "--data-dir", str(data)]) == 0
    # So is one whose groups are split by spaces alone, as a participant may read it out.
    assert main(["invite", "verify", *code.split("-"), "--data-dir", str(data)]) == 0
    assert capsys.readouterr().out.startswith("valid: P-1")
    # Many codes, one a line from stdin: exit 1 when any is not to be paid.
    monkeypatch.setattr("sys.stdin", io.StringIO(f"{code}\n\nPILOT-AAAA-BBBB-CCCC\n"))
    assert main(["invite", "verify", "-", "--data-dir", str(data)]) == 1
    captured = capsys.readouterr()
    assert captured.out.startswith("valid: P-1") and "no participant's" in captured.err
    # However many codes, as many statements: whose each is and how far they got, read once.
    # A participant's code given again is paid once: the repeats say so, and exit 1.
    counted = []
    for given, exit_status in ((code, 0), (f"{code}\n" * 5, 1)):
        monkeypatch.setattr("sys.stdin", io.StringIO(given))
        status, statements = run_counting(["invite", "verify", "-", "--data-dir", str(data)])
        assert status == exit_status
        counted.append(statements)
    again = (f"again: P-1 (labeller 'P-1', id {joined.id}): their code was given above, pay "
             "them once")
    assert capsys.readouterr().out.split("\n") == [line] * 2 + [again] * 4 + [""]
    assert counted[0] == counted[1]

    # The list to pay from.
    assert main(["invite", "participants", str(invite.id), "--csv", "--data-dir",
                 str(data)]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert [(r["participant"], r["decisive"], r["code_valid"], r["completion_code"])
            for r in rows] == [("P-1", "1", "True", code)]
    assert main(["invite", "participants", "999", "--data-dir", str(data)]) == 2
    assert "invite 999 does not exist" in capsys.readouterr().err


def test_invite_verify_given_no_code_says_so(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """An empty codes file (or a blank code) is a one-line mistake, not a silent exit 1 that
    reads as "some code is not to be paid"."""
    data = tmp_path / "data"
    migrate(sqlite_url(str(data)))
    for argv, stdin in ((["-"], ""), (["-"], "\n  \n"), (["  "], "")):
        monkeypatch.setattr("sys.stdin", io.StringIO(stdin))
        assert main(["invite", "verify", *argv, "--data-dir", str(data)]) == 2, (argv, stdin)
        captured = capsys.readouterr()
        assert captured.out == "" and captured.err.count("\n") == 1
        assert "no completion code given" in captured.err


def run_counting(argv: list[str]) -> tuple[int, int]:
    """`sepoa argv`'s exit status and the SQL statements it ran, on every engine it made."""
    seen: list[str] = []

    def count(conn: Any, cursor: Any, statement: str, *_: Any) -> None:
        seen.append(statement)

    event.listen(Engine, "before_cursor_execute", count)
    try:
        return main(argv), len(seen)
    finally:
        event.remove(Engine, "before_cursor_execute", count)


def test_a_bad_public_url_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["serve", "--data-dir", str(tmp_path), "--port", str(free_port()),
                 "--public-url", "label.example.org"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --public-url 'label.example.org': ") and err.count("\n") == 1


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def up(data: Path) -> subprocess.Popen[str]:
    env = os.environ | {"MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    env.pop("SEPOA_DATABASE_URL", None)
    return subprocess.Popen(
        [sys.executable, "-m", "sepoa.cli", "up", "--data-dir", str(data), "--port",
         str(free_port()), "--no-demo", "--threads", "1"],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        process_group=0,  # as a terminal's Ctrl-C: SIGINT to the whole foreground group
        # As from a terminal: a suite started in the background inherits SIGINT ignored.
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


@pytest.mark.parametrize("when", ["starting", "running"])
def test_ctrl_c_on_sepoa_up_stops_everything_without_a_traceback(tmp_path: Path,
                                                                  when: str) -> None:
    data = tmp_path / "data"
    process = up(data)
    try:
        if when == "starting":
            time.sleep(0.8)  # importing, migrating: before any child exists
        else:
            assert process.stdout is not None
            deadline = time.monotonic() + 60
            for line in process.stdout:
                if "Ctrl-C stops everything" in line or time.monotonic() > deadline:
                    break
            time.sleep(1)
        os.killpg(process.pid, signal.SIGINT)
        # Up to 20 s for the children to stop (sepoa.up.STOP_GRACE_S), more on a loaded host.
        out, err = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    # 130, or ended by the SIGINT itself (-2): what a shell reports as 130 either way.
    assert process.returncode in (0, 130, -signal.SIGINT), err
    # No child outlives it (a worker started as the Ctrl-C came used to run on).
    left = subprocess.run(["pgrep", "-f", str(data)], capture_output=True, text=True).stdout
    assert not left.strip(), left
    if when == "running":
        assert "stopping the server and the workers" in err
    else:
        assert err.strip().endswith("interrupted") or "stopping" in err, err
