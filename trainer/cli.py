"""The `sepoa` command line.

    sepoa train --task dmc:cheetah_run --algo pebble --teacher noisy --eps 0.3 \
                --preset small --seed 0 --steps 100000
    sepoa train --run-dir runs/x --resume          # continue a killed run where it stopped
    sepoa tasks                                    # list valid task names
    sepoa presets                                  # show the presets as data
"""

from __future__ import annotations

import argparse
import json
import os
import sys

os.environ.setdefault("MUJOCO_GL", "egl")


def _train_parser(sub) -> argparse.ArgumentParser:
    from trainer.config import add_config_arguments

    p = sub.add_parser("train", help="train one run (SAC oracle or PEBBLE)",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--task", default=None, help="dmc:<domain>_<task> or metaworld:<name>")
    p.add_argument("--preset", default=None, help="paper | small | tiny")
    p.add_argument("--teacher", dest="teacher.kind", default=None, help="noisy | bpref")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --run-dir from its last checkpoint")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_config_arguments(p)
    return p


def _config_from_args(args: argparse.Namespace):
    from trainer.config import apply_overrides, build_config, load_json, overrides_from_args

    overrides = overrides_from_args(args)
    if args.resume:
        run_dir = overrides.get("run_dir")
        if not run_dir:
            raise SystemExit("error: --resume needs --run-dir")
        config_path = os.path.join(run_dir, "config.json")
        if not os.path.exists(config_path):
            raise SystemExit(f"error: --resume: {run_dir} holds no run (config.json missing)")
        cfg = load_json(config_path)
        # A resumed run keeps its configuration; only the length may be extended.
        allowed = {"run_dir", "steps", "device", "threads"}
        ignored = set(overrides) - allowed
        if ignored:
            raise SystemExit(f"error: --resume keeps the run's configuration; "
                             f"cannot change {', '.join(sorted(ignored))}")
        return apply_overrides(cfg, overrides)
    task = args.task or "dmc:cheetah_run"
    preset = args.preset or "paper"
    return build_config(task, preset, overrides)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="sepoa", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    _train_parser(sub)
    sub.add_parser("tasks", help="list valid task names")
    sub.add_parser("presets", help="print the presets")
    args = parser.parse_args(argv)

    if args.command == "tasks":
        from trainer.envs import available_tasks

        print("\n".join(available_tasks()))
        return 0
    if args.command == "presets":
        from trainer.config import FAMILY_PRESETS, PRESETS, TASK_PRESETS

        print(json.dumps({"family": FAMILY_PRESETS, "task": TASK_PRESETS, "preset": PRESETS},
                         indent=2))
        return 0

    from trainer.envs import UnknownTaskError
    from trainer.loop import TrainingRun

    try:
        cfg = _config_from_args(args)
        run = TrainingRun(cfg, resume=args.resume, progress=not args.no_progress)
    except (ValueError, UnknownTaskError, FileExistsError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"run directory: {run.run_dir}", file=sys.stderr)
    summary = run.train()
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
