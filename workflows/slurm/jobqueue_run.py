"""Run ``holefill run`` on Dask workers that dask-jobqueue submits as SLURM jobs.

    python jobqueue_run.py OUT INPUT... [--jobs 4] [--cores 32] [--memory 128GB]
        [--partition NAME] [--account NAME] [--walltime 12:30:00] [-- holefill run options]

Starts a ``SLURMCluster`` (its scheduler runs in this process), asks for ``--jobs``
worker jobs, waits for the first worker, then runs
``holefill run INPUT... --out OUT --scheduler ADDRESS --resume --no-progress`` and exits
with holefill's status. SIGTERM and SIGINT are passed on to holefill, which stops and
keeps its finished tasks (exit 130); the worker jobs are cancelled when this script ends.

Workers run this same Python (``sys.executable``): install holefill and dask-jobqueue
where every node sees them at the same path, and keep the inputs and OUT on the shared
file system. Needs ``dask-jobqueue>=0.8`` (``pip install 'holefill[cluster]'``).
"""

from __future__ import annotations

import argparse
import shutil
import signal
import subprocess
import sys


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
    parser.add_argument("--walltime", default="12:30:00", help="time limit of each worker job")
    parser.add_argument("--partition", help="SLURM partition of the worker jobs")
    parser.add_argument("--account", help="SLURM account of the worker jobs")
    parser.add_argument("--local-directory", default="$TMPDIR", help="workers' scratch space on their node")
    parser.add_argument("--holefill", default=shutil.which("holefill") or "holefill", help="the holefill command")
    args = parser.parse_args(argv)

    try:
        from dask_jobqueue import SLURMCluster
        from distributed import Client
    except ImportError as e:
        print(f"jobqueue_run.py: needs dask-jobqueue (pip install 'holefill[cluster]'): {e}", file=sys.stderr)
        return 2

    cluster = SLURMCluster(
        cores=args.cores,
        processes=args.cores,  # one single-threaded worker process per core, like holefill's local cluster
        memory=args.memory,
        walltime=args.walltime,
        queue=args.partition,
        account=args.account,
        local_directory=args.local_directory,
        job_name="holefill-worker",
        python=sys.executable,
        job_extra_directives=["--signal=TERM@120"],
    )
    holefill: subprocess.Popen | None = None

    def forward(signum: int, frame: object) -> None:
        if holefill is not None and holefill.poll() is None:
            holefill.send_signal(signal.SIGTERM)

    signal.signal(signal.SIGTERM, forward)
    signal.signal(signal.SIGINT, forward)
    try:
        cluster.scale(jobs=args.jobs)
        with Client(cluster) as client:
            print(
                f"jobqueue_run.py: {args.jobs} worker jobs asked for; scheduler {cluster.scheduler_address}",
                file=sys.stderr,
            )
            client.wait_for_workers(1)
            command = [args.holefill, "run", *args.inputs, "--out", args.out]
            command += ["--scheduler", cluster.scheduler_address, "--resume", "--no-progress", *extra]
            holefill = subprocess.Popen(command)
            return holefill.wait()
    finally:
        cluster.close()


if __name__ == "__main__":
    sys.exit(main())
