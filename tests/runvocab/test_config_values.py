"""One parser for a field's value, on the command line and in JSON: the same spellings are
taken on both paths, and anything else is refused in one line that names the field and what it
takes (a bad bool lists the valid spellings) instead of running with another value."""

from __future__ import annotations

import argparse

import pytest

from runvocab.config import add_config_arguments, overrides_from_args, typed_overrides
from runvocab.config.args import field_docs
from runvocab.config.presets import WRITTEN_WHEN_SET, build_config, from_dict, to_dict
from runvocab.config.schema import RewardConfig, parse_value
from runvocab.names import ConfigError

SPELLINGS = "true/false, yes/no, on/off or 1/0"


def from_command_line(*argv: str) -> dict:
    parser = argparse.ArgumentParser(prog="sepoa train")
    add_config_arguments(parser)
    return overrides_from_args(parser.parse_args(list(argv)))


@pytest.mark.parametrize(("text", "value"), [
    ("true", True), ("YES", True), ("on", True), ("1", True),
    ("false", False), ("No", False), ("OFF", False), ("0", False),
])
def test_a_bool_takes_the_same_spellings_on_the_command_line_and_in_json(text, value) -> None:
    assert from_command_line("--reward.surf", text) == {"reward.surf": value}
    assert typed_overrides({"reward.surf": text}) == {"reward.surf": value}


def test_json_booleans_and_0_or_1_are_bools() -> None:
    assert typed_overrides({"reward.surf": True, "reward.rune": 0, "reward.rime": 1}) == {
        "reward.surf": True, "reward.rune": False, "reward.rime": True}


def test_a_bad_bool_on_the_command_line_is_one_line_with_the_valid_spellings(capsys) -> None:
    with pytest.raises(SystemExit) as exit_:
        from_command_line("--reward.surf", "flase")
    assert exit_.value.code == 2
    [error] = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert "argument --reward.surf: config field 'reward.surf' takes bool, got 'flase'" in error
    assert SPELLINGS in error


@pytest.mark.parametrize("value", ["flase", "", 2, 0.5, None, [True]])
def test_a_bad_bool_in_json_is_refused_with_the_valid_spellings(value) -> None:
    with pytest.raises(ConfigError) as err:
        typed_overrides({"feedback.wait_for_labels": value})
    assert err.value.field == "feedback.wait_for_labels"
    assert str(err.value) == (f"config field 'feedback.wait_for_labels' takes bool, got "
                              f"{value!r}; use {SPELLINGS}")


@pytest.mark.parametrize(("path", "given", "value"), [
    ("steps", "1e6", 1_000_000), ("steps", "2.0", 2), ("steps", 3.0, 3), ("steps", "12", 12),
    ("sac.lr", "1e-4", 1e-4), ("sac.lr", 3, 3.0), ("teacher.beta", "inf", float("inf")),
    ("task", "dmc:walker_run", "dmc:walker_run"),
    ("sac.betas", "0.8,0.99", (0.8, 0.99)), ("sac.betas", [0.8, 1], (0.8, 1.0)),
])
def test_numbers_text_and_pairs_parse_alike_from_both_paths(path, given, value) -> None:
    parsed = parse_value(path, given)
    assert parsed == value and type(parsed) is type(value)


@pytest.mark.parametrize(("path", "given", "takes"), [
    ("steps", "1.5e0", "int"), ("steps", 1.5, "int"), ("steps", True, "int"),
    ("steps", "many", "int"), ("steps", "inf", "int"), ("sac.lr", "fast", "float"),
    ("sac.lr", False, "float"), ("task", 5, "str"),
    ("sac.betas", "0.9", "2 values (float, float), comma-separated"),
    ("sac.betas", [0.9, 0.99, 0.1], "2 values (float, float), comma-separated"),
])
def test_a_value_of_the_wrong_kind_is_refused_not_rounded(path, given, takes) -> None:
    with pytest.raises(ConfigError) as err:
        parse_value(path, given)
    assert str(err.value) == f"config field {path!r} takes {takes}, got {given!r}"
    if isinstance(given, str):  # what the command line can give
        with pytest.raises(SystemExit):
            from_command_line(f"--{path}", given)


def test_an_unknown_field_is_named_with_a_near_miss() -> None:
    with pytest.raises(ConfigError, match="did you mean 'reward.surf'"):
        typed_overrides({"reward.surff": True})


def test_a_flag_is_helped_by_its_whole_docstring() -> None:
    doc = field_docs()[RewardConfig, "rime"]
    assert doc.startswith("RIME: train only on labels") and doc.endswith("before the first round")
    assert "\n" not in doc


@pytest.mark.parametrize("path", WRITTEN_WHEN_SET)
def test_a_later_field_is_stored_only_when_set_so_older_config_files_stay_equal(path) -> None:
    head, _, leaf = path.partition(".")
    default = build_config("dmc:cheetah_run", "small")
    assert leaf not in to_dict(default)[head]  # as config.json files written before it
    stored = getattr(getattr(default, head), leaf)
    value = ("/some/model.pt" if path == "reward.init_from"
             else not stored if isinstance(stored, bool) else True)
    changed = build_config("dmc:cheetah_run", "small", {path: value})
    assert to_dict(changed)[head][leaf] == value
    assert from_dict(to_dict(changed)) == changed and from_dict(to_dict(default)) == default
