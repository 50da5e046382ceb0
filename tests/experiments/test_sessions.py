"""A grid's training periods (`experiments.sessions`): each launcher that trains records when it
ran and how it ended, and status sums them, so a stop rule in wall time holds across sessions."""

from __future__ import annotations

import csv
import multiprocessing
import signal
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from experiments.launch import run_experiment
from experiments.sessions import FILE, recorded_session, worked
from experiments.spec import load_spec
from sepoa.cli import main

T0 = datetime(2026, 11, 28, 8, 0, tzinfo=UTC)

SPEC = """
name = "timed"
preset = "tiny"
steps = 1000
tasks = ["dmc:cheetah_run"]
eps = [0.3]
seeds = [0]

[variants.SAC]
algo = "sac"
"""


def write_sessions(folder: Path, rows: list[tuple[datetime, datetime | None, str]],
                   alive: list[datetime] | None = None) -> None:
    """sessions.csv with `rows` (start, end, how it ended); without `alive` in the file's first
    form, which had no `alive_at`."""
    folder.mkdir(parents=True, exist_ok=True)
    with (folder / FILE).open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["started_at", "ended_at", "workers", "threads", "ended_by"]
                        + (["alive_at"] if alive else []))
        for i, (start, end, by) in enumerate(rows):
            writer.writerow([start.isoformat(), end.isoformat() if end else "", 2, 1, by]
                            + ([alive[i].isoformat()] if alive else []))


def test_the_time_between_sessions_is_not_counted(tmp_path: Path) -> None:
    write_sessions(tmp_path, [(T0, T0 + timedelta(hours=2), "signal 15"),
                              (T0 + timedelta(hours=5), T0 + timedelta(hours=6), "finished")])
    period = worked(tmp_path, now=T0 + timedelta(hours=9))
    assert period is not None
    assert (period.seconds, period.sessions, period.running_since, period.unended) == (
        3 * 3600, 2, None, 0)
    assert worked(tmp_path / "never") is None


def test_an_unended_session_counts_to_now_only_while_it_is_the_newest(tmp_path: Path) -> None:
    write_sessions(tmp_path, [(T0, None, ""), (T0 + timedelta(hours=3), None, "")])
    period = worked(tmp_path, now=T0 + timedelta(hours=4))
    assert period is not None
    # The first was killed outright (a later one began): not counted; the newest runs.
    assert (period.seconds, period.running_since, period.unended) == (
        3600, T0 + timedelta(hours=3), 1)
    text = period.text("1h00m")
    assert "1h00m over 2 session(s)" in text and "running since 2026-11-28 11:00" in text
    assert "1 session(s) ended without a record" in text


def test_a_killed_session_counts_up_to_its_last_sign_of_life(tmp_path: Path) -> None:
    write_sessions(tmp_path, [(T0, None, ""), (T0 + timedelta(hours=3), None, "")],
                   alive=[T0 + timedelta(minutes=90), T0 + timedelta(hours=4)])
    # At 4 h 02 min the newest beat 2 min ago: it runs, and counts up to now.
    period = worked(tmp_path, now=T0 + timedelta(hours=4, minutes=2))
    assert period is not None
    assert (period.seconds, period.running_since, period.unended) == (
        90 * 60 + 62 * 60, T0 + timedelta(hours=3), 1)
    # An hour later it has not beaten since: killed too, counted up to its last beat.
    period = worked(tmp_path, now=T0 + timedelta(hours=5))
    assert period is not None
    assert (period.seconds, period.running_since, period.unended) == (90 * 60 + 3600, None, 2)


def test_two_launchers_at_once_count_their_common_time_once(tmp_path: Path) -> None:
    """Launcher A trains from 0 h on and still runs; B (another part of the grid) ran from
    1 h to 2 h: 4 h of wall time at 4 h, not 5, and A runs although its row is not the
    newest."""
    write_sessions(tmp_path, [(T0, None, ""), (T0 + timedelta(hours=1),
                                               T0 + timedelta(hours=2), "finished")],
                   alive=[T0 + timedelta(hours=3, minutes=59), T0 + timedelta(hours=2)])
    period = worked(tmp_path, now=T0 + timedelta(hours=4))
    assert period is not None
    assert (period.seconds, period.running_since, period.unended) == (4 * 3600, T0, 0)
    assert "ended without a record" not in period.text("4h00m")


def test_a_running_session_beats(tmp_path: Path) -> None:
    with recorded_session(tmp_path, workers=2, threads=1, now=T0, beat_s=0.02):
        deadline = time.monotonic() + 10
        while (alive := list(csv.DictReader((tmp_path / FILE).open()))[0]["alive_at"]) \
                == T0.isoformat():
            assert time.monotonic() < deadline
            time.sleep(0.02)
        assert datetime.fromisoformat(alive) > T0
    [row] = list(csv.DictReader((tmp_path / FILE).open()))
    assert row["ended_at"] == row["alive_at"] and row["ended_by"] == "error"


def test_a_session_records_its_end_however_it_ends(tmp_path: Path) -> None:
    with recorded_session(tmp_path, workers=2, threads=1, now=T0) as period:
        rows = list(csv.DictReader((tmp_path / FILE).open()))
        assert [(r["started_at"], r["ended_at"]) for r in rows] == [(T0.isoformat(), "")]
        period.end("signal 15")
    with pytest.raises(RuntimeError), recorded_session(tmp_path, workers=1, threads=1):
        raise RuntimeError("a worker could not start")
    rows = list(csv.DictReader((tmp_path / FILE).open()))
    assert [r["ended_by"] for r in rows] == ["signal 15", "error"]
    assert all(r["ended_at"] for r in rows)
    assert rows[0]["workers"] == "2"


def test_two_launchers_started_in_one_second_keep_their_own_rows(tmp_path: Path) -> None:
    with recorded_session(tmp_path, workers=1, threads=1, now=T0) as first:
        with recorded_session(tmp_path, workers=2, threads=1, now=T0) as second:
            second.end("finished")
        rows = list(csv.DictReader((tmp_path / FILE).open()))
        assert [(r["workers"], r["ended_by"]) for r in rows] == [("1", ""), ("2", "finished")]
        first.end("signal 15")
    rows = list(csv.DictReader((tmp_path / FILE).open()))
    assert [r["ended_by"] for r in rows] == ["signal 15", "finished"]


def _beating_launcher(folder: Path, workers: int) -> None:
    with recorded_session(folder, workers=workers, threads=1, beat_s=0.001,
                          echo=lambda line: None) as period:
        time.sleep(0.4)
        period.end("finished")


def test_two_launchers_beating_at_once_lose_no_row(tmp_path: Path) -> None:
    (tmp_path / FILE).write_text("started_at,ended_at,workers,threads,ended_by\n"
                                 f"{T0.isoformat()},{T0.isoformat()},3,1,finished\n")  # older
    fork = multiprocessing.get_context("fork")
    launchers = [fork.Process(target=_beating_launcher, args=(tmp_path, n)) for n in (1, 2)]
    for launcher in launchers:
        launcher.start()
    for launcher in launchers:
        launcher.join(30)
    rows = list(csv.DictReader((tmp_path / FILE).open()))
    assert sorted((r["workers"], r["ended_by"]) for r in rows) == [
        ("1", "finished"), ("2", "finished"), ("3", "finished")]
    assert sorted(p.name for p in tmp_path.iterdir()) == [FILE, f"{FILE}.lock"]  # no temp


def test_the_launcher_records_its_period_and_status_sums_them(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(SPEC)
    spec, results = load_spec(spec_path), tmp_path / "results"

    def stopped_by_sigterm(url, results, workers, threads, echo):  # type: ignore[no-untyped-def]
        return signal.SIGTERM.value

    code = run_experiment(spec, results=results, workers=2, threads=1,
                          echo=lambda line: None, train=stopped_by_sigterm)
    assert code == 128 + signal.SIGTERM.value
    rows = list(csv.DictReader((results / "timed" / FILE).open()))
    assert [(r["workers"], r["threads"], r["ended_by"]) for r in rows] == [("2", "1", "signal 15")]
    # Enqueueing alone (no workers) trains nothing and records nothing.
    assert run_experiment(spec, results=results, workers=0, echo=lambda line: None) == 0
    assert len(list(csv.DictReader((results / "timed" / FILE).open()))) == 1
    assert main(["experiment", "status", str(spec_path), "--results", str(results)]) == 0
    last = capsys.readouterr().out.splitlines()[-1]
    assert last.startswith("worked (local workers' wall time, sessions.csv): ")
    assert last.endswith(" over 1 session(s)")
