"""The `sepoa` command's database commands: labellers and export, flags before or after the
action, and a clear error for a database that is not there."""

from __future__ import annotations

from sepoa.cli import main


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


def test_export_names_a_missing_database_and_writes_an_empty_one(tmp_path, capsys):
    data = tmp_path / "data"
    assert main(["export", "--data-dir", str(data)]) == 2
    assert "no queue database" in capsys.readouterr().err
    main(["labeller", "create", "zoe", "--data-dir", str(data)])  # migrates the database
    out = tmp_path / "labels.jsonl"
    assert main(["export", "--data-dir", str(data), "--out", str(out)]) == 0
    assert out.read_text() == "" and not (tmp_path / "labels.jsonl.partial").exists()
    assert main(["export", "--data-dir", str(data), "--run", "7"]) == 2
    assert "run 7 does not exist" in capsys.readouterr().err
