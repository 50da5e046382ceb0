"""`sepoa train`, `pretrain`, `worker`, `doctor`, `reward fit`, `tasks` and `presets`: the
commands that run the trainer (torch, MuJoCo), imported only when one of them is given.

    sepoa train --task dmc:cheetah_run --algo pebble --teacher noisy --eps 0.3 \
                --preset small --seed 0 --steps 100000
    sepoa train --run-dir runs/x --resume          # continue a killed run where it stopped
    sepoa pretrain --task dmc:cheetah_run --skills aps --preset small --seed 0
                                                   # skill pretraining -> snapshots/*.pt
    sepoa worker --database-url sqlite:///data/queue.db --data-dir data
                                                   # train runs queued in the database
    sepoa doctor                                   # can this machine render clips? EGL, OSMesa
    sepoa reward fit datasets/sepoa/dmc-cheetah_run/run-3-v0 --out reward.pt
                                                   # a reward model fitted on exported labels
    sepoa tasks                                    # list valid task names
    sepoa presets                                  # show the presets as data
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from typing import TYPE_CHECKING

from sepoa.parser import (
    Command,
    DefaultsHelpFormatter,
    database_url_file_argument,
    environment,
    fail,
    integer,
    real,
)

if TYPE_CHECKING:
    from runvocab.config import RunConfig

os.environ.setdefault("MUJOCO_GL", "egl")


DEFAULT_TASK = "dmc:cheetah_run"
DEFAULT_PRESET = "paper"
"""what `train` and `pretrain` take without --task and --preset: the paper's sizes (1 M steps,
2 x 1024 nets), GPU work; --preset small learns on a CPU"""
PRESET_DEFAULT = " (default: the preset's)"
"""what a configuration field's flag says of its default: None here, the preset's value then"""


def _task_and_preset(p: argparse.ArgumentParser) -> None:
    from runvocab.names import SIZE_PRESETS

    p.add_argument("--task", default=DEFAULT_TASK, help="dmc:<domain>_<task> or "
                   "metaworld:<name>")
    p.add_argument("--preset", default=DEFAULT_PRESET, help=" | ".join(SIZE_PRESETS) + "; paper "
                   "is 1 M steps with 2 x 1024 nets (GPU work), small learns on a CPU")


def _add_config_arguments(p: argparse.ArgumentParser, exclude: tuple[str, ...] = ()) -> None:
    """A flag per configuration field (`runvocab.config.add_config_arguments`), each saying
    that leaving it out takes the preset's value."""
    from runvocab.config import add_config_arguments

    before = len(p._actions)
    add_config_arguments(p, exclude=exclude)
    for action in p._actions[before:]:
        action.help = (action.help or "") + PRESET_DEFAULT


def _train_arguments(p: argparse.ArgumentParser) -> None:
    from runvocab.names import TEACHER_KINDS

    _task_and_preset(p)
    p.add_argument("--teacher", dest="teacher.kind", default=None,
                   help=" | ".join(TEACHER_KINDS) + PRESET_DEFAULT)
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --run-dir from its last checkpoint")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_config_arguments(p)


def _pretrain_arguments(p: argparse.ArgumentParser) -> None:
    from runvocab.config.args import value_type

    _task_and_preset(p)
    p.add_argument("--steps", dest="skill.pretrain_steps", default=None,
                   type=value_type("skill.pretrain_steps"),
                   help="pretraining environment steps" + PRESET_DEFAULT)
    p.add_argument("--out", default=None, help="snapshot file; default "
                   "<skill.snapshot_dir>/<task>-<backend>-<steps>-s<seed>-<hash>.pt, the "
                   "hash covering every setting pretraining reads")
    p.add_argument("--quality-skills", type=_quality_skills, default=50, metavar="N",
                   help="beside each snapshot, the task return of N random skills (one "
                   "deterministic episode each) against N episodes of random actions; 0: none, "
                   f"else at least {QUALITY_TOP}, for its top-{QUALITY_TOP} mean")
    p.add_argument("--snapshots-at", type=_steps_list, default=None, metavar="STEPS",
                   help="also write a snapshot (and its quality) at these steps, "
                   "comma-separated, e.g. 100000,200000,500000")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    # --steps is the pretraining length here, not the online run's.
    _add_config_arguments(p, exclude=("steps",))


QUALITY_TOP = 5
"""the fewest skills a quality measurement takes, for its top-5 mean
(`trainer.skills.quality.TOP`, not imported here: it would load torch for --help)"""


def _quality_skills(text: str) -> int:
    count = integer("a count of skills", low=0)(text)
    if 0 < count < QUALITY_TOP:
        raise argparse.ArgumentTypeError(
            f"{text!r} is too few skills: give 0 (no quality measurement) or at least "
            f"{QUALITY_TOP}")
    return count


def _steps_list(text: str) -> tuple[int, ...]:
    try:
        steps = tuple(int(float(part)) for part in text.split(",") if part.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"takes whole step counts, comma-separated (100000,200000), got {text!r}") from None
    if not steps or min(steps) < 1:
        raise argparse.ArgumentTypeError(f"takes positive step counts, got {text!r}")
    return steps


def _run_pretrain(args: argparse.Namespace) -> int:
    import signal
    import time

    from runvocab.config import build_config, overrides_from_args
    from runvocab.snapshot_names import default_snapshot_path
    from trainer.departure import LEAVE_SIGNALS, Departure
    from trainer.envs import UnknownTaskError
    from trainer.skills.pretrain import PretrainingLeft, pretrain

    # Told to go (SIGTERM, Slurm's SIGUSR1, a first Ctrl-C), the pretraining leaves at the end
    # of its episode with its progress saved, for the same command to go on from; a second
    # signal stops it at once.
    departure = Departure()

    def leave(signum: int, frame: object) -> None:
        departure.on_signal(signum, frame)  # a second SIGTERM or SIGUSR1 ends it at once,
        signal.signal(signal.SIGINT, signal.default_int_handler)  # and a second Ctrl-C

    for sig in (*LEAVE_SIGNALS, signal.SIGINT):
        signal.signal(sig, leave)

    def tick(step: int) -> bool:
        if departure.due and not departure.announced:
            departure.announced = True
            print(f"sepoa pretrain: {departure.name} at step {step}: leaving at the end of this "
                  "episode with the progress saved (again to stop at once)", file=sys.stderr,
                  flush=True)
        return departure.due

    start = time.time()
    try:
        cfg = build_config(args.task, args.preset, overrides_from_args(args))
        # By default the name online runs of these settings look for: it hashes the settings
        # as given, where pretraining's own default hashes them with its skill fields resolved.
        path = pretrain(cfg, out=args.out or default_snapshot_path(cfg),
                        progress=not args.no_progress, tick=tick,
                        quality_skills=args.quality_skills,
                        snapshots_at=args.snapshots_at or ())
    except PretrainingLeft as err:
        print(f"sepoa pretrain: {err}; the same command goes on from there", file=sys.stderr,
              flush=True)
        return 128 + (departure.signum or 0)
    except (ValueError, UnknownTaskError, FileExistsError) as err:
        return fail(str(err))
    seconds = time.time() - start
    steps = cfg.skill.pretrain_steps
    from trainer.skills import quality

    measured = quality.read(path)
    print(json.dumps({"snapshot": path, "steps": steps, "seconds": round(seconds, 1),
                      "steps_per_second": round(steps / max(seconds, 1e-9), 1)}
                     | ({"skill_quality": {k: measured[k] for k in ("skill", "random_actions")}}
                        if measured else {})))
    return 0


def _worker_arguments(p: argparse.ArgumentParser) -> None:
    env = os.environ.get
    p.add_argument("--database-url", default=None,
                   help="the queue database (env SEPOA_DATABASE_URL; default "
                   "sqlite:///<data-dir>/queue.db); a URL here shows in `ps`: keep a password in "
                   "the environment, a --database-url-file or a libpq password file")
    database_url_file_argument(p)
    p.add_argument("--data-dir", default=env("SEPOA_DATA_DIR", "data"),
                   help="runs and clips go under it (env SEPOA_DATA_DIR)")
    p.add_argument("--clips-dir", default=env("SEPOA_CLIPS_DIR"),
                   help="where clips go; <data-dir>/clips when unset (env SEPOA_CLIPS_DIR)")
    p.add_argument("--results", default=env("SEPOA_RESULTS_DIR"),
                   help="experiments' runs go to <results>/<spec name>/<run>; "
                   "<data-dir>/results when unset (env SEPOA_RESULTS_DIR)")
    p.add_argument("--worker-id", default=env("SEPOA_WORKER_ID"),
                   help="name in the database (env SEPOA_WORKER_ID; host-pid if unset); a "
                   "worker restarted under the same id takes its runs back at once")
    p.add_argument("--once", action="store_true", help="exit when no run is waiting")
    p.add_argument("--poll-seconds", type=_poll_seconds, default=2.0,
                   help="how long to wait before looking for a run again")
    p.add_argument("--device", default=None,
                   help="overrides each run's device: auto | cpu | cuda | cuda:N")
    p.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads per run; default: the cores divided by "
                   "--host-processes")
    p.add_argument("--host-processes", type=HOST_PROCESSES, default=None,
                   help="processes sharing this host's cores: the training workers, plus one "
                   "for the server if it runs here (env SEPOA_HOST_PROCESSES; default 2)")
    p.add_argument("--clip-size", type=int, default=256,
                   help="clip width and height in pixels, for runs that choose no clip_size")
    p.add_argument("--clip-fps", type=float, default=100 / 3,
                   help="clip frame rate, one frame per step (100/3: 50 steps in 1.5 s)")
    p.add_argument("--clip-shadow-size", type=int, default=512,
                   help="shadow map texels (0: no shadows); larger is slower on a CPU")
    p.add_argument("--clip-multisamples", type=int, default=0,
                   help="off-screen multisampling; 0 is fastest on a CPU")


HOST_PROCESSES = integer("a count of processes", 1)


def _poll_seconds(text: str) -> float:
    seconds: float = real("a number of seconds")(text)
    if seconds <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds above 0")
    return seconds


def _run_worker(args: argparse.Namespace) -> int:
    from pathlib import Path

    from sqlalchemy.exc import DBAPIError

    from labelqueue import check_url, database_url, mask_url, sqlite_url
    from labelqueue.errors import database_reason
    from labelqueue.schema import check_queue_file
    from trainer.clips import ClipConfig  # no MuJoCo yet: the rendering check comes first

    if args.host_processes is None:
        try:
            args.host_processes = environment("SEPOA_HOST_PROCESSES", "2", HOST_PROCESSES)
        except ValueError as err:
            return fail(str(err))
    try:
        clip = ClipConfig(width=args.clip_size, height=args.clip_size, fps=args.clip_fps,
                          shadow_size=args.clip_shadow_size, multisamples=args.clip_multisamples)
    except ValueError as err:
        return fail(str(err))
    from trainer.threads import cpu_cores

    if (args.threads is not None and args.threads < 1) or args.host_processes < 1:
        return fail("--threads and --host-processes must be at least 1")
    if args.device is not None:
        from trainer.utils import pick_device

        try:  # here, not as each run starts: a run it cannot train would be marked failed
            pick_device(args.device)
        except ValueError as err:
            return fail(str(err))
    threads = args.threads or max(1, cpu_cores() // args.host_processes)
    # WorkerConfig's default name, chosen here so that every line the worker prints has it
    import socket

    worker_id = args.worker_id or f"{socket.gethostname()}-{os.getpid()}"
    prefix = f"[worker {worker_id}]"
    try:
        url = check_url(database_url(args.database_url, args.database_url_file)
                        or sqlite_url(args.data_dir))
        check_queue_file(url)  # its migration would refuse it, after retries, in a traceback
    except ValueError as err:
        return fail(str(err))
    from trainer.doctor import RenderingUnavailable, choose_backend

    try:  # a probe process per backend: a broken EGL cannot take this process down
        choose_backend(lambda line: print(f"{prefix} {line}", file=sys.stderr, flush=True))
    except RenderingUnavailable as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    from trainer.worker import WorkerConfig, run_worker  # imports MuJoCo

    why = ("--threads" if args.threads is not None else
           f"{cpu_cores()} cores shared by {args.host_processes} processes; --threads or "
           "--host-processes to change")
    print(f"{prefix} torch threads: {threads} ({why})", file=sys.stderr, flush=True)
    worker = WorkerConfig(
        database_url=url, data_dir=Path(args.data_dir),
        clips_dir=Path(args.clips_dir) if args.clips_dir else None, once=args.once,
        results_dir=Path(args.results) if args.results else None,
        poll_seconds=args.poll_seconds, device=args.device, threads=threads, clip=clip,
        worker_id=worker_id,
    )
    try:
        run_worker(worker)
    except KeyboardInterrupt:
        return 130
    except DBAPIError as err:  # the database cannot be reached (or went away)
        return fail(f"queue database {mask_url(url)}: {database_reason(err)}")
    return 0


def _doctor_arguments(p: argparse.ArgumentParser) -> None:
    from trainer.doctor import BACKENDS, TASKS

    p.add_argument("--backend", action="append", choices=BACKENDS, default=None,
                   help=f"a backend to check (repeatable); default {' and '.join(BACKENDS)}")
    p.add_argument("--task", action="append", default=None,
                   help=f"a task to render (repeatable); default {' and '.join(TASKS)}")
    p.add_argument("--size", type=int, default=128, help="frame width and height in pixels")
    p.add_argument("--frames", type=int, default=20, help="frames timed after the first")
    from sepoa.queue_commands import database_args

    database_args(p)  # the queue database, checked first


def _check_queue_database(url: str) -> int:
    """The doctor's first line: whether SQLite's integrity check finds the queue database
    damaged (then it says so, in one line, and the doctor stops: exit 2)."""
    from labelqueue.db_url import mask_url
    from labelqueue.schema import check_database, sqlite_file

    path = sqlite_file(url)
    if path is None:
        print(f"queue database {mask_url(url)}: not checked (the integrity check is SQLite's)")
        return 0
    if not os.path.isfile(path):
        print(f"queue database {path}: none yet (`sepoa up` or `sepoa serve` makes it)")
        return 0
    try:
        check_database(url)
    except ValueError as err:
        return fail(str(err))
    print(f"queue database {path}: ok (PRAGMA quick_check)")
    return 0


def _run_doctor(args: argparse.Namespace) -> int:
    from sepoa.queue_commands import database_url
    from trainer.doctor import BACKENDS, TASKS, run_doctor

    if not 16 <= args.size <= 2048 or args.frames < 0:
        return fail("--size takes 16 to 2048 pixels and --frames at least 0")
    try:
        url = database_url(args)
    except ValueError as err:
        return fail(str(err))
    if _check_queue_database(url):
        return 2
    return run_doctor(args.backend or BACKENDS, args.task or TASKS, size=args.size,
                      frames=args.frames)


def _reward_arguments(p: argparse.ArgumentParser) -> None:
    actions = p.add_subparsers(dest="action", required=True)
    fit = actions.add_parser(
        "fit", help="train the run's reward ensemble on an exported dataset's labels; report "
        "held-out accuracy and the correlation of r_hat with the true reward; save the model "
        "for reward.init_from", formatter_class=DefaultsHelpFormatter)
    fit.add_argument("dataset", help="a dataset folder (sepoa export --dataset) or its Minari id "
                     "under MINARI_DATASETS_PATH")
    fit.add_argument("--out", default=None,
                     help="where to save the model (default: reward-<dataset name>.pt); an "
                     "existing file is refused")
    fit.add_argument("--holdout", type=real("a share", 0, 0.9), metavar="SHARE", default=0.2,
                     help="share of the labelled pairs held out, in [0, 0.9]")
    fit.add_argument("--seed", type=integer("a seed", 0), default=0)
    fit.add_argument("--epochs", type=integer("a number of epochs", 1), default=None,
                     help="most passes over the pairs per training (default: the run's "
                     "reward.max_epochs)")
    fit.add_argument("--schedule", choices=("rounds", "once"), default="rounds",
                     help="rounds: train as the run did, after each round's pairs join, on "
                     "every pair so far; once: one training on all of them")
    fit.add_argument("--threads", type=integer("a thread count", 1), default=1,
                     help="torch CPU threads")
    fit.add_argument("--device", default="cpu", help="cpu | cuda")
    fit.add_argument("--compare", default=None, metavar="CHECKPOINT",
                     help="also score the exported run's own reward model (the checkpoint.pt "
                     "in its run folder) on the same pairs")


def _run_reward_fit(args: argparse.Namespace) -> int:
    from rundata.dataset import DatasetError, read_dataset

    if args.device not in ("cpu", "cuda"):
        return fail(f"--device {args.device!r}: give cpu or cuda")
    try:
        dataset = read_dataset(args.dataset)
    except DatasetError as err:
        return fail(str(err))
    out = args.out or f"reward-{dataset.path.name}.pt"
    if os.path.exists(out):
        return fail(f"--out {out} exists; remove it or give another file")
    if not os.path.isdir(os.path.dirname(os.path.abspath(out))):
        return fail(f"--out {out}: its folder does not exist")
    import torch

    from trainer.reward_fit import compare, fit, run_reward_model, save_reward_model

    if args.device == "cuda" and not torch.cuda.is_available():
        return fail("--device cuda: no CUDA device here")
    torch.set_num_threads(args.threads)
    try:
        run_model = None if args.compare is None else run_reward_model(args.compare, dataset)
        result = fit(dataset, holdout=args.holdout, seed=args.seed, epochs=args.epochs,
                     device=args.device, schedule=args.schedule)
        if run_model is not None:
            result.metrics.update(compare(run_model, result, dataset, args.seed))
        save_reward_model(out, result, dataset)
    except (DatasetError, ValueError) as err:
        return fail(str(err))
    except OSError as err:
        return fail(f"cannot write --out {out}: {err.strerror or err}")
    m = result.metrics
    print(f"{dataset.info.get('dataset_id')}: {int(m['train_pairs'])} pairs trained on, "
          f"{int(m['heldout_pairs'])} held out; held-out accuracy {m['heldout_accuracy']:.3f} "
          f"({int(m['heldout_decisive'])} decisive), training accuracy "
          f"{m['train_accuracy']:.3f}, on true-order pairs {m['true_order_accuracy']:.3f}, "
          f"r_hat vs true reward r = {m['reward_corr']:.3f}; {int(m['epochs'])} epochs over "
          f"{int(m['trainings'])} trainings in {m['seconds']:.1f} s; saved {out} (start a "
          f"run from it with reward.init_from={out})", file=sys.stderr)
    if run_model is not None:
        print(f"the run's own reward model: held-out accuracy "
              f"{m['run_heldout_accuracy']:.3f} (it trained on these pairs), on true-order "
              f"pairs {m['run_true_order_accuracy']:.3f}, r_hat vs true reward r = "
              f"{m['run_reward_corr']:.3f}", file=sys.stderr)
    # A figure with nothing to measure (no decisive pair) is nan: null in JSON, which has no NaN.
    plain = {k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in m.items()}
    print(json.dumps({"model": out} | plain, allow_nan=False))
    return 0


def _config_from_args(args: argparse.Namespace) -> RunConfig:
    from runvocab.config import apply_overrides, build_config, load_json, overrides_from_args

    overrides = overrides_from_args(args)
    if args.resume:
        run_dir = overrides.get("run_dir")
        if not run_dir:
            raise ValueError("--resume needs --run-dir")
        config_path = os.path.join(run_dir, "config.json")
        if not os.path.exists(config_path):
            raise ValueError(f"--resume: {run_dir} holds no run (config.json missing)")
        cfg = load_json(config_path)
        # A resumed run keeps its configuration; only the length may be extended.
        allowed = {"run_dir", "steps", "device", "threads"}
        ignored = set(overrides) - allowed
        if ignored:
            raise ValueError(f"--resume keeps the run's configuration; "
                             f"cannot change {', '.join(sorted(ignored))}")
        return apply_overrides(cfg, overrides)
    return build_config(args.task, args.preset, overrides)


def _run_train(args: argparse.Namespace) -> int:
    from trainer.envs import UnknownTaskError
    from trainer.loop import TrainingRun

    try:
        cfg = _config_from_args(args)
        run = TrainingRun(cfg, resume=args.resume, progress=not args.no_progress)
    except (ValueError, UnknownTaskError, FileExistsError, FileNotFoundError) as err:
        return fail(str(err))
    print(f"run directory: {run.run_dir}", file=sys.stderr)
    from trainer.threads import cpu_cores

    print("torch threads: " + (f"{cfg.threads} (--threads)" if cfg.threads > 0 else
          f"torch's default, one per core ({cpu_cores()}); --threads 1 when processes share "
          "the cores"), file=sys.stderr, flush=True)
    summary = run.train()
    print(json.dumps(summary))
    return 0



def _run_tasks(_args: argparse.Namespace) -> int:
    from runvocab.names import all_tasks

    print("\n".join(all_tasks()))
    return 0


def _run_presets(_args: argparse.Namespace) -> int:
    from runvocab.config import preset_layers

    print(json.dumps(preset_layers(), indent=2))
    return 0


def _nothing(_p: argparse.ArgumentParser) -> None:
    pass


COMMANDS = {
    "train": Command(_train_arguments, _run_train, defaults_in_help=True),
    "pretrain": Command(_pretrain_arguments, _run_pretrain, defaults_in_help=True),
    "worker": Command(_worker_arguments, _run_worker, defaults_in_help=True),
    "doctor": Command(_doctor_arguments, _run_doctor, defaults_in_help=True),
    "reward": Command(_reward_arguments, _run_reward_fit),
    "tasks": Command(_nothing, _run_tasks),
    "presets": Command(_nothing, _run_presets),
}
