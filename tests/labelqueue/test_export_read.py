"""Export files as the calibration report reads them: a database export gives the same report
in every format, and a file that is not an export is refused in one line."""

from __future__ import annotations

import random
from pathlib import Path

import pytest
from queue_helpers import running_run
from sqlalchemy.orm import Session

from labelqueue import create_labeller, lease_next_query, push_queries, submit_label
from labelstats.calibration import REQUIRED_COLUMNS, calibration_report
from rundata.export_read import ExportFileError, read_export
from rundata.label_files import write_export


def test_every_export_format_gives_the_same_report(session: Session, tmp_path: Path) -> None:
    run = running_run(session)
    rng = random.Random(3)
    specs = []
    for i in range(40):
        first, second = 100 + rng.uniform(-60, 60), 100 + rng.uniform(-60, 60)
        specs.append({"round": i // 20, "position": i % 20, "segment_length": 50,
                      "first_trajectory": 2 * i, "first_start": 0,
                      "second_trajectory": 2 * i + 1, "second_start": 0,
                      "first_segment_return": first / 20, "second_segment_return": second / 20,
                      "first_trajectory_return": first, "second_trajectory_return": second,
                      "needs_labels": 2})
    push_queries(session, run_id=run.id, queries=specs)
    people = [create_labeller(session, name=name)[0].id for name in ("ann", "bob")]
    choices = ["left", "right", "equal", "cant_tell", "skip"]
    for turn in range(80):
        labeller = people[turn % 2]
        query = lease_next_query(session, labeller_id=labeller, run_id=run.id)
        assert query is not None
        submit_label(session, query_id=query.id, labeller_id=labeller,
                     choice=rng.choice(choices), left_is_first=rng.random() < 0.5)
    reports = []
    for fmt in ("jsonl", "csv", "parquet"):
        path = tmp_path / f"labels.{fmt}"
        with open(path, "wb") as file:
            assert write_export(session, fmt=fmt, out=file) == 80
        rows = read_export(str(path))
        assert set(REQUIRED_COLUMNS) <= set(rows[0])
        reports.append(calibration_report(rows))
    assert reports[0] == reports[1] == reports[2]
    assert [g.name for g in reports[0].labellers] == ["ann", "bob"]
    assert reports[0].everyone.rates.answers == 80


def test_files_that_are_not_exports_are_refused_in_one_line(tmp_path: Path) -> None:
    cases = {
        "missing.jsonl": (None, "does not exist"),
        "notes.txt": (b"hello\n", "not a label export"),
        "bad.jsonl": (b'{"a": 1}\nnot json\n', "line 2: not JSON"),
        "bad.csv": (b"label_id,run_id\n1\n", "line 2: 1 cells under a header of 2"),
        "bad.parquet": (b"PAR1 not really", "not a readable Parquet file"),
        "binary.csv": (b"\xff\xfe\x00", "not UTF-8"),
    }
    for name, (content, message) in cases.items():
        path = tmp_path / name
        if content is not None:
            path.write_bytes(content)
        with pytest.raises(ExportFileError, match=message) as caught:
            read_export(str(path))
        assert "\n" not in str(caught.value)
    with pytest.raises(ExportFileError, match="is a folder"):
        read_export(str(tmp_path))
