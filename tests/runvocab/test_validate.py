"""The run vocabulary: one check of a whole configuration, and the configuration a queued run
describes; every refusal names the field and what is valid."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from runvocab.config import PRESETS, build_config
from runvocab.names import ALGOS, SIZE_PRESETS, ConfigError, all_tasks
from runvocab.queued_run import queued_run_config
from runvocab.validate import validate

ROOT = Path(__file__).resolve().parents[2]
PAPER_TASKS = ("dmc:cheetah_run", "dmc:walker_run", "dmc:quadruped_walk", "metaworld:door-open")


def refusal(overrides: dict, task: str = "dmc:cheetah_run") -> ConfigError:
    with pytest.raises(ConfigError) as err:
        validate(build_config(task, "tiny", overrides))
    return err.value


def queued(**fields) -> dict:
    return {"task": "dmc:cheetah_run", "algo": "pebble", "preset": "tiny", "seed": 0,
            "budget": 30, "teacher_params": {}, "config": {}} | fields


def test_the_package_imports_neither_torch_nor_mujoco_nor_the_trainer() -> None:
    probe = ("import sys, runvocab.config, runvocab.names, runvocab.validate, "
             "runvocab.queued_run, runvocab.answers, runvocab.query_fields; "
             "runvocab.names.all_tasks(); print(sorted(m for m in sys.modules if m.split('.')[0] "
             "in ('torch', 'mujoco', 'dm_control', 'metaworld', 'numpy', 'sqlalchemy', "
             "'trainer', 'server', 'labelqueue')))")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                            check=True, cwd=ROOT)
    assert result.stdout.strip() == "[]"
    for path in (ROOT / "runvocab").glob("*.py"):  # not even a lazy import further down
        tree = ast.parse(path.read_text())
        modules = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
        modules |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        banned = {"torch", "mujoco", "numpy", "sqlalchemy", "trainer", "server", "labelqueue"}
        assert not {m.split(".")[0] for m in modules} & banned, path.name


def test_the_size_presets_are_the_named_ones() -> None:
    assert tuple(PRESETS) == SIZE_PRESETS


@pytest.mark.parametrize("preset", SIZE_PRESETS)
@pytest.mark.parametrize("algo", ALGOS)
@pytest.mark.parametrize("task", PAPER_TASKS)
def test_every_preset_of_every_algorithm_on_the_paper_tasks_is_valid(task, algo, preset) -> None:
    validate(build_config(task, preset, {"algo": algo}))


@pytest.mark.parametrize(("overrides", "field", "words"), [
    ({"algo": "sepoaa"}, "algo", ["did you mean 'sepoa'", "valid: sac, pebble"]),
    ({"feedback.selection": "disagrement"}, "feedback.selection", ["'disagreement'"]),
    ({"teacher.kind": "noisey"}, "teacher.kind", ["'noisy'", "bpref"]),
    ({"skill.backend": "apz"}, "skill.backend", ["'aps'", "diayn, cic"]),
    ({"device": "gpu"}, "device", ["auto, cpu, cuda"]),
    ({"feedback.per_round": 0}, "feedback.per_round", ["must be positive"]),
    ({"teacher.eps": 1.5}, "teacher.eps", ["[0, 1)"]),
    ({"feedback.selection": "skill"}, "feedback.selection", ["use algo sepoa"]),
    ({"algo": "surf", "feedback.segment_length": 50, "reward.surf_crop_max": 55},
     "reward.surf_crop_max", ["exceeds feedback.segment_length"]),
    ({"algo": "surf", "reward.surf_threshold": 0.3}, "reward.surf_threshold", ["(0.5, 1)"]),
    ({"reward.rune": True, "reward.rune_decay": 1.0}, "reward.rune_decay", ["[0, 1)"]),
    ({"reward.rune": True, "reward.rune_beta0": -0.1}, "reward.rune_beta0", ["negative"]),
    ({"reward.rime": True, "reward.rime_beta_min": 4.0}, "reward.rime_beta_min", ["at most"]),
    ({"reward.rime": True, "reward.rime_k": 0.0}, "reward.rime_k", ["positive"]),
    ({"algo": "sepoa", "skill.knn_k": 100}, "skill.knn_k", ["exceeds the batch"]),
    ({"algo": "sepoa", "skill.initial_rollouts": 500}, "skill.initial_rollouts",
     ["pool_trajectories"]),
])
def test_a_bad_field_is_named_with_what_is_valid(overrides, field, words) -> None:
    err = refusal(overrides)
    assert err.field == field and field in str(err)
    for word in words:
        assert word in str(err)


def test_an_unknown_task_gets_a_near_miss_and_its_family() -> None:
    err = refusal({}, task="dmc:cheetah_runn")
    assert err.field == "task"
    assert "did you mean 'dmc:cheetah_run'" in str(err)
    assert "dmc:walker_run" in str(err) and "metaworld:" not in str(err)
    assert "did you mean 'dmc:cheetah_run'" in str(refusal({}, task="cheetah_run"))
    assert "<family>:<name>" in str(refusal({}, task="gym:Pendulum"))


def test_the_task_list_covers_both_suites() -> None:
    tasks = all_tasks()
    assert set(PAPER_TASKS) <= set(tasks) and len(tasks) == len(set(tasks))


def test_an_unknown_field_gets_a_near_miss() -> None:
    with pytest.raises(ConfigError, match=r"'feedback.per_rund' \(did you mean "
                                          r"'feedback.per_round'\?\)") as err:
        build_config("dmc:cheetah_run", "tiny", {"feedback.per_rund": 10})
    assert err.value.field == "feedback.per_rund"
    with pytest.raises(ConfigError, match="did you mean 'small'"):
        build_config("dmc:cheetah_run", "smal")


def test_a_queued_run_becomes_its_training_configuration() -> None:
    cfg = queued_run_config(**queued(algo="sepoa", seed=3, budget=20,
                                     teacher_params={"eps": 0.1},
                                     config={"sac.lr": 1e-3, "teacher.eps": 0.1}))
    assert (cfg.algo, cfg.seed, cfg.feedback.budget, cfg.teacher.eps, cfg.sac.lr) == (
        "sepoa", 3, 20, 0.1, 1e-3)
    assert cfg.feedback.selection == "skill"  # the algorithm's preset applies


@pytest.mark.parametrize(("fields", "field", "words"), [
    ({"config": {"feedback.per_rund": 10}}, "feedback.per_rund",
     ["unknown config field", "did you mean 'feedback.per_round'"]),
    ({"config": {"sac.lr": "fast"}}, "sac.lr", ["takes float"]),
    ({"config": {"feedback.budget": 500}}, "feedback.budget", ["top-level field says 30"]),
    ({"config": {"algo": "sac"}}, "algo", ["'sac'", "says 'pebble'"]),
    ({"config": {"seed": 1}}, "seed", ["says 0"]),
    ({"config": {"task": "dmc:walker_run"}}, "task", ["says 'dmc:cheetah_run'"]),
    ({"config": {"run_dir": "/tmp/x"}}, "run_dir", ["worker"]),
    ({"config": {"teacher.eps": 0.2}, "teacher_params": {"eps": 0.1}}, "teacher.eps",
     ["teacher_params says 0.1"]),
    ({"teacher_params": {"epss": 0.1}}, "teacher.epss",
     ["teacher_params:", "did you mean 'teacher.eps'"]),
    ({"task": "dmc:cheetah_runn"}, "task", ["did you mean 'dmc:cheetah_run'"]),
    ({"preset": "huge"}, "preset", ["valid: paper, small, tiny"]),
])
def test_a_queued_run_that_contradicts_itself_or_names_nothing_is_refused(fields, field,
                                                                          words) -> None:
    with pytest.raises(ConfigError) as err:
        queued_run_config(**queued(**fields))
    assert err.value.field == field
    for word in words:
        assert word in str(err.value)


def test_a_config_that_repeats_a_top_level_field_is_accepted() -> None:
    cfg = queued_run_config(**queued(config={"algo": "pebble", "feedback.budget": 30}))
    assert cfg.feedback.budget == 30
