"""A throwaway one-node Slurm cluster for tests: munged, slurmctld and slurmd from Debian's
`munge` and `slurm-wlm` (scripts/setup.sh --for-tests installs them), each with its files in
one temporary folder and its own ports on 127.0.0.1, so nothing of the machine's own Slurm
(if any) is used.

    with slurm_cluster(tmp_path / "slurm") as cluster:
        job = cluster.sbatch(script_path)
        cluster.wait(lambda: not cluster.jobs(job), timeout=60, what="the job")

`start` raises `SlurmUnavailable` with the reason (and the daemons' logs) when the cluster
cannot be started; tests turn it into a skip. Stopping cancels every job and ends the
processes this cluster started: the daemons, and any job step left behind (found by the
cluster's own SLURM_CONF in their environment).
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

NODE = "sepoa-node"
DAEMONS = ("munged", "slurmctld", "slurmd")
CLIENTS = ("sbatch", "squeue", "scancel", "sinfo", "scontrol")


class SlurmUnavailable(Exception):
    """Slurm cannot be started here; the message says why."""


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _which(name: str) -> str | None:
    return shutil.which(name) or next(
        (str(p) for p in (Path("/usr/sbin") / name, Path("/sbin") / name) if p.exists()), None)


class Cluster:
    def __init__(self, folder: Path):
        self.folder = folder
        self.conf = folder / "slurm.conf"
        self.env = os.environ | {"SLURM_CONF": str(self.conf)}
        self.processes: list[subprocess.Popen[bytes]] = []

    # -- set-up -------------------------------------------------------------------------------
    def start(self, timeout: float = 30.0) -> None:
        missing = [name for name in DAEMONS + CLIENTS if _which(name) is None]
        if missing:
            raise SlurmUnavailable(f"{', '.join(missing)} not installed (apt-get install "
                                   "slurm-wlm munge; scripts/setup.sh --for-tests does)")
        if os.geteuid() != 0:
            raise SlurmUnavailable("slurmd must run as root to start jobs")
        folder = self.folder
        for sub in ("munge", "state", "spool", "log"):
            (folder / sub).mkdir(parents=True, exist_ok=True)
        (folder / "munge").chmod(0o700)
        key = folder / "munge" / "munge.key"
        key.write_bytes(os.urandom(1024))
        key.chmod(0o600)
        socket_path = folder / "munge" / "munge.socket"
        self._spawn([_which("munged"), "--foreground", "--force", f"--key-file={key}",
                     f"--socket={socket_path}", f"--pid-file={folder / 'munge' / 'pid'}",
                     f"--log-file={folder / 'log' / 'munged.log'}",
                     f"--seed-file={folder / 'munge' / 'seed'}"])
        self._until(socket_path.exists, timeout, "munged to open its socket")
        cpus = max(2, os.cpu_count() or 1)  # two tasks side by side even on one core
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2**20
        host = socket.gethostname().split(".")[0]
        self.conf.write_text(f"""\
ClusterName=sepoatest
SlurmctldHost={host}(127.0.0.1)
SlurmctldPort={_free_port()}
SlurmdPort={_free_port()}
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={socket_path}
SlurmUser=root
SlurmdUser=root
StateSaveLocation={folder / 'state'}
SlurmdSpoolDir={folder / 'spool'}
SlurmctldPidFile={folder / 'slurmctld.pid'}
SlurmdPidFile={folder / 'slurmd.pid'}
SlurmctldLogFile={folder / 'log' / 'slurmctld.log'}
SlurmdLogFile={folder / 'log' / 'slurmd.log'}
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
MpiDefault=none
SchedulerType=sched/builtin
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
SlurmdParameters=config_overrides
ReturnToService=2
KillWait=30
MinJobAge=600
InactiveLimit=0
NodeName={NODE} NodeHostname={host} NodeAddr=127.0.0.1 CPUs={cpus} RealMemory={memory} State=UNKNOWN
PartitionName=test Nodes={NODE} Default=YES MaxTime=INFINITE State=UP
""")
        self._spawn([_which("slurmctld"), "-D", "-f", str(self.conf)])
        self._spawn([_which("slurmd"), "-D", "-f", str(self.conf), "-N", NODE])
        self._until(lambda: self.run("sinfo", "-h", "-o", "%T", check=False).strip()
                    .rstrip("*") == "idle", timeout, "the node to be idle")

    def _spawn(self, argv: list[str | None]) -> None:
        log = (self.folder / "log" / "daemons.out").open("ab")
        self.processes.append(subprocess.Popen([str(a) for a in argv], env=self.env, stdout=log,
                                               stderr=subprocess.STDOUT,
                                               stdin=subprocess.DEVNULL))

    def _until(self, ready: Callable[[], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if ready():
                return
            dead = [p for p in self.processes if p.poll() is not None]
            if dead:
                raise SlurmUnavailable(f"{Path(str(dead[0].args[0])).name} exited with "
                                       f"{dead[0].returncode} while waiting for {what}"
                                       f"{self.logs()}")
            time.sleep(0.2)
        raise SlurmUnavailable(f"timed out after {timeout:.0f} s waiting for {what}{self.logs()}")

    def logs(self, lines: int = 15) -> str:
        out = []
        for path in sorted((self.folder / "log").glob("*")):
            tail = path.read_text(errors="replace").splitlines()[-lines:]
            out.append(f"\n--- {path.name}\n" + "\n".join(tail))
        return "".join(out)

    # -- use ----------------------------------------------------------------------------------
    def run(self, *argv: str, check: bool = True) -> str:
        done = subprocess.run(list(argv), env=self.env, capture_output=True, text=True,
                              timeout=30)
        if check and done.returncode != 0:
            raise RuntimeError(f"{' '.join(argv)}: {done.stderr.strip()}{self.logs()}")
        return done.stdout

    def sbatch(self, script: Path, *options: str, env: dict[str, str] | None = None) -> str:
        """Submit `script` (as `sbatch` would from a shell with `env`); the job id."""
        done = subprocess.run(["sbatch", "--parsable", *options, str(script)],
                              env=(env or os.environ) | {"SLURM_CONF": str(self.conf)},
                              capture_output=True, text=True, timeout=30)
        if done.returncode != 0:
            raise RuntimeError(f"sbatch: {done.stderr.strip()}{self.logs()}")
        return done.stdout.strip().split(";")[0]

    def jobs(self, job: str) -> dict[str, str]:
        """The array's tasks still pending or running: {task id: state}."""
        out = self.run("squeue", "-h", "-r", "-j", job, "-o", "%i %T", check=False)
        return dict(line.split() for line in out.splitlines() if line.strip())

    def stop(self) -> None:
        if self.conf.exists():
            self.run("scancel", "--full", "--user", "root", check=False)
        for process in reversed(self.processes):
            if process.poll() is None:
                process.terminate()
        for process in self.processes:
            try:
                process.wait(10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        for pid in self._leftovers():
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass

    def _leftovers(self) -> list[int]:
        """Processes of this cluster still alive: slurmstepd and job steps, which carry its
        SLURM_CONF in their environment."""
        marker = f"SLURM_CONF={self.conf}".encode()
        found = []
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit() or int(entry.name) == os.getpid():
                continue
            try:
                environ = (entry / "environ").read_bytes().split(b"\0")
            except OSError:
                continue
            if marker in environ:
                found.append(int(entry.name))
        return found


@contextmanager
def slurm_cluster(folder: Path) -> Iterator[Cluster]:
    """A started cluster, stopped at the end (SlurmUnavailable when it cannot start)."""
    cluster = Cluster(folder)
    try:
        cluster.start()
        yield cluster
    finally:
        cluster.stop()
