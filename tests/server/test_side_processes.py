"""The server's side processes (the export process and the drawing process) end with it, even
when it is killed with SIGKILL and runs no shutdown of its own."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SERVER = """
import os, sys
from server import curves
from server.export_job import ExportProcess

exports = ExportProcess()
exporter = exports.run(os.getpid)
drawer = curves._drawer.run(os.getpid)
print(exporter, drawer, flush=True)
sys.stdin.read()  # until killed
"""


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state != "Z"  # a zombie has ended (it waits for its new parent to reap it)


def test_side_processes_exit_when_the_server_is_killed_with_sigkill():
    server = subprocess.Popen([sys.executable, "-c", SERVER], cwd=ROOT, text=True,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    children: list[int] = []
    try:
        assert server.stdout is not None
        children += [int(pid) for pid in server.stdout.readline().split()]
        assert len(children) == 2 and all(_alive(pid) for pid in children), children
        os.kill(server.pid, signal.SIGKILL)
        server.wait(timeout=10)
        deadline = time.monotonic() + 10
        while any(_alive(pid) for pid in children) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not [pid for pid in children if _alive(pid)]
    finally:
        if server.poll() is None:
            server.kill()
            server.wait()
        for pid in children:  # orphans left by a failure
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
