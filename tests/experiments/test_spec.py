"""Experiment specs: expansion into run folders, clear errors for bad specs."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest
from sepoa_docs import authors_overrides

from experiments.spec import SpecError, load_spec

ROOT = Path(__file__).resolve().parents[2]

GRID = """
name = "grid"
preset = "tiny"
steps = 600
tasks = ["dmc:cheetah_run", "dmc:walker_run"]
eps = [0.1, 0.3]
seeds = [0, 1, 2]
budgets = [20, 30]

[overrides]
"feedback.per_round" = 10
eval_every = 200

[variants.PEBBLE]
algo = "pebble"

[variants."S-EPOA w/o pretraining"]
algo = "sepoa"
"feedback.per_round" = 5
skill.pretrain_steps = 0
"""


def write(tmp_path: Path, text: str, name: str = "spec.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_a_grid_expands_into_one_folder_per_run(tmp_path: Path) -> None:
    spec = load_spec(write(tmp_path, GRID), check=False)
    runs = spec.runs()
    assert len(runs) == 2 * 2 * 2 * 2 * 3
    assert len({r.dir for r in runs}) == len(runs)
    run = next(r for r in runs if r.variant == "S-EPOA w/o pretraining" and r.seed == 2
               and r.eps == 0.1 and r.budget == 30 and r.task == "dmc:walker_run")
    assert run.dir == Path("dmc-walker_run/S-EPOA_w-o_pretraining/eps0.1/budget30/s2")
    # Shared overrides reach every run; the variant's win; the budget axis sets the budget.
    assert run.overrides == {"feedback.per_round": 5, "eval_every": 200,
                             "skill.pretrain_steps": 0, "feedback.budget": 30}
    cfg = run.config()
    assert (cfg.algo, cfg.seed, cfg.teacher.eps, cfg.feedback.budget) == ("sepoa", 2, 0.1, 30)
    assert cfg.feedback.per_round == 5 and cfg.skill.pretrain_steps == 0
    pebble = next(r for r in runs if r.variant == "PEBBLE")
    assert pebble.config().feedback.per_round == 10


BAD_SPECS = [
    ('[variants.PEBBLE]\nalgo = "pebble"', '[variants.X]\nalgo = "nope"',
     "[variants.\"X\"]: unknown algo 'nope'"),
    ('eval_every = 200', 'sac.width = 3', "[overrides]: unknown config field 'sac.width'"),
    ("seeds = [0, 1, 2]", "seeds = []", "'seeds' is empty"),
    ('tasks = ["dmc:cheetah_run", "dmc:walker_run"]\n', "", "missing required key 'tasks'"),
    ("eval_every = 200", "eval_every = 0.5", "'eval_every' takes int"),
    ("eval_every = 200", '"reward.surf" = "flase"', "'reward.surf' takes bool, got 'flase'; use"),
    ("eval_every = 200", '"teacher.eps" = 0.1', "'teacher.eps' is set by the spec's eps"),
    ("seeds = [0, 1, 2]", "seeds = [0, 1, 1]", "'seeds' lists 1 twice"),
    ('tasks = ["dmc:cheetah_run", "dmc:walker_run"]', 'tasks = ["dmc:cheetah_rum"]',
     "unknown task 'dmc:cheetah_rum'"),
    ('[variants.PEBBLE]\nalgo = "pebble"', '[variants.PEBBLE]\nsteps = 3',
     '[variants."PEBBLE"]: missing required key \'algo\''),
]


@pytest.mark.parametrize(("old", "new", "message"), BAD_SPECS)
def test_a_bad_spec_is_refused_with_a_message_naming_the_problem(
        tmp_path: Path, old: str, new: str, message: str) -> None:
    assert old in GRID
    path = write(tmp_path, GRID.replace(old, new, 1), "bad.toml")
    with pytest.raises(SpecError) as err:
        load_spec(path)
    assert str(err.value).startswith(f"{path}: ")
    assert message in str(err.value)


def test_a_bad_run_config_is_refused_before_anything_runs(tmp_path: Path) -> None:
    path = write(tmp_path, GRID.replace("eval_every = 200", '"feedback.selection" = "best"'))
    with pytest.raises(SpecError, match="unknown feedback.selection 'best'"):
        load_spec(path)


def test_a_variant_can_have_its_own_seeds_and_runs_are_queued_seed_first(tmp_path: Path) -> None:
    text = GRID.replace('budgets = [20, 30]\n', '').replace(
        'tasks = ["dmc:cheetah_run", "dmc:walker_run"]', 'tasks = ["dmc:cheetah_run"]').replace(
        'eps = [0.1, 0.3]', 'eps = [0.3]') + '\n[variants.SAC]\nalgo = "sac"\nseeds = [1]\n'
    spec = load_spec(write(tmp_path, text))
    assert [(r.variant, r.seed) for r in spec.runs_seed_first()] == [
        ("PEBBLE", 0), ("S-EPOA w/o pretraining", 0), ("SAC", 1),
        ("PEBBLE", 1), ("S-EPOA w/o pretraining", 1),
        ("PEBBLE", 2), ("S-EPOA w/o pretraining", 2)]
    assert "seeds" not in spec.variants[2].overrides


def test_a_part_of_the_grid_names_the_seeds_it_lacks(tmp_path: Path) -> None:
    """`--seed 1 --seed 7` where no variant runs seed 7: refused, not trained as seed 1 alone;
    a seed some other variant runs is fine when that variant is in the part."""
    text = GRID + '\n[variants.SAC]\nalgo = "sac"\nseeds = [5]\n'
    spec = load_spec(write(tmp_path, text), check=False)
    with pytest.raises(SpecError, match="runs no seed 7 with any variant; its seeds there: "
                                        "0, 1, 2, 5$"):
        spec.only(None, [1, 7])
    with pytest.raises(SpecError,
                       match="runs no seed 5 with 'PEBBLE'; its seeds there: 0, 1, 2$"):
        spec.only(["PEBBLE"], [0, 1, 5])
    part = spec.only(["PEBBLE", "SAC"], [1, 5])
    assert sorted((r.variant, r.seed) for r in part.runs() if r.task == "dmc:cheetah_run"
                  and r.eps == 0.1 and r.budget == 20) == [("PEBBLE", 1), ("SAC", 5)]


def test_within_a_seed_a_second_run_of_one_snapshot_is_queued_after_those_needing_none() -> None:
    # The authors' grid: both S-EPOA arms of a seed start from one snapshot. Queued after
    # PEBBLE and SURF, the second finds it pretrained by the first's worker instead of waiting.
    spec = load_spec(ROOT / "specs" / "small" / "sepoa-authors.toml")
    order = [(r.variant, r.seed) for r in spec.runs_seed_first()]
    assert order[:5] == [("S-EPOA (paper)", 10), ("PEBBLE", 10), ("SURF", 10),
                         ("S-EPOA (authors)", 10), ("S-EPOA (paper)", 11)]
    paper, authors = (next(r for r in spec.runs() if r.variant == v and r.seed == 10)
                      for v in ("S-EPOA (paper)", "S-EPOA (authors)"))
    assert paper.snapshot() == authors.snapshot() is not None
    assert next(r for r in spec.runs() if r.variant == "PEBBLE").snapshot() is None


def test_the_docs_authors_overrides_are_the_authors_grids_variant() -> None:
    with open(ROOT / "specs" / "small" / "sepoa-authors.toml", "rb") as f:
        variant = tomllib.load(f)["variants"]["S-EPOA (authors)"]
    # Beyond the algorithm and the grid's pretraining length, the same overrides.
    assert authors_overrides() == {k: v for k, v in variant.items()
                                   if k not in ("algo", "skill.pretrain_steps")}


@pytest.mark.parametrize("analysis, message", [
    ('metric = "final_quarter"\nreference = "PEBBLE"\ncompare_to = ["SURF"]',
     "'SURF' is not a variant; variants: PEBBLE, S-EPOA w/o pretraining"),
    ('metric = "best"\nreference = "PEBBLE"\ncompare_to = ["PEBBLE"]',
     "unknown metric 'best'; valid: final_quarter"),
    ('metric = "final_quarter"\nreference = "PEBBLE"', "takes the keys"),
    ('metric = "final_quarter"\nreference = "PEBBLE"\ncompare_to = ["S-EPOA w/o pretraining"]'
     '\nalso = [["PEBBLE"]]', "'also' must be a list of pairs"),
    ('metric = "final_quarter"\nreference = "PEBBLE"\ncompare_to = ["S-EPOA w/o pretraining"]'
     '\nalso = [["SAC", "PEBBLE"]]', "'SAC' is not a variant"),
])
def test_a_bad_analysis_is_refused_by_name(tmp_path: Path, analysis: str, message: str) -> None:
    with pytest.raises(SpecError, match=message.replace("(", r"\(")):
        load_spec(write(tmp_path, GRID + "\n[analysis]\n" + analysis + "\n"))


def test_the_true_reward_decomposition_preregisters_its_three_comparisons() -> None:
    spec = load_spec(ROOT / "specs" / "small" / "sepoa-true-reward.toml")
    assert spec.analysis is not None
    b, c = "S-EPOA agent, true reward", "S-EPOA agent, true reward, no pretraining"
    assert spec.analysis.pairs() == [(b, "SAC"), (b, c), (c, "SAC")]
    configs = {r.variant: r.config() for r in spec.runs() if r.seed == 10}
    assert configs[b].reward.true_reward and configs[c].reward.true_reward
    assert configs[b].skill.pretrain_steps == 200_000 and configs[c].skill.pretrain_steps == 0
    # The fair grid's S-EPOA settings, written out: its run is the labelled counterpart.
    fair = {r.variant: r.config() for r in load_spec(
        ROOT / "specs" / "small" / "sepoa-fair.toml").runs() if r.seed == 10}["S-EPOA"]
    assert configs[b].skill == fair.skill and configs[b].feedback.every == fair.feedback.every
    assert [r.seed for r in spec.runs_seed_first()][:3] == [10, 10, 10]


def test_the_fair_comparison_spec_preregisters_its_analysis() -> None:
    spec = load_spec(ROOT / "specs" / "small" / "sepoa-fair.toml")
    assert spec.analysis is not None and spec.analysis.metric == "final_quarter"
    assert (spec.analysis.reference, spec.analysis.compare_to) == ("S-EPOA", ("SURF", "PEBBLE"))
    seeds = {v.label: len(v.seeds or spec.seeds) for v in spec.variants}
    assert seeds["S-EPOA"] == seeds["SURF"] == seeds["PEBBLE"] == 8
    # Equal update budgets and the same labels for every arm.
    configs = {r.variant: r.config() for r in spec.runs()}
    assert {c.update_every for c in configs.values()} == {1}
    assert {(c.feedback.budget, c.feedback.per_round, c.feedback.every)
            for c in configs.values()} == {(1000, 100, 5000)}
