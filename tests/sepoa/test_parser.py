"""The one parser of the `sepoa` command: a bad value, an unknown flag or command is one line
naming the problem and what is valid, exit status 2, no traceback, whichever command it is;
every command builds and has help; the commands the README and docs show exist; and a command
that needs no trainer does not import torch."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from sepoa.cli import COMMANDS, build_parser, main
from sepoa.parser import integer, real

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(("argv", "words"), [
    (["worker", "--threads", "two"], ["sepoa worker: error: argument --threads:",
                                      "'two' is not a whole number"]),
    (["worker", "--poll-seconds", "soon"], ["--poll-seconds", "'soon' is not a number"]),
    (["doctor", "--size", "1.5"], ["--size", "'1.5' is not a whole number"]),
    (["up", "--workers", "many"], ["--workers", "'many' is not a whole number"]),
    (["experiment", "run", "spec.toml", "--workers", "x"],
     ["sepoa experiment run: error:", "'x' is not a whole number"]),
    (["reward", "fit", "d", "--holdout", "0.95"], ["--holdout", "'0.95' is not a share",
                                                   "give 0 to 0.9"]),
    (["reward", "fit", "d", "--epochs", "0"], ["--epochs", "'0' is not a number of epochs",
                                               "give at least 1"]),
    (["label-dataset", "d", "--budget", "-3"], ["--budget", "'-3' is not a budget",
                                                "give 1 to 2147483647"]),
    (["pretrain", "--quality-skills", "3"], ["--quality-skills", "'3' is too few skills",
                                             "give 0 (no quality measurement) or at least 5"]),
    (["train", "--reward.surf", "flase"], ["--reward.surf", "true/false, yes/no, on/off or 1/0"]),
    (["export", "--format", "xml"], ["invalid choice: 'xml'", "'jsonl', 'csv', 'parquet'"]),
    (["serve", "--prot", "80"], ["unrecognized arguments: --prot 80"]),
    (["labeller", "rename", "x"], ["invalid choice: 'rename'", "'create'"]),
    (["trian"], ["invalid choice: 'trian'", "'train'"]),
    ([], ["the following arguments are required: COMMAND"]),
])
def test_a_mistake_is_one_line_with_exit_status_2(argv: list[str], words: list[str],
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        main(argv)
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.endswith("--help)\n"), err
    assert all(word in err for word in words), err


def test_pretrain_takes_the_quality_skills_the_measurement_needs() -> None:
    from sepoa.trainer_commands import QUALITY_TOP, _quality_skills
    from trainer.skills.quality import TOP

    assert QUALITY_TOP == TOP
    assert [_quality_skills(n) for n in ("0", "5", "50")] == [0, 5, 50]


def test_typed_values_name_the_range() -> None:
    port = integer("a TCP port", 1, 65535)
    assert port("8000") == 8000
    for text in ("0", "65536", "http", "80.0"):
        with pytest.raises(Exception, match=rf"'{re.escape(text)}' is not a TCP port: give 1 to"):
            port(text)
    share = real("a share", 0, 0.9)
    assert share("0.25") == 0.25
    for text in ("nan", "inf", "-0.1", "half"):
        with pytest.raises(Exception, match="is not a share: give 0 to 0.9"):
            share(text)


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_command_builds_and_has_help(name: str,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        build_parser(name).parse_args([name, "--help"])
    assert exited.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: sepoa {name}")


def test_train_and_pretrain_help_show_the_defaults_an_absent_flag_takes(
        capsys: pytest.CaptureFixture[str]) -> None:
    """Without --preset a run is the paper's (1 M steps, 1024-wide nets), without --task
    cheetah run; a configuration field left out is the preset's, never "None"."""
    for name in ("train", "pretrain"):
        with pytest.raises(SystemExit):
            main([name, "--help"])
        out = " ".join(capsys.readouterr().out.split())
        assert "None" not in out, name
        assert "(default: dmc:cheetah_run)" in out and "(default: paper)" in out, name
        assert re.search(r"--sac\.lr FLOAT [^(]*\(default: the preset's\)", out), name


def test_the_help_names_snapshots_as_pretraining_does(
        capsys: pytest.CaptureFixture[str]) -> None:
    """pretrain --out and the skill.snapshot_dir field give the name with its settings hash
    (`runvocab.snapshot_names.default_snapshot_path`)."""
    from runvocab.config import build_config
    from runvocab.snapshot_names import default_snapshot_path

    name = os.path.basename(default_snapshot_path(build_config("dmc:cheetah_run", "tiny", {})))
    assert re.fullmatch(r"dmc-cheetah_run-aps-\d+-s0-[0-9a-f]{10}\.pt", name), name
    for command, flag in (("pretrain", "--out OUT"), ("train", "--skill.snapshot-dir STR")):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        out = " ".join(capsys.readouterr().out.split("options:")[1].split())
        said = out.replace("- <", "-<").split(flag)[1].split(" --")[0]
        assert "<task>-<backend>-<steps>-s<seed>-<hash>.pt" in said, (command, said)


def test_the_top_level_help_lists_every_command(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    assert all(re.search(rf"^    {re.escape(name)}\b", out, re.M) for name in COMMANDS), out
    # Every action of a command is in its line: labeller's token, invite's participants.
    lines = " ".join(out.split())
    assert "revoke or restore labellers, or give one a new token" in lines
    assert "or list an invite's participants" in lines


def test_the_commands_the_docs_show_exist(capsys: pytest.CaptureFixture[str]) -> None:
    """Each `sepoa <command> [<word>]` in the README and docs parses (with --help): the
    command exists, and so does its action (`sepoa experiment run`, `sepoa labeller create`)."""
    shown = set()
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for found in re.finditer(r"`sepoa ([a-z][a-z-]*)(?: ([a-z][a-z-]*))?", path.read_text()):
            shown.add(found.groups())
    assert len(shown) > 10, shown
    for name, word in sorted(shown, key=str):
        with pytest.raises(SystemExit) as exited:
            main([name, *([word] if word else []), "--help"])
        assert exited.value.code == 0, (name, word, capsys.readouterr().err)
    capsys.readouterr()


def test_a_command_without_the_trainer_does_not_import_torch() -> None:
    code = ("import sys; from sepoa.cli import build_parser, command; "
            "[build_parser(n) for n in ('serve', 'export', 'labeller', 'experiment')]; "
            "print(sorted(m for m in ('torch', 'mujoco') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, env=os.environ | {"PYTHONPATH": str(ROOT)}, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stderr
