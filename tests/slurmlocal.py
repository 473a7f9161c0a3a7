"""A one-node SLURM brought up inside a test run, from Debian's packages (slurm-wlm, munge).

No systemd: munged, slurmctld and slurmd run in the foreground (``-D``) as children of
the test, with their configuration, sockets, state and logs in a temporary folder and
ports of their own, so they touch nothing of the machine's and stop with the test.
:func:`start` raises :class:`Unavailable` (the test skips) where the programs are missing,
the test is not root (slurmd must be), or the daemons do not come up.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import time
from pathlib import Path

DAEMONS = ("munged", "slurmctld", "slurmd", "sbatch", "squeue", "scontrol", "scancel", "sinfo")
#: Seconds for the node to register as idle.
START_TIMEOUT_S = 60


class Unavailable(RuntimeError):
    """SLURM cannot run here (the reason says why)."""


class Slurm:
    """The running daemons and the environment that points the SLURM commands at them."""

    def __init__(self, root: Path, processes: list[subprocess.Popen], env: dict[str, str]) -> None:
        self.root = root
        self.processes = processes
        self.env = env

    def run(self, *command: str, check: bool = True) -> str:
        done = subprocess.run(command, env=self.env, capture_output=True, text=True, timeout=60)
        if check and done.returncode != 0:
            raise AssertionError(f"{' '.join(command)}: {done.returncode} {done.stderr}")
        return done.stdout

    def job(self, job_id: str) -> dict[str, str]:
        """``scontrol show job`` as a dict (JobState, ExitCode, Restarts, ...)."""
        text = self.run("scontrol", "show", "job", "-o", job_id)
        return dict(item.split("=", 1) for item in text.split() if "=" in item)

    def wait_state(self, job_id: str, states: set[str], timeout: float) -> dict[str, str]:
        started = time.monotonic()
        while time.monotonic() - started < timeout:
            info = self.job(job_id)
            if info.get("JobState") in states:
                return info
            time.sleep(1)
        raise AssertionError(f"job {job_id} not in {states} after {timeout} s: {self.job(job_id)}")

    def stop(self) -> None:
        for process in reversed(self.processes):
            if process.poll() is None:
                process.terminate()
        for process in reversed(self.processes):
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _config(root: Path, host: str, cpus: int, memory_mb: int) -> str:
    ctld, slurmd = _free_port(), _free_port()
    return f"""ClusterName=holefilltest
SlurmctldHost={host}
SlurmctldPort={ctld}
SlurmdPort={slurmd}
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={root}/munge.socket
StateSaveLocation={root}/state
SlurmdSpoolDir={root}/spool/%n
SlurmctldPidFile={root}/slurmctld.pid
SlurmdPidFile={root}/slurmd.pid
SlurmctldLogFile={root}/slurmctld.log
SlurmdLogFile={root}/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
MpiDefault=none
SchedulerType=sched/builtin
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
ReturnToService=2
JobRequeue=1
MinJobAge=3600
KillWait=30
InactiveLimit=0
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/filetxt
JobCompLoc={root}/jobcomp.txt
NodeName={host} CPUs={cpus} RealMemory={memory_mb} State=UNKNOWN
PartitionName=test Nodes=ALL Default=YES MaxTime=INFINITE State=UP
"""


def start(root: Path) -> Slurm:
    """Start munged, slurmctld and slurmd for one node (this host) under ``root``."""
    missing = [name for name in DAEMONS if shutil.which(name) is None]
    if missing:
        raise Unavailable(f"not installed: {', '.join(missing)} (apt-get install slurm-wlm munge)")
    if os.geteuid() != 0:
        raise Unavailable("slurmd must run as root")
    key = Path("/etc/munge/munge.key")
    if not key.exists():
        raise Unavailable(f"{key} missing (the munge package creates it)")
    host = socket.gethostname().split(".")[0]
    for sub in ("state", "spool", "munge"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    conf = root / "slurm.conf"
    memory_mb = max(512, os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2**20 // 2)
    conf.write_text(_config(root, host, os.cpu_count() or 1, memory_mb))
    env = {**os.environ, "SLURM_CONF": str(conf)}
    log = (root / "daemons.log").open("ab")
    munged = [
        "munged", "--foreground", "--force", f"--socket={root}/munge.socket", f"--key-file={key}",
        f"--pid-file={root}/munge/munged.pid", f"--log-file={root}/munge/munged.log", f"--seed-file={root}/munge/seed",
    ]  # fmt: skip
    processes = [subprocess.Popen(munged, stdout=log, stderr=log)]
    time.sleep(1)
    processes.append(subprocess.Popen(["slurmctld", "-D", "-i", "-f", str(conf)], env=env, stdout=log, stderr=log))
    time.sleep(2)
    processes.append(subprocess.Popen(["slurmd", "-D", "-f", str(conf), "-N", host], env=env, stdout=log, stderr=log))
    slurm = Slurm(root, processes, env)
    started = time.monotonic()
    while time.monotonic() - started < START_TIMEOUT_S:
        dead = [p.args[0] for p in processes if p.poll() is not None]
        if dead:
            break
        state = subprocess.run(["sinfo", "-h", "-o", "%t"], env=env, capture_output=True, text=True).stdout.strip()
        if state in ("idle", "mix", "alloc"):
            return slurm
        time.sleep(1)
    slurm.stop()
    tail = (root / "daemons.log").read_text(errors="replace")[-2000:]
    for name in ("slurmctld.log", "slurmd.log"):
        if (root / name).exists():
            tail += "\n" + (root / name).read_text(errors="replace")[-1500:]
    raise Unavailable(f"SLURM did not come up: {tail}")
