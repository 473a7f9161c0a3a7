"""The SLURM recipes on a real one-node SLURM: time limit, scancel, requeue, resume, locks, exit lines.

Minutes long, so not in the default run: select it with ``HOLEFILL_TEST_SLURM=1 pytest -m
slurm tests/test_slurm.py`` (as root, with ``apt-get install slurm-wlm munge``; the
daemons are started by the test, tests/slurmlocal.py). Skips, never fails, where SLURM
cannot be installed or started.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.synth import generate_survey, preset

from . import slurmlocal
from .test_resume import same_outputs

pytestmark = [
    pytest.mark.slow,
    pytest.mark.slurm,
    pytest.mark.skipif(not os.environ.get("HOLEFILL_TEST_SLURM"), reason="set HOLEFILL_TEST_SLURM=1 (minutes)"),
]

SLURM_DIR = Path(__file__).resolve().parent.parent / "workflows" / "slurm"
#: A job of one minute, stopped 50 s before its limit: about 10 s of work per attempt, where the
#: survey needs about 13 s with one worker, so the first attempt is stopped and requeued.
JOB_OPTIONS = ("--time=1", "--cpus-per-task=1", "--mem=300M")


@pytest.fixture(scope="module")
def slurm(tmp_path_factory):
    try:
        cluster = slurmlocal.start(tmp_path_factory.mktemp("slurm"))
    except slurmlocal.Unavailable as e:
        pytest.skip(str(e))
    cluster.env.update(HOLEFILL_VENV=sys.prefix, HOLEFILL_MAX_REQUEUES="8", HOLEFILL_STOP_LEAD_S="50")
    yield cluster
    cluster.stop()


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    folder = tmp_path_factory.mktemp("slurm-survey")
    generate_survey(folder / "tiles", preset("demo", width_m=1000.0, height_m=600.0, tile_size_m=100.0, seed=11))
    reference = folder / "reference"
    done = subprocess.run(
        [sys.executable, "-m", "pipeline.cli", "run", str(folder / "tiles"), "--out", str(reference), "--workers", "1"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr
    return folder


def submit(slurm, *args: str) -> str:
    return slurm.run("sbatch", "--parsable", *args).strip().split(";")[0]


def log_of(slurm, job_id: str) -> str:
    path = Path(slurm.job(job_id)["StdOut"])
    return path.read_text() if path.exists() else ""


def test_single_node_job_stopped_at_its_time_limit_is_requeued_and_resumes(slurm, survey, tmp_path):
    out = tmp_path / "out"
    # stopped 54 s before the one-minute limit: 6 s an attempt, less than the survey needs however
    # quiet the machine (7.5 s of stages alone on an idle 2-core VM), so the first attempt is stopped
    job = submit(
        slurm, *JOB_OPTIONS, "--export=ALL,HOLEFILL_STOP_LEAD_S=54", f"--output={tmp_path}/job-%j.log", f"--chdir={tmp_path}",
        str(SLURM_DIR / "single-node.sbatch"), str(out), str(survey / "tiles"),
    )  # fmt: skip
    info = slurm.wait_state(job, {"COMPLETED", "FAILED", "CANCELLED", "TIMEOUT"}, timeout=900)
    log = log_of(slurm, job)
    assert info["JobState"] == "COMPLETED" and info["ExitCode"] == "0:0", log
    assert int(info["Restarts"]) >= 1, log  # stopped before the limit at least once, requeued
    assert "holefill: exit 130 (interrupted" in log and "requeueing job" in log
    assert log.rstrip().splitlines()[-1] == "holefill: exit 0 (done)"
    assert "Traceback" not in log
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["complete"] and manifest["summary"]["resumed_tasks"] > 0
    assert not (out / ".holefill.lock").exists() and not list(out.glob(".holefill-partial-*"))
    same_outputs(survey / "reference", out)


def test_array_task_cancelled_keeps_its_work_and_a_resubmission_resumes(slurm, survey, tmp_path):
    out = tmp_path / "out"
    surveys = tmp_path / "surveys.txt"
    surveys.write_text(f"# one survey\n{out} {survey / 'tiles'}\n")
    options = ("--time=10", "--cpus-per-task=1", "--mem=300M", f"--output={tmp_path}/array-%j.log")
    array = submit(slurm, *options, "--array=0", str(SLURM_DIR / "survey-array.sbatch"), str(surveys))
    started = time.monotonic()
    while not list(out.glob(".holefill-partial-*/work/done/rasterize-*")):
        assert time.monotonic() - started < 300, "the array task kept no tile result"
        time.sleep(0.2)
    slurm.run("scancel", f"{array}_0")
    task = slurm.wait_state(f"{array}_0", {"CANCELLED", "COMPLETED", "FAILED"}, timeout=120)
    time.sleep(2)  # the batch script's last line after the job's state changed
    log = log_of(slurm, task["JobId"])
    assert "holefill: exit 130 (interrupted" in log and "requeueing" not in log, log
    assert not (out / ".holefill.lock").exists(), log  # scancel leaves no lock, however its TERMs arrive
    assert len(list(out.glob(".holefill-partial-*"))) == 1

    again = submit(slurm, *options, "--array=0", str(SLURM_DIR / "survey-array.sbatch"), str(surveys))
    info = slurm.wait_state(f"{again}_0", {"COMPLETED", "FAILED", "CANCELLED"}, timeout=600)
    log = log_of(slurm, info["JobId"])
    assert info["JobState"] == "COMPLETED", log
    assert log.rstrip().splitlines()[-1] == "holefill: exit 0 (done)"
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["summary"]["resumed_tasks"] > 0 and not (out / ".holefill.lock").exists()
    same_outputs(survey / "reference", out)


def test_array_recipe_without_array_says_so(slurm, tmp_path):
    job = submit(
        slurm,
        "--time=1",
        "--cpus-per-task=1",
        "--mem=100M",
        f"--output={tmp_path}/noarray-%j.log",
        str(SLURM_DIR / "survey-array.sbatch"),
        "x.txt",
    )
    info = slurm.wait_state(job, {"FAILED", "COMPLETED"}, timeout=120)
    assert info["ExitCode"] == "2:0"
    assert "holefill: exit 2 (bad configuration" in (tmp_path / f"noarray-{job}.log").read_text()
