"""Child processes that live and die with the `sepoa` command that started them: the server and
workers of `sepoa up`, the local workers of `sepoa experiment run`.

    with Supervisor(grace_s=20) as children:
        children.start("the server", [python, "-m", "uvicorn", ...], env=env)
        outcome = children.wait(until="any")   # or "all"
    # every child has ended here

While the block runs, SIGINT and SIGTERM are noted, never raised: a Ctrl-C that comes while a
child is being started cannot leave that child running outside the list (a KeyboardInterrupt
inside `Popen`), and `start` starts nothing once one came (`stopping` says so). `wait` returns
at the first such signal. Leaving the block stops the children still running: each gets
SIGTERM once (a worker checkpoints and releases its run; a second SIGTERM would end it at once)
and `grace_s` to end, then SIGKILL; a second signal to the parent meanwhile kills them at once.
Each child runs in a process group of its own, so a terminal's Ctrl-C reaches the parent only,
and is sent SIGTERM by the kernel should the parent die without stopping it (SIGKILL, a crash):
no child outlives the parent.
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from types import FrameType, TracebackType
from typing import Any, Literal

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
PR_SET_PDEATHSIG = 1
POLL_S = 0.1


def _die_with_parent(parent: int) -> None:  # pragma: no cover - runs in the child before exec
    """Ask the kernel for SIGTERM when the parent dies (Linux; elsewhere nothing happens)."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        return
    if os.getppid() != parent:  # the parent died before the request was made
        os.kill(os.getpid(), signal.SIGTERM)


@dataclass
class Child:
    """A started child: the name messages give it, and its process."""

    name: str
    process: subprocess.Popen[bytes]

    @property
    def returncode(self) -> int | None:
        """its exit status (-N: ended by signal N); None while it runs"""
        return self.process.poll()


@dataclass(frozen=True)
class Outcome:
    """Why `wait` returned."""

    signal: int | None
    """the first SIGINT or SIGTERM the parent was sent, if one ended the wait"""
    exited: Child | None = None
    """with `until="any"`: the child that ended first, if one ended the wait"""

    @property
    def status(self) -> int:
        """The parent's exit status as a shell reports it: 128 + the signal that stopped it,
        else the ended child's status (1 when that child exited with 0 though it should not
        have), else 0."""
        if self.signal is not None:
            return 128 + self.signal
        if self.exited is not None:
            code = self.exited.returncode or 1
            return code if code > 0 else 128 - code
        return 0


@dataclass
class Supervisor:
    """Starts children, waits for them, and stops every one of them on leaving its block."""

    grace_s: float = 20.0
    """how long a child has to end after its SIGTERM before it is killed"""
    children: list[Child] = field(default_factory=list)
    signals: list[int] = field(default_factory=list)
    """the stop signals the parent was sent while the block ran, in order"""
    _previous: dict[int, Any] = field(default_factory=dict)

    def __enter__(self) -> Supervisor:
        for sig in STOP_SIGNALS:
            try:
                self._previous[sig] = signal.signal(sig, self._note)
            except ValueError:  # not the main thread: signals stay with whoever handles them
                pass
        return self

    def __exit__(self, kind: type[BaseException] | None, err: BaseException | None,
                 tb: TracebackType | None) -> None:
        try:
            self.stop()
        finally:
            for sig, handler in self._previous.items():
                signal.signal(sig, handler)
            self._previous.clear()

    def _note(self, signum: int, _frame: FrameType | None) -> None:
        # Nothing printed here: the signal may have come in the middle of a print.
        self.signals.append(signum)

    @property
    def stopping(self) -> bool:
        """whether the parent was told to stop (then `start` starts nothing)"""
        return bool(self.signals)

    def start(self, name: str, argv: Sequence[str], **popen: Any) -> Child | None:
        """Start `argv` as a child named `name` (`popen`: Popen's other arguments: env, stdout,
        ...); None, starting nothing, once the parent was told to stop."""
        if self.stopping:
            return None
        parent = os.getpid()
        process = subprocess.Popen(list(argv), process_group=0,
                                   preexec_fn=lambda: _die_with_parent(parent), **popen)
        child = Child(name, process)
        self.children.append(child)
        return child

    def running(self) -> list[Child]:
        return [c for c in self.children if c.returncode is None]

    def wait(self, until: Literal["any", "all"]) -> Outcome:
        """Until the parent is sent SIGINT or SIGTERM, or until any child (`"any"`: a server
        and its workers) or every child (`"all"`: workers that end when the work is done)
        has ended."""
        while not self.signals:
            ended = [c for c in self.children if c.returncode is not None]
            if until == "any" and ended:
                return Outcome(signal=None, exited=ended[0])
            if until == "all" and len(ended) == len(self.children):
                return Outcome(signal=None)
            time.sleep(POLL_S)
        return Outcome(signal=self.signals[0])

    def stop(self) -> None:
        """SIGTERM once to each child still running, `grace_s` for them all to end, then
        SIGKILL to those left; at once if the parent is sent another signal meanwhile."""
        asked = len(self.signals)
        for child in self.running():
            child.process.terminate()
        deadline = time.monotonic() + self.grace_s
        while self.running() and time.monotonic() < deadline:
            if len(self.signals) > asked:  # told (again) while stopping: no more grace
                break
            time.sleep(POLL_S)
        for child in self.running():
            child.process.kill()
        for child in self.children:
            child.process.wait()
