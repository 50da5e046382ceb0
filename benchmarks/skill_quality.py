"""Skill quality against pretraining length: run the pretrainings of a skill-quality spec
(specs/small/skill-quality.toml) and report their snapshots' quality.

    .venv/bin/python benchmarks/skill_quality.py run SPEC --results results [--workers 2]
    .venv/bin/python benchmarks/skill_quality.py report SPEC --results results [--out DIR]

`run` starts one `sepoa pretrain` per seed (at most `--workers` at a time), with the spec's
intermediate snapshots; each measures its snapshots' skill quality as it writes them
(`trainer/skills/quality.py`). SIGTERM or Ctrl-C passes the signal on to the pretrainings, which
save their progress at the end of their episode and exit (a second one stops them at once).
Running it again goes on where a stopped pretraining left off (its `.partial` file) and skips
finished seeds. Logs: <results>/<name>/seed-<seed>.log.

`report` applies the spec's pre-registered rule to every snapshot measured so far: the top-5
mean of the skills' returns against random actions', each with a bootstrap interval over its 50
episodes, and writes report.md, quality.csv and the measured quality files to
specs/<size>/reports/<name>/ (or --out). A length is missing from the table until both seeds
reach it; the report says so.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pandas as pd

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, ROOT)

from experiments.skill_quality import (  # noqa: E402
    quality_files,
    quality_markdown,
    quality_table,
)


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

    told: list[int] = []  # the signal, once one came
    signalled: set[int] = set()

    def tell(proc: subprocess.Popen) -> None:
        """Pass the signal on, once: a second one would stop the pretraining at once, unsaved."""
        if told and proc.pid not in signalled:
            signalled.add(proc.pid)
            proc.send_signal(told[0])

    def stop(signum: int, _frame: object) -> None:
        # Each pretraining saves its progress at the end of its episode and exits; no seed
        # starts after this. Running the command again goes on from there. A second signal
        # stops them at once, as it stops `sepoa pretrain`.
        again = bool(told)
        told.append(signum)
        waiting.clear()
        for _, proc in running:
            if again:
                proc.send_signal(signum)
            else:
                tell(proc)

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, stop)
    while waiting or running:
        while waiting and len(running) < workers:
            seed = waiting.pop(0)
            log = open(os.path.join(folder, f"seed-{seed}.log"), "a")  # noqa: SIM115
            print(f"pretraining seed {seed}", flush=True)
            # Its own process group, so that a terminal's Ctrl-C reaches it once, from here.
            proc = subprocess.Popen(pretrain_command(spec, seed, results), stdout=log,
                                    stderr=subprocess.STDOUT, process_group=0)
            running.append((seed, proc))
            tell(proc)  # a signal that came as it started
        seed, proc = running[0]
        code = proc.wait()
        running.pop(0)
        print(f"seed {seed} ended with exit code {code}", flush=True)
        failed += code != 0
    return 1 if failed else 0


def _finished(spec: dict[str, Any], seed: int, results: str) -> bool:
    table = quality_table(quality_files(Path(snapshot_dir(spec, results))), resamples=1)
    return bool(((table["seed"] == seed) & (table["steps"] == spec["steps"])).any())


def report(spec: dict[str, Any], results: str, out: str) -> int:
    folder = Path(snapshot_dir(spec, results))
    table = quality_table(quality_files(folder), spec.get("bootstrap", 10_000))
    table["passes"] = ((table["skill_top5_low"] > table["random_top5_high"])
                       & (table["skill_top5"] >= 2 * table["random_top5"]))
    os.makedirs(out, exist_ok=True)
    table.to_csv(os.path.join(out, "quality.csv"), index=False)
    for path in quality_files(folder):
        shutil.copy(path, out)
    lengths = sorted([spec["steps"], *spec["snapshots_at"]])
    text = _markdown(spec, table, lengths)
    with open(os.path.join(out, "report.md"), "w") as f:
        f.write(text)
    print(text)
    return 0


def _markdown(spec: dict[str, Any], table: pd.DataFrame, lengths: list[int]) -> str:
    seeds = set(spec["seeds"])
    lines = [f"# {spec['name']}: skill quality against pretraining length", "",
             f"{spec['backend'].upper()} on `{spec['task']}`, preset `{spec['preset']}`, seeds "
             f"{', '.join(map(str, spec['seeds']))}; per snapshot, "
             f"{spec.get('quality_skills', 50)} random skills (one deterministic episode each) "
             "against as many episodes of uniform random actions. Top-5 means with 95 % "
             "bootstrap intervals over the episodes.", "", quality_markdown(table), "",
             "The pre-registered rule (the spec): a length carries task behaviour when, on "
             "every seed, the skills' top-5 lower bound is above the random actions' top-5 "
             "upper bound and the skills' top-5 mean is at least twice the random actions'.", ""]
    passing, complete = [], True
    for length in lengths:
        at = table[table["steps"] == length]
        if set(at["seed"]) != seeds:
            complete = False
            lines.append(f"- {length:,} steps: not measured on every seed yet "
                         f"({len(at)} of {len(seeds)}).")
            continue
        ok = bool(at["passes"].all())
        passing += [length] if ok else []
        lines.append(f"- {length:,} steps: {'passes' if ok else 'does not pass'}.")
    lines.append("")
    failing = [n for n in lengths if n not in passing
               and set(table[table["steps"] == n]["seed"]) == seeds]
    if passing:
        lines.append(f"**Answer (the rule's):** the shortest length whose skills carry task "
                     f"behaviour is {min(passing):,} steps."
                     + (f" Measured on every seed and not passing: "
                        f"{', '.join(f'{n:,}' for n in failing)}." if failing else "")
                     + ("" if complete else " Partial: longer lengths are not measured yet."))
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
