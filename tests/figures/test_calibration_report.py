"""`sepoa report --calibration EXPORT_FILE`: the figure, table and numbers of a label export,
and every mistake a user can make one line of error with exit status 2."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from sepoa.cli import main

ROW = {
    "schema_version": 2, "label_id": 1, "run_id": 1, "round": 0, "algo": "sepoa",
    "query_id": 1, "labeller_id": 4, "labeller_name": "ann", "choice": "left",
    "answer": "first", "first_trajectory": 0, "second_trajectory": 1,
    "first_segment_return": 5.0, "second_segment_return": 4.0,
    "first_trajectory_return": 110.0, "second_trajectory_return": 90.0,
}


def run_report(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    code = main(["report", *args])
    out, err = capsys.readouterr()
    return code, out, err


def test_an_export_gives_a_figure_a_table_and_the_numbers(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    export = tmp_path / "labels-v2.jsonl"
    rows = [ROW | {"label_id": i, "query_id": i} for i in range(1, 5)]
    rows.append(ROW | {"label_id": 5, "query_id": 5, "choice": "cant_tell", "answer": "cant_tell",
                       "future_column": "ignored"})
    export.write_text("".join(json.dumps(row) + "\n" for row in rows))
    code, out, err = run_report(capsys, "--calibration", str(export))
    assert code == 0, err
    folder = tmp_path / "labels-v2-calibration"  # beside the export by default
    assert out.split() == [str(folder / name) for name in (
        "calibration.png", "calibration.md", "calibration.json", "labellers.csv",
        "agreement.json")]
    assert (folder / "calibration.png").read_bytes().startswith(b"\x89PNG")
    numbers = json.loads((folder / "calibration.json").read_text())
    [ann] = numbers["labellers"]
    rates = ann["rates"]
    assert (ann["name"], rates["answers"], rates["correct"], rates["cant_tell"]) == (
        "ann", 5, 4, 1)
    table = (folder / "calibration.md").read_text()
    assert "| ann | 5 | 1.00 [0.51, 1.00] | 0.20 |" in table
    # The eps interval comes before the point, flagged when wider than eps.
    fit = ann["fit"]
    assert (fit["eps_low"], fit["eps_high"], fit["wide"]) == (0.0, 0.2, True)
    assert f"| [0.00, 0.20] (ε̂ {fit['eps']:.2f}) wide |" in table
    assert "| sepoa | 1 | 5 | 5 |" in table
    [quality] = list(csv.DictReader((folder / "labellers.csv").open()))
    assert (quality["labeller_name"], quality["answers"], quality["cant_tell_k"]) == (
        "ann", "5", "1")
    agreement = json.loads((folder / "agreement.json").read_text())
    assert agreement["everyone"]["queries"] == 0  # one labeller: nothing shared


def test_bins_and_an_empty_export(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    export = tmp_path / "empty.csv"
    export.write_text(",".join(ROW) + "\n")  # a header, no rows
    code, _, err = run_report(capsys, "--calibration", str(export), "--out",
                              str(tmp_path / "out"), "--bins", "0,0.5,inf")
    assert code == 0, err
    numbers = json.loads((tmp_path / "out" / "calibration.json").read_text())
    assert numbers["edges"] == [0.0, 0.5, None] and numbers["rows"] == 0


def test_an_export_without_the_columns_is_refused_and_nothing_is_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from labelstats.calibration import REQUIRED_COLUMNS

    header_only = tmp_path / "header.csv"
    header_only.write_text("label_id,choice,note\n")  # no rows, and not the columns
    with_rows = tmp_path / "rows.csv"
    with_rows.write_text("label_id,choice,note\n1,left,x\n")
    partial = {key: value for key, value in ROW.items() if key != "algo"}
    uneven = tmp_path / "uneven.jsonl"  # the second row lacks a column
    uneven.write_text(json.dumps(ROW) + "\n" + json.dumps(partial) + "\n")
    expected = ", ".join(REQUIRED_COLUMNS)
    for export, missing in [
        (header_only, "run_id, round, algo, query_id"),
        (with_rows, "run_id, round, algo, query_id"),
        (uneven, "row 2 lacks the columns a calibration report needs: algo"),
    ]:
        code, out, err = run_report(capsys, "--calibration", str(export))
        assert code == 2, (export, out, err)
        assert missing in err and expected in err and err.count("\n") == 1, (export, err)
        assert out == "" and not Path(str(export).rsplit(".", 1)[0] + "-calibration").exists()


def test_an_empty_jsonl_export_is_an_empty_report_and_one_of_other_columns_is_named_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    empty = tmp_path / "empty.jsonl"  # a run with no labels yet: no rows, so no header
    empty.write_text("")
    code, _, err = run_report(capsys, "--calibration", str(empty), "--out", str(tmp_path / "a"))
    assert code == 0, err
    assert json.loads((tmp_path / "a" / "calibration.json").read_text())["rows"] == 0
    other = tmp_path / "other.csv"
    other.write_text("x,y\n1,2\n")
    code, out, err = run_report(capsys, "--calibration", str(other))
    assert code == 2 and out == "" and err.count("\n") == 1, err
    assert "has none of the columns" in err and err.count("labeller_id") == 1, err


def test_every_mistake_is_one_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    no_columns = tmp_path / "other.jsonl"
    no_columns.write_text(json.dumps({"label_id": 1, "choice": "left"}) + "\n")
    picture = tmp_path / "labels.csv"
    picture.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00")
    notes = tmp_path / "notes.txt"
    notes.write_text("some notes\n")
    good = tmp_path / "good.jsonl"
    good.write_text(json.dumps(ROW) + "\n")
    blocked = tmp_path / "file"
    blocked.write_text("")
    cases = [
        (["--calibration", str(tmp_path / "missing.jsonl")], "does not exist"),
        (["--calibration", str(no_columns)], "lacks the columns a calibration report needs: "
         "run_id, round, algo, query_id, labeller_id, labeller_name, answer"),
        (["--calibration", str(picture)], "not UTF-8"),
        (["--calibration", str(notes)], "not a label export"),
        (["--calibration", str(tmp_path)], "is a folder"),
        (["--calibration", str(good), "--bins", "0.1,1"], "first edge must be 0"),
        (["--calibration", str(good), "--out", str(blocked / "sub")], "is a file, not a folder"),
        ([], "give a results folder, or --calibration EXPORT_FILE"),
        (["results/x", "--calibration", str(good)], "not both"),
        (["results/x", "--bins", "0,1"], "--bins goes with --calibration"),
    ]
    for args, message in cases:
        code, out, err = run_report(capsys, *args)
        assert code == 2, (args, out, err)
        assert message in err and err.count("\n") == 1, (args, err)


def test_an_unbounded_eps_interval_is_said_in_words() -> None:
    from figures.calibration import _eps_cell
    from labelstats.calibration_stats import EpsFit

    unbounded = EpsFit(0.0, 0.0, None, -3.0, 0.0, 0.0, 3, 0.95, wide=True)
    assert _eps_cell(unbounded) == "≥ 0.00, no upper bound (wide)"  # not "[0.00, ∞)"
    narrow = EpsFit(0.3, 0.28, 0.33, -50.0, 0.0, 0.0, 600, 0.95, wide=False)
    assert _eps_cell(narrow) == "[0.28, 0.33] (ε̂ 0.30)"
