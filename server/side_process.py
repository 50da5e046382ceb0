"""The server's side processes (label exports, `server.export_job`; figures, `server.curves`):
one spawned process each, at a lower priority, that ends with the server.

A server stopped with SIGTERM shuts its pools down. One killed with SIGKILL (the kernel's
out-of-memory killer, a supervisor's hard stop) runs no code: its side processes, each waiting
on a queue whose write end it holds itself, would wait forever as orphans (about 130 MB and
80 MB each). So each one watches the server from a thread of its own and exits once the server
is gone: through a pidfd on Linux (woken at once), else by checking its parent every second.
PR_SET_PDEATHSIG would not do: it fires when the *thread* that started the process ends, and
the server starts them from a request's worker thread, which its thread pool retires when idle.
"""

from __future__ import annotations

import multiprocessing
import os
import select
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from typing import Any, TypeVar

T = TypeVar("T")

NICENESS = 10
"""how much lower a side process's scheduling priority is than the server's"""
POLL_SECONDS = 1.0
"""how often a side process checks its parent where no pidfd can watch it"""


class SideProcess:
    """One side process of the calling (server) process, started at its first job and kept for
    the next (starting one takes about a second); jobs queue for it one at a time."""

    def __init__(self) -> None:
        self._pool: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()

    def run(self, job: Callable[..., T], /, *args: Any, **kwargs: Any) -> T:
        """`job(*args, **kwargs)` in the side process (blocking); its errors come back as they
        were raised there."""
        with self._lock:
            if self._pool is None:
                self._pool = _side_process_pool()
            pool = self._pool
        return pool.submit(job, *args, **kwargs).result()

    def close(self) -> None:
        """End the side process, if one was started (the server's shutdown)."""
        with self._lock:
            if self._pool is not None:
                self._pool.shutdown(cancel_futures=True)
                self._pool = None


def _side_process_pool() -> ProcessPoolExecutor:
    """A pool of one side process of the calling (server) process, started at its first job."""
    return ProcessPoolExecutor(
        max_workers=1,
        # Not forked: the server has threads (and a database pool) to not copy.
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_start, initargs=(os.getpid(),))


def _start(parent: int) -> None:
    os.nice(NICENESS)
    threading.Thread(target=_exit_with, args=(parent,), name="exit-with-server",
                     daemon=True).start()


def _exit_with(parent: int) -> None:
    """Return never: exit the process once `parent` has ended."""
    try:
        watch: int | None = os.pidfd_open(parent)
    except (AttributeError, OSError):  # ended already; not Linux; a kernel before 5.3
        watch = None
    # Checked after opening: a pidfd opened once the parent had ended may watch another process
    # that took its id.
    if watch is not None and os.getppid() == parent:
        select.select([watch], [], [])  # readable once the process has ended
    while os.getppid() == parent:
        time.sleep(POLL_SECONDS)
    os._exit(0)
