"""The `sepoa` command line (`python -m sepoa` is the same command).

    sepoa up                          # server + worker on SQLite under ./data, and a demo run
    sepoa serve --port 8000           # the web server only (settings from SEPOA_* variables)
    sepoa worker                      # a trainer worker only
    sepoa train --task dmc:cheetah_run --algo pebble --preset small   # one run, no server
    sepoa pretrain --task dmc:cheetah_run --skills aps --preset small # skill snapshot
    sepoa experiment run specs/small/dmc-curves.toml --workers 2     # a grid of runs
    sepoa report results/dmc-curves-small                            # its figures and tables
    sepoa export --format parquet --run 3 --out labels.parquet
    sepoa export --dataset datasets --run 3   # the run's episodes and labels as a Minari dataset
    sepoa reward fit datasets/sepoa/dmc-cheetah_run/run-3-v0 --out reward.pt  # offline r_hat
    sepoa label-dataset datasets/sepoa/dmc-cheetah_run/run-3-v0 --budget 200  # label it
    sepoa labeller create alice [--role operator]
    sepoa labeller revoke alice | activate alice | token alice | list
    sepoa invite verify PILOT-7KQ3-M9XD-2WPA   # whose completion code is it, how far did they get
    sepoa invite participants 4 --csv          # everyone who joined invite 4, to pay from
    sepoa doctor                      # can this machine render clips? (EGL, OSMesa, fps, upright)
    sepoa tasks | presets
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys

from sepoa.parser import Command, DefaultsHelpFormatter, OneLineParser

COMMANDS: dict[str, tuple[str, str]] = {
    "up": ("sepoa.up", "start the server and a worker on SQLite, with a demo run"),
    "serve": ("sepoa.up", "run the web server (API, label page, dashboard)"),
    "worker": ("sepoa.trainer_commands", "train the runs queued in the queue database"),
    "train": ("sepoa.trainer_commands", "train one run of any algorithm (sac, pebble, surf, "
              "rune, rime, sepoa) standalone, answered by a scripted teacher"),
    "pretrain": ("sepoa.trainer_commands", "pretrain skills (APS, DIAYN, CIC) for a task; "
                 "writes a reusable snapshot"),
    "experiment": ("sepoa.experiment_commands", "a spec's grid of runs in the queue, trained "
                   "by workers (docs/EXPERIMENTS.md)"),
    "report": ("sepoa.experiment_commands", "figures and tables of an experiment's results, or "
               "the teacher-calibration report of a label export"),
    "export": ("sepoa.queue_commands", "write the labels as JSONL, CSV or Parquet, or a run as "
               "a Minari dataset"),
    "reward": ("sepoa.trainer_commands", "fit the reward ensemble on a dataset export's labels "
               "(sepoa reward fit DATASET)"),
    "label-dataset": ("sepoa.queue_commands", "queue a labelling-only run over a dataset "
                      "export: pairs of its episodes for people to label, no training "
                      "(docs/EXPORT.md)"),
    "labeller": ("sepoa.queue_commands", "create, list, revoke or restore labellers, or give "
                 "one a new token"),
    "invite": ("sepoa.queue_commands", "check a participant's completion code, or list an "
               "invite's participants (answers, gold score, code) to pay from"),
    "doctor": ("sepoa.trainer_commands", "check off-screen rendering: EGL and OSMesa, GL "
               "strings, fps, upright frames"),
    "tasks": ("sepoa.trainer_commands", "list valid task names"),
    "presets": ("sepoa.trainer_commands", "print the presets"),
}
"""each command's module (which holds its arguments and what runs it) and its line of help"""


def command(name: str) -> Command:
    """The command `name`, from its module (imported only now: the trainer's imports torch)."""
    found: Command = importlib.import_module(COMMANDS[name][0]).COMMANDS[name]
    return found


def build_parser(given: str | None = None) -> OneLineParser:
    """The whole `sepoa` parser; of the commands, only `given` gets its arguments (the others
    are listed in `sepoa --help`, and are never parsed when `given` is)."""
    parser = OneLineParser(prog="sepoa", description=__doc__,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (_module, text) in COMMANDS.items():
        if name != given:
            sub.add_parser(name, help=text)
            continue
        found = command(name)
        p = sub.add_parser(name, help=text, description=text, formatter_class=(
            DefaultsHelpFormatter if found.defaults_in_help
            else argparse.HelpFormatter))
        found.arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    given = next((a for a in argv[:1] if a in COMMANDS), None)
    try:
        args = build_parser(given).parse_args(argv)  # exit 2 on a mistake, 0 after --help
        return command(args.command).run(args)
    except KeyboardInterrupt:  # Ctrl-C while starting up or running: no traceback
        # A second Ctrl-C (or the same one seen again) while the interpreter shuts down would
        # end it by the signal instead of this exit status.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
