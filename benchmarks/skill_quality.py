"""Skill quality against pretraining length: run the pretrainings of a skill-quality spec
(specs/small/skill-quality.toml) and report their snapshots' quality.

    .venv/bin/python benchmarks/skill_quality.py run SPEC --results results [--workers 2]
    .venv/bin/python benchmarks/skill_quality.py report SPEC --results results [--out DIR]

`run` starts one `sepoa pretrain` per seed (at most `--workers` at a time), with the spec's
intermediate snapshots; each measures its snapshots' skill quality as it writes them
(`trainer/skills/quality.py`). Running it again goes on where a killed pretraining stopped (its
`.partial` file) and skips finished seeds. Logs: <results>/<name>/seed-<seed>.log.

`report` applies the spec's pre-registered rule to every snapshot measured so far: the top-5
mean of the skills' returns against random actions', each with a bootstrap interval over its 50
episodes, and writes report.md, quality.csv and the measured quality files to
specs/<size>/reports/<name>/ (or --out). A length is missing from the table until both seeds
reach it; the report says so.
"""

from __future__ import annotations

import argparse
import csv
import glob
import json
import os
import shutil
import subprocess
import sys
import tomllib
from typing import Any

import numpy as np

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
TOP = 5


def load_spec(path: str) -> dict[str, Any]:
    with open(path, "rb") as f:
        spec = tomllib.load(f)
    missing = {"name", "task", "preset", "backend", "steps", "snapshots_at", "seeds"} - set(spec)
    if missing:
        raise SystemExit(f"{path}: missing {', '.join(sorted(missing))}")
    return spec


def snapshot_dir(spec: dict[str, Any], results: str) -> str:
    return os.path.join(results, spec["name"], "snapshots")


def pretrain_command(spec: dict[str, Any], seed: int, results: str) -> list[str]:
    return [
        os.path.join(ROOT, ".venv", "bin", "sepoa"), "pretrain", "--task", spec["task"],
        "--preset", spec["preset"], "--seed", str(seed), "--steps", str(spec["steps"]),
        "--skill.backend", spec["backend"], "--threads", str(spec.get("threads", 1)),
        "--skill.snapshot_dir", snapshot_dir(spec, results),
        "--snapshots-at", ",".join(str(s) for s in spec["snapshots_at"]),
        "--quality-skills", str(spec.get("quality_skills", 50)), "--no-progress",
    ]


def run(spec: dict[str, Any], results: str, workers: int) -> int:
    folder = os.path.join(results, spec["name"])
    os.makedirs(folder, exist_ok=True)
    waiting = [seed for seed in spec["seeds"] if not _finished(spec, seed, results)]
    running: list[tuple[int, subprocess.Popen]] = []
    failed = 0
    while waiting or running:
        while waiting and len(running) < workers:
            seed = waiting.pop(0)
            log = open(os.path.join(folder, f"seed-{seed}.log"), "a")  # noqa: SIM115
            print(f"pretraining seed {seed}", flush=True)
            running.append((seed, subprocess.Popen(pretrain_command(spec, seed, results),
                                                   stdout=log, stderr=subprocess.STDOUT)))
        seed, proc = running[0]
        code = proc.wait()
        running.pop(0)
        print(f"seed {seed} ended with exit code {code}", flush=True)
        failed += code != 0
    return 1 if failed else 0


def _finished(spec: dict[str, Any], seed: int, results: str) -> bool:
    finals = [p for p in _quality_files(spec, results) if _steps_of(p)[1] == seed
              and _steps_of(p)[0] == spec["steps"]]
    return bool(finals)


def _quality_files(spec: dict[str, Any], results: str) -> list[str]:
    return sorted(glob.glob(os.path.join(snapshot_dir(spec, results), "*.quality.json")))


def _steps_of(path: str) -> tuple[int, int]:
    """(pretraining steps asked for, seed) of a quality file, from its JSON."""
    with open(path) as f:
        data = json.load(f)
    name = data["snapshot"]
    at = name.rsplit("-at", 1)[1].split(".")[0] if "-at" in name else None
    return (int(at) if at else int(data["pretrain_steps"])), int(data["seed"])


def bootstrap_top(returns: list[float], resamples: int, rng: np.random.Generator,
                  ) -> tuple[float, float, float]:
    """The top-5 mean of `returns` and its 95 % percentile-bootstrap interval."""
    values = np.asarray(returns, dtype=np.float64)
    draws = rng.choice(values, size=(resamples, len(values)), replace=True)
    tops = np.sort(draws, axis=1)[:, -TOP:].mean(axis=1)
    low, high = np.percentile(tops, [2.5, 97.5])
    return float(np.sort(values)[-TOP:].mean()), float(low), float(high)


def report(spec: dict[str, Any], results: str, out: str) -> int:
    rng = np.random.default_rng(0)
    rows = []
    for path in _quality_files(spec, results):
        steps, seed = _steps_of(path)
        with open(path) as f:
            q = json.load(f)
        skill = bootstrap_top(q["skill_returns"], spec.get("bootstrap", 10_000), rng)
        rand = bootstrap_top(q["random_action_returns"], spec.get("bootstrap", 10_000), rng)
        rows.append({
            "steps": steps, "seed": seed,
            "skill_median": q["skill"]["median"], "skill_top5": skill[0],
            "skill_top5_low": skill[1], "skill_top5_high": skill[2], "skill_max": q["skill"]["max"],
            "random_median": q["random_actions"]["median"], "random_top5": rand[0],
            "random_top5_low": rand[1], "random_top5_high": rand[2],
            "random_max": q["random_actions"]["max"],
            "passes": skill[1] > rand[2] and skill[0] >= 2 * rand[0],
        })
    rows.sort(key=lambda r: (r["steps"], r["seed"]))
    os.makedirs(out, exist_ok=True)
    if rows:
        with open(os.path.join(out, "quality.csv"), "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    for path in _quality_files(spec, results):
        shutil.copy(path, out)
    lengths = [spec["steps"], *spec["snapshots_at"]]
    with open(os.path.join(out, "report.md"), "w") as f:
        f.write(_markdown(spec, rows, sorted(lengths)))
    print(open(os.path.join(out, "report.md")).read())
    return 0


def _markdown(spec: dict[str, Any], rows: list[dict], lengths: list[int]) -> str:
    seeds = spec["seeds"]
    lines = [f"# {spec['name']}: skill quality against pretraining length", "",
             f"{spec['backend'].upper()} on `{spec['task']}`, preset `{spec['preset']}`, seeds "
             f"{', '.join(map(str, seeds))}; per snapshot, "
             f"{spec.get('quality_skills', 50)} random skills (one deterministic episode each) "
             "against as many episodes of uniform random actions. Top-5 means with 95 % "
             "bootstrap intervals over the episodes.", "",
             "| steps | seed | skills: median | skills: top-5 mean [95 %] | skills: max | "
             "random: median | random: top-5 mean [95 %] | random: max | passes |",
             "|---:|---:|---:|---|---:|---:|---|---:|---|"]
    for r in rows:
        lines.append(
            f"| {r['steps']:,} | {r['seed']} | {r['skill_median']:.1f} | {r['skill_top5']:.1f} "
            f"[{r['skill_top5_low']:.1f}, {r['skill_top5_high']:.1f}] | {r['skill_max']:.1f} | "
            f"{r['random_median']:.1f} | {r['random_top5']:.1f} [{r['random_top5_low']:.1f}, "
            f"{r['random_top5_high']:.1f}] | {r['random_max']:.1f} | "
            f"{'yes' if r['passes'] else 'no'} |")
    lines += ["", "The pre-registered rule (the spec): a length carries task behaviour when, on "
              "every seed, the skills' top-5 lower bound is above the random actions' top-5 "
              "upper bound and the skills' top-5 mean is at least twice the random actions'.", ""]
    verdicts, complete = [], True
    for length in lengths:
        at = [r for r in rows if r["steps"] == length]
        if {r["seed"] for r in at} != set(seeds):
            complete = False
            verdicts.append(f"- {length:,} steps: not measured on every seed yet "
                            f"({len(at)} of {len(seeds)}).")
            continue
        ok = all(r["passes"] for r in at)
        verdicts.append(f"- {length:,} steps: {'passes' if ok else 'does not pass'}.")
    lines += verdicts
    passing = [n for n in lengths if (at := [r for r in rows if r["steps"] == n])
               and {r["seed"] for r in at} == set(seeds) and all(r["passes"] for r in at)]
    lines.append("")
    if passing:
        lines.append(f"**Answer:** the skills carry task behaviour from {min(passing):,} steps "
                     "of pretraining on.")
    elif complete:
        lines.append(f"**Answer:** no length up to {max(lengths):,} steps passes: the skills do "
                     "not carry task behaviour by this measure (a null answer).")
    else:
        lines.append("**Partial:** no measured length passes so far; the lengths not yet "
                     "measured on every seed are open.")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("action", choices=("run", "report"))
    parser.add_argument("spec")
    parser.add_argument("--results", default="results")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    spec = load_spec(args.spec)
    if args.action == "run":
        return run(spec, args.results, args.workers)
    out = args.out or os.path.join(os.path.dirname(os.path.abspath(args.spec)), "reports",
                                   spec["name"])
    return report(spec, args.results, out)


if __name__ == "__main__":
    sys.exit(main())
