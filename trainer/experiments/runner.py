"""Runs a spec's grid: each run a `train` process, a few at a time, resumable.

A run's folder tells its state: `done.json` (written here from the run's summary once its
process exits 0) means finished, `checkpoint.pt` alone means partial (resumed with `--resume`),
neither means not started (a leftover folder is cleared first). S-EPOA runs start from a skill
snapshot; each distinct snapshot is pretrained once, by one process, before the runs that need
it start, so parallel runs never pretrain the same one. Snapshots live in `<results>/snapshots`
under a name that hashes every setting pretraining reads, so specs share them safely.

`run.json` in each folder records what the run is; a changed spec that would redefine a run
with results is refused unless forced. Only `steps` may grow: finished runs are then resumed.
"""

from __future__ import annotations

import dataclasses
import fcntl
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from trainer.experiments.spec import Run, Spec, SpecError
from trainer.skills.pretrain import ONLINE_SKILL_FIELDS, default_snapshot_path
from trainer.threads import cpu_cores

DONE, FAILED, RUN_INFO, LOG = "done.json", "failed.json", "run.json", "log.txt"
CHECKPOINT = "checkpoint.pt"
LOG_HEADER = "=== "
STOP_GRACE_S = 30.0
POLL_S = 0.2


@dataclass
class Job:
    name: str
    """shown in progress lines: the run's folder, or the snapshot's file name"""
    argv: list[str]
    log: Path
    run: Run | None = None
    """None for a pretraining"""
    folder: Path | None = None
    snapshot: Path | None = None
    """a pretraining's output, or the snapshot a run waits for"""
    resume: bool = False


@dataclass
class Outcome:
    """What a runner call did, by job name."""

    skipped: list[str] = field(default_factory=list)
    started: list[str] = field(default_factory=list)
    resumed: list[str] = field(default_factory=list)
    pretrained: list[str] = field(default_factory=list)
    finished: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    stopped_by: int | None = None
    """the signal that stopped the runner"""

    @property
    def exit_code(self) -> int:
        if self.stopped_by is not None:
            return 128 + self.stopped_by
        return 1 if self.failed else 0


def spec_folder(results: str | Path, spec: Spec) -> Path:
    return Path(results) / spec.name


def default_parallel(threads: int) -> int:
    return max(1, cpu_cores() // threads)


# ---------------------------------------------------------------------------------------------
# Planning: which snapshots to pretrain, which runs to start, resume or skip.

def snapshot_file(results: Path, run: Run) -> Path | None:
    """The snapshot the run starts from: its own `skill.snapshot`, else a shared one under
    `<results>/snapshots`, named as `sepoa pretrain` names it (`default_snapshot_path`)."""
    cfg = run.config()
    if cfg.algo != "sepoa" or cfg.skill.pretrain_steps == 0:
        return None
    if run.overrides.get("skill.snapshot"):
        return Path(run.overrides["skill.snapshot"])
    shared = dataclasses.replace(cfg, skill=dataclasses.replace(
        cfg.skill, snapshot_dir=str(results / "snapshots")))
    return Path(default_snapshot_path(shared, cfg.skill.snapshot_seed))


def _flag(path: str, value: Any) -> str:
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, list | tuple):
        text = ",".join(str(v) for v in value)
    else:
        text = str(value)
    return f"--{path}={text}"


def _trainer(command: str) -> list[str]:
    return [sys.executable, "-m", "trainer.cli", command]


def pretrain_argv(run: Run, out: Path, threads: int) -> list[str]:
    """`sepoa pretrain` with the run's settings that shape a snapshot."""
    seed = run.config().skill.snapshot_seed
    shaping = {p: v for p, v in run.overrides.items()
               if p in ("episode_length", "replay_capacity", "device") or p.startswith("sac.")
               or (p.startswith("skill.") and p[6:] not in ONLINE_SKILL_FIELDS)}
    return (_trainer("pretrain")
            + [f"--task={run.task}", f"--preset={run.preset}", f"--seed={seed}", f"--out={out}",
               f"--threads={threads}", "--no-progress"]
            + [_flag(p, v) for p, v in shaping.items()])


def train_argv(run: Run, folder: Path, threads: int, snapshot: Path | None) -> list[str]:
    argv = (_trainer("train")
            + [f"--task={run.task}", f"--preset={run.preset}", f"--run_dir={folder}",
               f"--threads={threads}", "--no-progress"]
            + [_flag(p, v) for p, v in run.config_overrides().items()])
    if snapshot is not None and "skill.snapshot" not in run.overrides:
        argv.append(_flag("skill.snapshot", snapshot))
    return argv


def resume_argv(run: Run, folder: Path, threads: int) -> list[str]:
    return _trainer("train") + ["--resume", f"--run_dir={folder}", f"--steps={run.steps}",
                                f"--threads={threads}", "--no-progress"]


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _write_json(path: Path, data: dict[str, Any]) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    os.replace(tmp, path)


def conflicts(spec: Spec, results: Path) -> dict[Path, str]:
    """Run folders holding results of a different definition (only more steps is fine), with
    what they hold."""
    out = {}
    for run in spec.runs():
        folder = spec_folder(results, spec) / run.dir
        stored = _read_json(folder / RUN_INFO)
        if stored is None:
            if (folder / CHECKPOINT).exists() or (folder / DONE).exists():
                out[run.dir] = f"results without {RUN_INFO} (not made by this runner)"
            continue
        new = run.identity()
        if ({k: v for k, v in stored.items() if k != "steps"}
                != {k: v for k, v in new.items() if k != "steps"}):
            out[run.dir] = f"was {json.dumps(stored)}"
        elif stored.get("steps", 0) > run.steps:
            out[run.dir] = f"has {stored['steps']} steps, the spec now {run.steps}"
    return out


def plan(spec: Spec, results: Path, threads: int) -> tuple[list[Job], list[Job], list[str]]:
    """(pretrainings, runs to start or resume, names of finished runs). Runs are ordered seed
    first, so a partial grid has every variant's first seeds."""
    root = spec_folder(results, spec)
    pretrains: dict[Path, Job] = {}
    jobs, finished = [], []
    order = sorted(spec.runs(), key=lambda r: (r.seed, r.budget or 0, r.eps,
                                               spec.tasks.index(r.task)))
    for run in order:
        folder = root / run.dir
        name = str(run.dir)
        done = _read_json(folder / DONE)
        if done is not None and done.get("step", 0) >= run.steps:
            finished.append(name)
            continue
        snapshot = snapshot_file(results, run)
        if snapshot is not None and not snapshot.exists() and snapshot not in pretrains:
            pretrains[snapshot] = Job(snapshot.name, pretrain_argv(run, snapshot, threads),
                                      snapshot.with_suffix(".log.txt"), snapshot=snapshot)
        resume = (folder / CHECKPOINT).exists()
        argv = (resume_argv(run, folder, threads) if resume
                else train_argv(run, folder, threads, snapshot))
        jobs.append(Job(name, argv, folder / LOG, run, folder, snapshot, resume))
    return list(pretrains.values()), jobs, finished


# ---------------------------------------------------------------------------------------------
# Execution.

def _summary(log: Path) -> dict[str, Any]:
    """The run's JSON summary: the last JSON object printed by the latest attempt."""
    lines = log.read_text(errors="replace").splitlines()
    starts = [i for i, line in enumerate(lines) if line.startswith(LOG_HEADER)]
    for line in reversed(lines[starts[-1] if starts else 0:]):
        if line.startswith("{"):
            try:
                data = json.loads(line)
            except ValueError:
                continue
            if isinstance(data, dict):
                return data
    return {}


def _tail(log: Path, lines: int = 15) -> str:
    try:
        text = log.read_text(errors="replace").splitlines()[-lines:]
    except OSError:
        return "    (no log)"
    return "\n".join(f"    | {line}" for line in text)


@contextmanager
def spec_lock(root: Path) -> Iterator[None]:
    """One runner per spec folder; the lock dies with its process."""
    root.mkdir(parents=True, exist_ok=True)
    with open(root / ".runner.lock", "a+") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise SpecError(f"{root}: another runner is working on this spec") from None
        f.truncate(0)
        f.write(f"{os.getpid()}\n")
        f.flush()
        yield


def runner_active(root: Path) -> bool:
    lock = root / ".runner.lock"
    if not lock.exists():
        return False
    with open(lock) as f:
        try:
            fcntl.flock(f, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
    return False


class Runner:
    """Runs jobs as processes, `parallel` at a time; a run waits for its snapshot's
    pretraining. SIGINT/SIGTERM stop it: children get SIGTERM (then SIGKILL after a grace
    period), their checkpoints stay for the next call."""

    def __init__(self, parallel: int, threads: int, echo: Callable[[str], None]):
        self.parallel, self.threads, self.echo = parallel, threads, echo
        self.start = time.time()
        self.active: dict[subprocess.Popen, tuple[Job, float, TextIO]] = {}
        self.stop_signal: int | None = None
        self.outcome = Outcome()
        self.total = 0

    def say(self, event: str, name: str, detail: str = "") -> None:
        elapsed = int(time.time() - self.start)
        clock = f"{elapsed // 3600}:{elapsed // 60 % 60:02d}:{elapsed % 60:02d}"
        o = self.outcome
        counts = (f"[{len(o.finished) + len(o.skipped)}/{self.total} done, "
                  f"{len(self.active)} running, {len(o.failed)} failed]")
        self.echo(" ".join(part for part in (clock, f"{event:<8}", name, detail, counts)
                           if part))

    def execute(self, pretrains: list[Job], jobs: list[Job]) -> Outcome:
        pending = pretrains + jobs
        snapshots = {job.snapshot: "pending" for job in pretrains}
        handlers = self._catch_signals()
        try:
            while (pending or self.active) and self.stop_signal is None:
                for job in list(pending):
                    if len(self.active) >= self.parallel:
                        break
                    state = snapshots.get(job.snapshot) if job.run is not None else None
                    if state == "pending":
                        continue  # its snapshot is being pretrained
                    pending.remove(job)
                    if state == "failed":
                        self._fail(job, f"its snapshot {job.snapshot} failed to pretrain")
                    else:
                        self._launch(job)
                time.sleep(POLL_S)
                for proc in [p for p in self.active if p.poll() is not None]:
                    job = self._finish(proc)
                    if job.run is None:
                        ok = proc.returncode == 0 and job.snapshot is not None and \
                            job.snapshot.exists()
                        snapshots[job.snapshot] = "ready" if ok else "failed"
        finally:
            self._stop_children()
            for sig, handler in handlers.items():
                signal.signal(sig, handler)
        self.outcome.stopped_by = self.stop_signal
        return self.outcome

    def _catch_signals(self) -> dict[int, Any]:
        def on_signal(signum: int, frame: Any) -> None:
            self.stop_signal = signum

        handlers = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                handlers[sig] = signal.signal(sig, on_signal)
            except ValueError:  # not the main thread: the caller handles stopping
                pass
        return handlers

    def _launch(self, job: Job) -> None:
        if job.run is not None and job.folder is not None:
            if not job.resume and job.folder.exists():
                shutil.rmtree(job.folder)  # leftovers of a run that never checkpointed
            job.folder.mkdir(parents=True, exist_ok=True)
            (job.folder / FAILED).unlink(missing_ok=True)
            (job.folder / DONE).unlink(missing_ok=True)
            _write_json(job.folder / RUN_INFO, job.run.identity())
        job.log.parent.mkdir(parents=True, exist_ok=True)
        log = open(job.log, "a")
        log.write(f"{LOG_HEADER}{time.strftime('%Y-%m-%d %H:%M:%S')} {' '.join(job.argv)}\n")
        log.flush()
        threads = str(self.threads)
        env = os.environ | {"OMP_NUM_THREADS": threads, "MKL_NUM_THREADS": threads,
                            "PYTHONUNBUFFERED": "1"}
        # Own session: a Ctrl-C reaches only the runner, which stops its children itself.
        proc = subprocess.Popen(job.argv, stdout=log, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, env=env, start_new_session=True)
        self.active[proc] = (job, time.time(), log)
        if job.run is None:
            event, listing = "pretrain", self.outcome.pretrained
        elif job.resume:
            event, listing = "resumed", self.outcome.resumed
        else:
            event, listing = "started", self.outcome.started
        listing.append(job.name)
        self.say(event, job.name, f"(pid {proc.pid})")

    def _finish(self, proc: subprocess.Popen) -> Job:
        job, started, log = self.active.pop(proc)
        log.close()
        minutes = f"after {(time.time() - started) / 60:.1f} min"
        if proc.returncode != 0:
            self._fail(job, f"exit code {proc.returncode} {minutes}", _tail(job.log))
        elif job.run is None:
            self.say("snapshot", job.name, minutes)
        else:
            assert job.folder is not None
            summary = _summary(job.log) | {"seconds": round(time.time() - started, 1)}
            _write_json(job.folder / DONE, summary)
            self.outcome.finished.append(job.name)
            self.say("finished", job.name, f"{minutes}, step {summary.get('step')}")
        return job

    def _fail(self, job: Job, why: str, tail: str = "") -> None:
        if job.folder is not None:
            job.folder.mkdir(parents=True, exist_ok=True)
            _write_json(job.folder / FAILED, {"reason": why,
                                              "at": time.strftime("%Y-%m-%d %H:%M:%S")})
        self.outcome.failed.append(job.name)
        self.say("FAILED", job.name, why)
        if tail:
            self.echo(f"    the end of {job.log}:\n{tail}")

    def _stop_children(self) -> None:
        if not self.active:
            return
        self.echo(f"stopping {len(self.active)} running process(es); their checkpoints stay")
        for proc in self.active:
            _signal_group(proc, signal.SIGTERM)
        deadline = time.time() + STOP_GRACE_S
        for proc in self.active:
            try:
                proc.wait(max(0.1, deadline - time.time()))
            except subprocess.TimeoutExpired:
                _signal_group(proc, signal.SIGKILL)
                proc.wait()
        for job, _, log in self.active.values():
            log.close()
            self.echo(f"stopped   {job.name}")
        self.active.clear()


def _print(line: str) -> None:
    print(line, flush=True)  # progress stays live when the output goes to a file


def _signal_group(proc: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(proc.pid, sig)
    except ProcessLookupError:
        pass


def run_spec(spec: Spec, results: str | Path = "results", parallel: int | None = None,
             dry_run: bool = False, only_pretrain: bool = False, force: bool = False,
             echo: Callable[[str], None] | None = None, threads: int | None = None) -> Outcome:
    """Train the spec's grid under `results/<spec name>`; see the module docstring. `threads`
    (torch threads per process) overrides the spec's; it is no part of a run's definition."""
    echo = echo or _print
    results = Path(results)
    root = spec_folder(results, spec)
    why = "--threads" if threads is not None else "the spec's threads"
    threads = threads or spec.threads
    parallel = parallel or default_parallel(threads)
    clash = conflicts(spec, results)
    if clash and not force:
        lines = [f"{folder}: {why}" for folder, why in clash.items()]
        shown = "\n  ".join(lines[:5]) + (f"\n  ... {len(lines) - 5} more" if len(lines) > 5
                                          else "")
        raise SpecError(f"{root} holds results of a different definition for "
                        f"{len(clash)} run(s):\n  {shown}\nuse another spec name, or --force "
                        "to delete those runs and train them again")
    if dry_run:
        pretrains, jobs, finished = plan(spec, results, threads)
        for job in pretrains + ([] if only_pretrain else jobs):
            action = "pretrain" if job.run is None else "resume" if job.resume else "start"
            echo(f"{action:<8} {job.name}\n         {' '.join(job.argv)}")
        echo(f"{len(pretrains)} pretraining(s), {len(jobs)} run(s) to train, "
             f"{len(finished)} finished{'; ' + str(len(clash)) + ' to redo' if clash else ''}; "
             f"{parallel} at a time, {threads} thread(s) each ({why})")
        return Outcome(skipped=finished)
    with spec_lock(root):
        for folder in clash:
            shutil.rmtree(root / folder, ignore_errors=True)
        (root / "spec.toml").write_text(spec.source)
        pretrains, jobs, finished = plan(spec, results, threads)
        runner = Runner(parallel, threads, echo)
        runner.outcome.skipped = finished
        runner.total = len(spec.runs())
        echo(f"{spec.name}: {runner.total} runs, {len(finished)} finished, "
             f"{sum(j.resume for j in jobs)} to resume, {len(pretrains)} snapshot(s) to "
             f"pretrain; {parallel} at a time, {threads} thread(s) each ({why}) -> {root}")
        outcome = runner.execute(pretrains, [] if only_pretrain else jobs)
    done = len(outcome.finished) + len(outcome.skipped)
    echo(f"{spec.name}: {done}/{runner.total} runs finished, {len(outcome.failed)} failed"
         + (f", stopped by signal {outcome.stopped_by}" if outcome.stopped_by else "")
         + f" ({(time.time() - runner.start) / 60:.1f} min)")
    return outcome


def status_table(spec: Spec, results: str | Path = "results") -> str:
    """A table of the spec's runs: done / partial (step reached) / failed / not started."""
    from trainer.experiments.results import run_state

    root = spec_folder(results, spec)
    header = ("task", "variant", "eps", "budget", "seed", "state", "step")
    rows, counts = [], dict.fromkeys(("done", "partial", "failed", "not started"), 0)
    for run in spec.runs():
        state, step = run_state(root / run.dir)
        counts[state] += 1
        rows.append((run.task, run.variant, f"{run.eps:g}",
                     "-" if run.budget is None else str(run.budget), str(run.seed), state,
                     "-" if step is None else f"{step}/{run.steps}"))
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip()
             for r in [header, *rows]]
    summary = ", ".join(f"{n} {state}" for state, n in counts.items())
    active = " (a runner is working on it)" if runner_active(root) else ""
    return "\n".join([f"{spec.name}: {len(rows)} runs: {summary}{active}", *lines])
