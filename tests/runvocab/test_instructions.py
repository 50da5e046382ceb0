"""Every task tells its labellers what "better" means, in a text of its own; an unknown task gets
one built from its name; clip sizes and the clip speed against real time are known per task."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from runvocab.clip_format import (
    CLIP_FPS,
    CLIP_SIZES,
    DEFAULT_CLIP_SIZE,
    parse_clip_size,
    real_time_ratio,
    step_seconds,
)
from runvocab.instructions import (
    MAX_CHARS,
    clean_instruction,
    default_instruction,
    generic_instruction,
    instruction_sha256,
    run_instruction,
    specific_instruction,
    tie_kind,
    tie_sentence,
)
from runvocab.names import all_tasks

ROOT = Path(__file__).resolve().parents[2]


def test_the_modules_import_neither_torch_nor_mujoco() -> None:
    probe = ("import sys, runvocab.instructions, runvocab.clip_format; print(sorted(m for m in "
             "sys.modules if m.split('.')[0] in ('torch', 'mujoco', 'dm_control', 'metaworld', "
             "'numpy', 'trainer', 'server', 'labelqueue')))")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                            check=True, cwd=ROOT)
    assert result.stdout.strip() == "[]"


@pytest.mark.parametrize("task", all_tasks())
def test_every_task_has_an_instruction_of_its_own(task: str) -> None:
    text = specific_instruction(task)
    assert text is not None, f"{task} has no instruction of its own"
    goal, how = text.split("\n")
    assert goal.endswith(".") and how.endswith(".")
    assert 20 <= len(text) <= MAX_CHARS
    assert default_instruction(task) == text
    assert clean_instruction(text) == text  # an operator could store it as it is


def test_the_papers_four_tasks_say_at_least_what_the_papers_instructions_say() -> None:
    cheetah = default_instruction("dmc:cheetah_run").lower()
    assert all(word in cheetah for word in ("fast", "forward", "sprint", "posts", "ground"))
    walker = default_instruction("dmc:walker_run").lower()
    assert all(word in walker for word in ("upright", "first", "faster", "right", "ground"))
    for task, speed in (("dmc:quadruped_walk", "steady walk"), ("dmc:quadruped_run", "fast run")):
        quadruped = default_instruction(task).lower()
        assert all(word in quadruped for word in ("upright", "first", "faster", speed, "higher"))
    door = default_instruction("metaworld:door-open").lower()
    assert "open" in door and "handle" in door


# Lengths and speeds in units nobody can see in a clip (the clips show no scale but the floor's
# squares and the posts): "0.6 m", "10 m/s", "2 cm", "1.4 metres".
UNSEEN_UNITS = re.compile(r"\d\s*(m|cm|mm|km|m/s|km/h|metres?|meters?|centimetres?)\b",
                          re.IGNORECASE)
TIE_KINDS = {"often", "sometimes", "rare"}


def parts(task: str) -> tuple[str, str, str]:
    """(goal line, what decides, the tie sentence) of the task's instruction."""
    goal, how = default_instruction(task).split("\n")
    tie = tie_sentence(task)
    assert tie and how.endswith(tie), f"{task}: no tie sentence at the end of {how!r}"
    return goal, how.removesuffix(tie).strip(), tie


def check_parts(task: str, decides_words: tuple[str, ...]) -> None:
    goal, decides, tie = parts(task)
    assert goal and decides, task
    # What the reward measures: a rule that says what is preferred.
    assert any(word in decides for word in decides_words), f"{task}: {decides!r}"
    # What ties look like: one of the three kinds (trainer/tie_check.py checks it).
    assert tie_kind(task) in TIE_KINDS, f"{task}: {tie!r}"
    assert not UNSEEN_UNITS.search(default_instruction(task)), (
        f"{task}: {UNSEEN_UNITS.search(default_instruction(task))[0]!r}")


@pytest.mark.parametrize("task", [t for t in all_tasks() if t.startswith("dmc:")])
def test_every_dmc_instruction_says_what_is_measured_and_what_ties_look_like(task: str) -> None:
    check_parts(task, ("Prefer", "prefer"))


@pytest.mark.parametrize("task", [t for t in all_tasks() if t.startswith("metaworld:")])
def test_every_metaworld_instruction_says_what_is_measured_and_what_ties_look_like(
    task: str,
) -> None:
    check_parts(task, ("Best", "Prefer"))
    # Dense rewards (reaching alone pays a little), but for the three trainer.tie_check finds
    # exact ties in.
    tying = {"metaworld:dial-turn", "metaworld:drawer-close", "metaworld:pick-place-wall",
             "metaworld:shelf-place"}
    assert (tie_kind(task) == "rare") == (task not in tying)


def test_the_generic_instruction_has_a_tie_sentence_too() -> None:
    check_parts("dmc:juggler_juggle", ("Prefer",))
    assert tie_kind("metaworld:hammer-throw") == "sometimes"


def test_the_tie_sentences_of_the_issues_cases() -> None:
    """hopper_hop's reward is 0 unless the body is up high and moving forward: early pairs are
    nearly all exact ties, which the text must say; walker's never is."""
    assert tie_kind("dmc:hopper_hop") == "often"
    assert "equally good" in tie_sentence("dmc:hopper_hop")
    assert tie_kind("dmc:cheetah_run") == "sometimes"
    assert tie_kind("dmc:walker_run") == "rare"
    for task in ("dmc:hopper_stand", "dmc:walker_stand", "dmc:humanoid_run"):
        assert not UNSEEN_UNITS.search(default_instruction(task))
    assert UNSEEN_UNITS.search("counts fully at 0.6 m") and UNSEEN_UNITS.search("10 m/s")


def test_a_task_without_its_own_instruction_gets_one_from_its_name() -> None:
    assert specific_instruction("dmc:juggler_juggle") is None
    text = default_instruction("dmc:juggler_juggle")
    assert text == generic_instruction("dmc:juggler_juggle")
    assert "juggler juggle" in text and "Prefer" in text
    assert "hammer throw" in default_instruction("metaworld:hammer-throw")
    assert default_instruction("nonsense")  # never nothing


def test_an_operators_text_replaces_the_default_and_is_checked() -> None:
    assert run_instruction("dmc:cheetah_run", None) == default_instruction("dmc:cheetah_run")
    assert run_instruction("dmc:cheetah_run", "  Go.  ") == "Go."
    assert clean_instruction(" a\r\nb\r") == "a\nb"
    for bad, words in (("", "empty"), (" \n ", "empty"), ("x" * (MAX_CHARS + 1), "at most"),
                       ("a\x07", "control")):
        with pytest.raises(ValueError, match=words):
            clean_instruction(bad)
    assert instruction_sha256("Go.") == instruction_sha256("Go.") != instruction_sha256("Go!")
    assert len(instruction_sha256("Go.")) == 64


@pytest.mark.parametrize("task", all_tasks())
def test_every_task_knows_how_fast_its_clips_play_against_real_time(task: str) -> None:
    seconds = step_seconds(task)
    assert seconds is not None and 0.005 <= seconds <= 0.05
    ratio = real_time_ratio(task)
    assert ratio == pytest.approx(seconds * CLIP_FPS)


def test_clip_sizes_and_the_frame_rate() -> None:
    assert CLIP_SIZES[DEFAULT_CLIP_SIZE] == (256, 256)
    assert parse_clip_size("320x240") == (320, 240)
    with pytest.raises(ValueError, match="256x256"):
        parse_clip_size("640x480")
    assert 50 / CLIP_FPS == pytest.approx(1.5)  # the paper's labellers saw 50 steps in 1.5 s
    # cheetah: 10 ms a step, so a clip shows a third of real speed; walker: 25 ms, 0.83x
    assert real_time_ratio("dmc:cheetah_run") == pytest.approx(1 / 3)
    assert real_time_ratio("dmc:walker_run") == pytest.approx(0.25 / 0.3)
    assert step_seconds("dmc:humanoid_CMU_run") == 0.02
    assert step_seconds("dmc:humanoid_run") == 0.025
    assert step_seconds("dmc:ball_in_cup_catch") == 0.02
    assert step_seconds("atari:pong") is None and real_time_ratio("atari:pong") is None
