"""The `sepoa` command's database commands: labellers and export, flags before or after the
action; and every mistake a user can make is one line of error with exit status 2."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

from database_helpers import damaged_copies

from sepoa.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_labellers_are_created_and_listed_with_the_data_folder_given_anywhere(tmp_path, capsys):
    data = str(tmp_path / "data")
    assert main(["labeller", "create", "zoe", "--data-dir", data]) == 0
    assert main(["labeller", "--data-dir", data, "create", "amy", "--role", "operator"]) == 0
    token = capsys.readouterr().out.splitlines()[1]
    assert token.startswith("1.")
    assert main(["labeller", "create", "zoe", "--data-dir", data]) == 2  # the name is taken
    assert "already exists" in capsys.readouterr().err
    assert main(["labeller", "list", "--data-dir", data]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines == ["1\tzoe\tlabeller\tactive", "2\tamy\toperator\tactive"]



def test_a_blank_labeller_name_is_refused_in_one_line_and_a_name_is_stored_trimmed(
    tmp_path, capsys
):
    """As POST /api/labellers: a name of white space alone is refused (it listed as an empty
    line nobody could tell apart), and outer white space is not stored."""
    data = str(tmp_path / "data")
    for blank in (" ", "\t\u3000 "):
        assert main(["labeller", "create", blank, "--data-dir", data]) == 2
        [line] = capsys.readouterr().err.splitlines()
        assert f"labeller name {blank!r} is blank" in line and "besides white space" in line
    assert main(["labeller", "create", " zoe ", "--data-dir", data]) == 0
    assert "'zoe' created" in capsys.readouterr().out
    assert main(["labeller", "list", "--data-dir", data]) == 0
    assert capsys.readouterr().out.splitlines() == ["1\tzoe\tlabeller\tactive"]

def test_export_names_a_missing_database_and_writes_an_empty_one(tmp_path, capsys,
                                                                  monkeypatch):
    data = tmp_path / "data"
    assert main(["export", "--data-dir", str(data)]) == 2
    assert "no queue database" in capsys.readouterr().err
    main(["labeller", "create", "zoe", "--data-dir", str(data)])  # migrates the database
    out = tmp_path / "labels.jsonl"
    # Files of the same names as a fixed temporary name would have: not the export's to touch.
    for name in ("-.partial", "labels.jsonl.partial"):
        (tmp_path / name).write_text("someone else's")
    monkeypatch.chdir(tmp_path)
    assert main(["export", "--data-dir", str(data), "--out", str(out)]) == 0
    assert main(["export", "--data-dir", str(data)]) == 0  # to standard output
    assert out.read_text() == ""
    assert sorted(os.listdir(tmp_path)) == ["-.partial", "data", "labels.jsonl",
                                            "labels.jsonl.partial"]
    assert (tmp_path / "-.partial").read_text() == "someone else's"
    assert (tmp_path / "labels.jsonl.partial").read_text() == "someone else's"
    assert main(["export", "--data-dir", str(data), "--run", "7"]) == 2
    assert "run 7 does not exist" in capsys.readouterr().err


def test_labellers_are_revoked_restored_and_given_new_tokens(tmp_path, capsys):
    from labelqueue import authenticate, make_engine, session_factory, sqlite_url

    data = str(tmp_path / "data")
    assert main(["labeller", "create", "zoe", "--data-dir", data]) == 0
    old = capsys.readouterr().out.splitlines()[1]
    assert main(["labeller", "revoke", "zoe", "--data-dir", data]) == 0
    assert main(["labeller", "list", "--data-dir", data]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "1\tzoe\tlabeller\trevoked"
    assert main(["labeller", "--data-dir", data, "activate", "zoe"]) == 0
    assert main(["labeller", "token", "zoe", "--data-dir", data]) == 0
    new = capsys.readouterr().out.splitlines()[-1]
    engine = make_engine(sqlite_url(data))
    with session_factory(engine)() as session:
        assert authenticate(session, token=old) is None  # replaced by the new token
        assert authenticate(session, token=new) is not None  # and active again
    engine.dispose()
    assert main(["labeller", "revoke", "nobody", "--data-dir", data]) == 2
    assert "no labeller named 'nobody'" in capsys.readouterr().err


def test_a_damaged_or_read_only_database_is_refused_in_one_line(tmp_path):
    """Export, the labeller commands, serve and doctor check the database first: a damaged one
    is refused (nothing exported), a read-only one cannot be served; one line, exit 2."""
    copies = damaged_copies(tmp_path)
    out = tmp_path / "labels.jsonl"
    for kind, folder in copies.items():
        for args in (["export", "--out", str(out)], ["labeller", "list"],
                     ["serve", "--port", "18675"], ["doctor", "--backend", "egl"]):
            done = _sepoa(*args, "--data-dir", str(folder), cwd=tmp_path)
            lines = done.stderr.strip().splitlines()
            assert done.returncode == 2, (kind, args, done.stderr)
            assert len(lines) == 1 and "Traceback" not in done.stderr, (kind, args, lines)
            assert "is damaged (PRAGMA quick_check:" in lines[0], (kind, args, lines[0])
            assert "restore it from a backup" in lines[0]
        assert not out.exists()
    sound = _sepoa("export", "--data-dir", str(tmp_path / "sound"), "--out", str(out),
                   cwd=tmp_path)
    assert sound.returncode == 0 and sound.stderr.strip() == "233 labels exported"
    # A read-only database (as root ignores file modes, SQLite's read-only mode stands in).
    read_only = f"sqlite:///file:{tmp_path / 'sound' / 'queue.db'}?mode=ro&uri=true"
    for command in ("serve", "up"):
        done = _sepoa(command, "--port", "18676", "--database-url", read_only, "--no-demo"
                      if command == "up" else "--host=127.0.0.1", cwd=tmp_path)
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 2 and len(lines) == 1, (command, done.stderr)
        assert "attempt to write a readonly database" in lines[0], lines[0]


def _sepoa(*args: str, cwd: Path,
           env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    code = "import sys; from sepoa.cli import main; sys.exit(main())"
    env = os.environ | {"OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)} | (env or {})
    return subprocess.run([sys.executable, "-c", code, *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=120)


def test_every_cli_mistake_is_one_line_with_exit_status_2(tmp_path, capsys):
    data = tmp_path / "data"
    assert main(["labeller", "create", "zoe", "--data-dir", str(data)]) == 0  # a real database
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = str(busy.getsockname()[1])
        cases = [
            (["export", "--data-dir", str(data), "--out", "/nonexistent/dir/x.jsonl"],
             ["/nonexistent/dir", "does not exist"]),
            (["export", "--database-url", "nonsense://x"], ["nonsense://x", "sqlite:///"]),
            (["export", "--database-url", "postgresql://u:pw@h/d"],  # psycopg2's form
             ["'postgresql://u:***@h/d' needs the psycopg2 driver", "postgresql+psycopg://"]),
            (["worker", "--database-url", "nonsense://x", "--once"],
             ["nonsense://x", "postgresql+psycopg://"]),
            (["worker", "--device", "gpu", "--once", "--data-dir", str(tmp_path / "fresh")],
             ["unknown device 'gpu'", "auto, cpu, cuda, cuda:<index>"]),
            (["worker", "--device", "cuda:7", "--once", "--data-dir", str(tmp_path / "fresh")],
             ["'cuda:7'", "torch sees"]),
            (["train", "--steps", "abc"], ["--steps", "takes int, got 'abc'"]),
            (["train", "--reward.surf", "flase", "--run-dir", str(tmp_path / "never")],
             ["--reward.surf", "takes bool, got 'flase'", "true/false, yes/no, on/off or 1/0"]),
            (["pretrain", "--steps", "1.5", "--out", str(tmp_path / "never" / "s.pt")],
             ["--steps", "'skill.pretrain_steps' takes int, got '1.5'"]),
            (["labeller", "create", "", "--data-dir", str(data)], ["''", "1 to 100 characters"]),
            (["serve", "--port", port, "--data-dir", str(tmp_path / "fresh")],
             [f"127.0.0.1:{port} is in use", "--port"]),
            (["export", "--format", "xml"], ["'xml'", "jsonl"]),
            (["serve", "--port", "99999"], ["--port", "'99999' is not a TCP port", "65535"]),
            (["up", "--port", "-1", "--data-dir", str(tmp_path / "fresh")],
             ["--port", "'-1'", "1 to 65535"]),
            (["export", "--data-dir", str(data), "--run", "1180591620717411303424"],
             ["--run", "not a run id", "2147483647"]),
            (["train", "--steps", "1e30", "--run-dir", str(tmp_path / "never")],
             ["steps must be at most 2147483647", "1e+30"]),
            (["train", "--budget", "2147483648", "--run-dir", str(tmp_path / "never")],
             ["feedback.budget must be at most 2147483647", "2147483648"]),
        ]
        for args, words in cases:
            out = _sepoa(*args, cwd=tmp_path)
            lines = out.stderr.strip().splitlines()
            assert out.returncode == 2, (args, out.stderr)
            assert len(lines) == 1 and "Traceback" not in out.stderr, (args, out.stderr)
            assert all(word in lines[0] for word in words), (args, lines[0])
    # Nothing was created by the refused commands: no empty labeller, no database, no run.
    assert not (tmp_path / "fresh").exists() and not (tmp_path / "never").exists()
    capsys.readouterr()
    assert main(["labeller", "list", "--data-dir", str(data)]) == 0
    assert capsys.readouterr().out.splitlines() == ["1\tzoe\tlabeller\tactive"]


def test_a_worker_refuses_a_bad_host_count_or_poll_interval_in_one_line(tmp_path):
    """SEPOA_HOST_PROCESSES is parsed as the worker starts, named when it is no count (and
    --help shows regardless); --poll-seconds takes a time above 0, where 0 busy-looped and a
    negative one failed in the worker's first wait."""
    fresh = str(tmp_path / "fresh")
    bad = {"SEPOA_HOST_PROCESSES": "abc"}
    shown = _sepoa("worker", "--help", cwd=tmp_path, env=bad)
    assert shown.returncode == 0 and "SEPOA_HOST_PROCESSES" in shown.stdout, shown.stderr
    cases = [
        (("worker", "--once", "--data-dir", fresh), bad,
         ["SEPOA_HOST_PROCESSES='abc' is not a count of processes", "at least 1"]),
        (("worker", "--once", "--data-dir", fresh), {"SEPOA_HOST_PROCESSES": "0"},
         ["SEPOA_HOST_PROCESSES='0'", "at least 1"]),
        (("worker", "--once", "--data-dir", fresh, "--poll-seconds", "-1"), {},
         ["--poll-seconds", "'-1' is not a number of seconds above 0"]),
        (("worker", "--once", "--data-dir", fresh, "--poll-seconds", "0"), {},
         ["--poll-seconds", "'0' is not a number of seconds above 0"]),
    ]
    for args, env, words in cases:
        done = _sepoa(*args, cwd=tmp_path, env=env)
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 2, (args, env, done.stderr)
        assert len(lines) == 1 and "Traceback" not in done.stderr, (args, env, done.stderr)
        assert all(word in lines[0] for word in words), (args, lines[0])
    assert not os.path.exists(fresh)


def test_serve_and_up_check_the_settings_before_the_database_in_one_line_naming_them(
        tmp_path):
    """A bad --public-url is refused before the database is made or migrated; a bad SEPOA_
    variable is named (where pydantic's report took four lines, or --public-url was blamed),
    its value not shown when it is a secret."""
    fresh = tmp_path / "fresh"
    url, bad_url = "https://label.example.org", "label.example.org"
    cases = [
        (("serve", "--public-url", bad_url), {}, [f"--public-url {bad_url!r}", "https://"]),
        (("up", "--no-demo", "--public-url", bad_url), {}, [f"--public-url {bad_url!r}"]),
        (("serve", "--public-url", url), {"SEPOA_JOIN_BURST": "0"},
         ["SEPOA_JOIN_BURST='0'", "greater than or equal to 1"]),
        (("serve",), {"SEPOA_LEASE_PER_S": "x", "SEPOA_CLIP_MAX_FRAMES": "0"},
         ["SEPOA_LEASE_PER_S='x'", "SEPOA_CLIP_MAX_FRAMES='0'"]),
        (("serve",), {"SEPOA_SECRET_KEY": "hush"},
         ["SEPOA_SECRET_KEY (its value not shown)", "at least 16 characters"]),
        (("up", "--no-demo"), {"SEPOA_JOIN_BURST": "0"}, ["SEPOA_JOIN_BURST='0'"]),
    ]
    for args, env, words in cases:
        with socket.socket() as free:
            free.bind(("127.0.0.1", 0))
            port = str(free.getsockname()[1])
        done = _sepoa(*args, "--data-dir", str(fresh), "--port", port, cwd=tmp_path, env=env)
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 2, (args, env, done.stderr)
        assert len(lines) == 1 and "Traceback" not in done.stderr, (args, env, done.stderr)
        assert all(word in lines[0] for word in words), (args, env, lines[0])
        if words[0].startswith("SEPOA_"):  # not blamed on the URL
            assert "--public-url" not in lines[0], lines[0]
        assert "hush" not in lines[0]
        assert not fresh.exists(), (args, env)


def test_up_gives_the_server_its_own_secret_key_whatever_sepoa_secret_key_says(monkeypatch):
    import argparse

    from sepoa.up import _settings

    monkeypatch.setenv("SEPOA_SECRET_KEY", "short")
    given = argparse.Namespace(public_url="https://label.example.org/")
    assert _settings(given, secret_key=os.urandom(24).hex()) == "https://label.example.org"


def test_every_command_on_the_queue_database_reads_the_url_file_in_the_environment(
        tmp_path, capsys, monkeypatch):
    """SEPOA_DATABASE_URL_FILE names the queue database for export, labeller, invite,
    label-dataset, doctor, up and serve as for the worker and experiments: `labeller create`
    wrote to a new ./data/queue.db instead."""
    from sepoa.cli import build_parser
    from sepoa.queue_commands import database_url

    url = f"sqlite:///{tmp_path / 'elsewhere' / 'queue.db'}"
    url_file = tmp_path / "queue-url"
    url_file.write_text(f"# the study's queue\n{url}\n")
    url_file.chmod(0o600)
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("SEPOA_DATABASE_URL", raising=False)
    monkeypatch.delenv("SEPOA_DATA_DIR", raising=False)
    monkeypatch.setenv("SEPOA_DATABASE_URL_FILE", str(url_file))
    assert main(["labeller", "create", "bob"]) == 0
    assert main(["labeller", "list"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "1\tbob\tlabeller\tactive"
    assert (tmp_path / "elsewhere" / "queue.db").exists()
    assert main(["export", "--out", "labels.jsonl"]) == 0
    assert not (tmp_path / "data").exists()
    for argv in (["export"], ["labeller", "list"], ["invite", "verify", "X"],
                 ["label-dataset", "d", "--budget", "1"], ["doctor"], ["up"], ["serve"]):
        args = build_parser(argv[0]).parse_args(argv)
        assert database_url(args) == url, argv
    # A flag still wins over the environment; the two flags together are refused.
    args = build_parser("serve").parse_args(["serve", "--database-url", "sqlite:///x.db"])
    assert database_url(args) == "sqlite:///x.db"
    assert main(["labeller", "list", "--database-url", "sqlite:///x.db",
                 "--database-url-file", str(url_file)]) == 2
    assert "not both" in capsys.readouterr().err


def test_a_queue_database_under_a_file_is_refused_in_one_line(tmp_path, capsys):
    """A SQLite queue whose folder would be a file (--data-dir or --database-url a path through
    a file) is named in one line; it was a FileExistsError or NotADirectoryError traceback."""
    notes = tmp_path / "notes.txt"
    notes.write_text("kept\n")
    for argv in (["labeller", "list", "--data-dir", str(notes)],
                 ["labeller", "create", "alice", "--data-dir", str(notes / "sub")],
                 ["export", "--database-url", f"sqlite:///{notes / 'queue.db'}"],
                 ["experiment", "status", "specs/small/dmc-curves.toml",
                  "--results", str(notes)]):
        assert main(argv) == 2, argv
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and f"{notes} is a file, not a folder" in lines[0], (argv, lines)
    assert notes.read_text() == "kept\n"


def test_files_that_are_not_text_are_named_in_one_line(tmp_path, capsys):
    """A spec or database URL file that is not UTF-8 is named with what it should be; the
    line was Python's "'utf-8' codec can't decode byte 0xff in position 0", naming neither."""
    binary = tmp_path / "spec.toml"
    binary.write_bytes(b"\xff\xfe\x00name")
    binary.chmod(0o600)
    for argv, words in (
            (["experiment", "status", str(binary)], ("spec", "not UTF-8 text")),
            (["labeller", "list", "--database-url-file", str(binary)],
             ("database URL file", "not UTF-8 text"))):
        assert main(argv) == 2, argv
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and str(binary) in lines[0], (argv, lines)
        assert all(word in lines[0] for word in words), (argv, lines)


def test_a_report_out_under_a_file_is_refused_in_one_line(tmp_path, capsys):
    """`report --calibration E --out notes.txt` said `File exists`, and an --out under a file
    `Not a directory`; both kinds of report now name the file in the way first."""
    notes, export = tmp_path / "notes.txt", tmp_path / "labels.csv"
    notes.write_text("kept\n")
    data = ["--data-dir", str(tmp_path / "data")]
    assert main(["labeller", "create", "zoe", *data]) == 0
    assert main(["export", *data, "--format", "csv", "--out", str(export)]) == 0
    capsys.readouterr()
    for argv in (["--calibration", str(export), "--out", str(notes)],
                 ["--calibration", str(export), "--out", str(notes / "report")],
                 [str(tmp_path / "results"), "--out", str(notes / "report")]):
        assert main(["report", *argv]) == 2, argv
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and f"{notes} is a file, not a folder" in lines[0], (argv, lines)
    assert notes.read_text() == "kept\n"


def test_a_file_that_is_no_queue_is_named_for_what_it_is_and_left_as_it_was(tmp_path, capsys):
    """An SQLite database of something else, or a file that is no database at all, was called
    damaged (or `labeller` and the worker wrote the queue's tables into it): each is now named
    for what it is, in one line, and left byte for byte as it was."""
    import sqlite3
    from contextlib import closing

    other = tmp_path / "notes.db"
    with closing(sqlite3.connect(other)) as connection:
        connection.execute("CREATE TABLE notes (text TEXT)")
        connection.commit()
    text = tmp_path / "notes.txt"
    text.write_text("a list of things to do\n" * 50)
    for path, said in ((other, "is an SQLite database but not a sepoa queue (no queue tables)"),
                       (text, "is not an SQLite database")):
        before = path.read_bytes()
        for argv in (["labeller", "list"], ["labeller", "create", "amy"], ["export"],
                     ["worker", "--once"], ["invite", "verify", "X"]):
            assert main([*argv, "--database-url", f"sqlite:///{path}"]) == 2, argv
            lines = capsys.readouterr().err.strip().splitlines()
            assert len(lines) == 1 and f"{path} {said}" in lines[0], (argv, lines)
            assert "damaged" not in lines[0] and "the queue's own file" in lines[0], lines
        assert path.read_bytes() == before


def test_a_queue_in_memory_is_refused_at_the_door_naming_the_valid_forms(tmp_path, capsys):
    """In memory, the server, the workers and the next start each had a queue of their own:
    every command failed later with `no such table`."""
    for url in ("sqlite://", "sqlite:///", "sqlite:///:memory:"):
        for argv in (["labeller", "list"], ["labeller", "create", "amy"], ["export"],
                     ["serve", "--port", "18677"]):
            assert main([*argv, "--database-url", url]) == 2, (url, argv)
            lines = capsys.readouterr().err.strip().splitlines()
            assert len(lines) == 1 and "in memory" in lines[0], (url, argv, lines)
            assert "sqlite:///PATH or postgresql+psycopg://" in lines[0], lines


def test_commands_that_only_read_the_queue_make_none(tmp_path, capsys):
    """`labeller list` (and revoke, activate, token, export, invite) where no queue is made a
    folder and an empty queue there; they now say so in one line, and how one is made."""
    missing = tmp_path / "missing"
    for where in (["--data-dir", str(missing)],
                  ["--database-url", f"sqlite:///{missing / 'elsewhere.db'}"]):
        for argv in (["labeller", "list"], ["labeller", "revoke", "zoe"],
                     ["labeller", "activate", "zoe"], ["labeller", "token", "zoe"],
                     ["export"], ["invite", "verify", "X"], ["invite", "participants", "1"]):
            assert main([*argv, *where]) == 2, (argv, where)
            lines = capsys.readouterr().err.strip().splitlines()
            assert len(lines) == 1 and f"no queue database at {missing}" in lines[0], lines
            assert "sepoa up" in lines[0], lines
        assert not missing.exists()
    assert main(["labeller", "create", "zoe", "--data-dir", str(missing)]) == 0  # makes one
    assert main(["labeller", "list", "--data-dir", str(missing)]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "1\tzoe\tlabeller\tactive"
