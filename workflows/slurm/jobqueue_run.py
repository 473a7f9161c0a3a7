"""Run ``holefill run`` on Dask workers that dask-jobqueue submits as SLURM jobs.

    python jobqueue_run.py OUT INPUT... [--jobs 4] [--cores 32] [--memory 128GB]
        [--partition NAME] [--account NAME] [--walltime auto] [-- holefill run options]

Starts a ``SLURMCluster`` (its scheduler runs in this process), asks for ``--jobs``
worker jobs, waits for the first worker, then runs
``holefill run INPUT... --out OUT --scheduler ADDRESS --resume --no-progress`` and exits
with holefill's status. SIGTERM and SIGINT are passed on to holefill, which stops and
keeps its finished tasks (exit 130); before holefill has started they stop the wait for
workers (exit 130). The worker jobs are cancelled when this script ends, whatever ends it.

``--walltime auto`` gives the worker jobs this job's time left plus
:data:`WALLTIME_MARGIN_S` (they must outlive the driver, which stops holefill before its
own limit); outside a SLURM job, :data:`DEFAULT_WALLTIME`. Workers retire
:data:`RETIRE_BEFORE_S` before their limit (``dask worker --lifetime``): a signal from
``--signal`` would reach only the job's batch shell, never ``dask worker`` (with ``B:``)
or nothing at all (without: the worker runs in no job step).

Workers run this same Python (``sys.executable``): install holefill and dask-jobqueue
where every node sees them at the same path, and keep the inputs and OUT on the shared
file system. Needs ``dask-jobqueue>=0.8`` (``pip install 'holefill[cluster]'``).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import subprocess
import sys

#: Worker jobs get the driver's time left plus this (seconds).
WALLTIME_MARGIN_S = 600
#: ... or this outside a SLURM job.
DEFAULT_WALLTIME = "12:30:00"
#: Workers retire this long before their time limit (seconds).
RETIRE_BEFORE_S = 120


def time_left_s(job_id: str) -> int | None:
    """A SLURM job's time left (squeue's %L: [days-]hours:minutes:seconds or minutes:seconds), or None."""
    try:
        left = subprocess.run(
            ["squeue", "-h", "-j", job_id, "-o", "%L"], capture_output=True, text=True, timeout=30
        ).stdout.strip()
    except (OSError, subprocess.TimeoutExpired):
        return None
    match = re.fullmatch(r"(?:(\d+)-)?(?:(\d+):)?(\d+):(\d+)", left)
    if not match:
        return None
    days, hours, minutes, seconds = (int(g or 0) for g in match.groups())
    return ((days * 24 + hours) * 60 + minutes) * 60 + seconds


def walltime_seconds(text: str) -> int:
    """``[days-]hours:minutes:seconds`` (or ``minutes:seconds``) in seconds."""
    match = re.fullmatch(r"(?:(\d+)-)?(?:(\d+):)?(\d+):(\d+)", text)
    if not match:
        raise ValueError(f"--walltime {text!r}: expected [days-]hours:minutes:seconds")
    days, hours, minutes, seconds = (int(g or 0) for g in match.groups())
    return ((days * 24 + hours) * 60 + minutes) * 60 + seconds


def worker_walltime(asked: str) -> str:
    """``--walltime``, with ``auto`` resolved from this job's time left."""
    if asked != "auto":
        walltime_seconds(asked)  # checked
        return asked
    left = time_left_s(os.environ["SLURM_JOB_ID"]) if os.environ.get("SLURM_JOB_ID") else None
    if left is None:
        return DEFAULT_WALLTIME
    total = left + WALLTIME_MARGIN_S
    return f"{total // 3600:02d}:{total % 3600 // 60:02d}:{total % 60:02d}"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    extra: list[str] = []
    if "--" in argv:
        argv, extra = argv[: argv.index("--")], argv[argv.index("--") + 1 :]
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", help="output folder (on the shared file system)")
    parser.add_argument("inputs", nargs="+", help="LAS/LAZ files, folders or globs (on the shared file system)")
    parser.add_argument("--jobs", type=int, default=4, help="worker jobs (nodes) to ask for")
    parser.add_argument("--cores", type=int, default=32, help="cores per worker job (one worker process each)")
    parser.add_argument("--memory", default="128GB", help="memory per worker job")
    parser.add_argument("--walltime", default="auto", help="worker jobs' time limit ('auto': this job's time left + 10 min)")
    parser.add_argument("--partition", help="SLURM partition of the worker jobs")
    parser.add_argument("--account", help="SLURM account of the worker jobs")
    parser.add_argument("--local-directory", default="$TMPDIR", help="workers' scratch space on their node")
    parser.add_argument("--holefill", default=shutil.which("holefill") or "holefill", help="the holefill command")
    args = parser.parse_args(argv)

    try:
        from dask_jobqueue import SLURMCluster
        from distributed import Client
    except ImportError as e:
        print(
            f"jobqueue_run.py: needs dask-jobqueue: pip install 'holefill[cluster]' (the optional extra), {e}",
            file=sys.stderr,
        )
        return 2

    walltime = worker_walltime(args.walltime)
    lifetime = max(60, walltime_seconds(walltime) - RETIRE_BEFORE_S)
    holefill: subprocess.Popen | None = None

    def forward(signum: int, frame: object) -> None:
        if holefill is None:
            raise KeyboardInterrupt  # still waiting for workers: stop waiting, close the cluster
        if holefill.poll() is None:
            holefill.send_signal(signal.SIGTERM)

    signal.signal(signal.SIGTERM, forward)
    signal.signal(signal.SIGINT, forward)
    cluster = None
    try:
        cluster = SLURMCluster(
            cores=args.cores,
            processes=args.cores,  # one single-threaded worker process per core, like holefill's local cluster
            memory=args.memory,
            walltime=walltime,
            queue=args.partition,
            account=args.account,
            local_directory=args.local_directory,
            job_name="holefill-worker",
            python=sys.executable,
            worker_extra_args=["--lifetime", f"{lifetime}s", "--lifetime-stagger", "30s"],
        )
        cluster.scale(jobs=args.jobs)
        with Client(cluster) as client:
            print(
                f"jobqueue_run.py: {args.jobs} worker jobs of {walltime} asked for; "
                f"scheduler {cluster.scheduler_address}",
                file=sys.stderr,
            )
            client.wait_for_workers(1)
            command = [args.holefill, "run", *args.inputs, "--out", args.out]
            command += ["--scheduler", cluster.scheduler_address, "--resume", "--no-progress", *extra]
            holefill = subprocess.Popen(command)
            return holefill.wait()
    except KeyboardInterrupt:
        print("jobqueue_run.py: stopped before holefill started; cancelling the worker jobs", file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # the clean-up below must not be cut short
        if cluster is not None:
            cluster.close()  # cancels the worker jobs, pending or running


if __name__ == "__main__":
    sys.exit(main())
