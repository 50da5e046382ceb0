"""How many torch CPU threads a training process uses by default.

Torch's own default is one thread per core in every process. When several processes share the
cores (a server and its workers, or workers side by side) they then fight over them: on a
2-core machine a tiny run took 75.5 s with the default against 12.6 s with one thread. So a
process gets `cores // processes` threads, at least one, where `processes` counts every
training worker on the host and the web server as one more when it runs there.
"""

from __future__ import annotations

import os


def cpu_cores() -> int:
    """The cores this process may run on (its affinity mask, where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def default_threads(*, workers: int, server: bool, cores: int | None = None) -> int:
    """Threads per training process when `workers` of them (and a server, if `server`) share
    `cores` cores (default: this machine's)."""
    cores = cpu_cores() if cores is None else cores
    processes = max(1, workers) + (1 if server else 0)
    return max(1, cores // processes)


def describe(threads: int, *, workers: int, server: bool, chosen: bool) -> str:
    """One line for the start-up log: the choice and why."""
    if chosen:
        return f"torch threads per worker: {threads} (--threads)"
    sharing = f"{workers} worker{'s' if workers != 1 else ''}" + (" + the server" if server else "")
    return (f"torch threads per worker: {threads} ({cpu_cores()} cores shared by {sharing}; "
            "--threads to change)")
