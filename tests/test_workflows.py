"""workflows/: the recipes parse, and every holefill command and option they use exists.

Checked where a tool is at hand: ``bash -n`` for shell scripts, ``systemd-analyze
verify`` for the units (skipped without it), PyYAML for Kubernetes (skipped without
it), the five time fields of cron and scrontab lines. The options check reads every
``holefill <command> --option`` of the recipes (shell, cron, READMEs' sh blocks, the
Kubernetes container command, the dask-jobqueue script's command list) and compares it
with ``holefill <command> --help``.
"""

from __future__ import annotations

import ast
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from pipeline.cli import main

WORKFLOWS = Path(__file__).resolve().parents[1] / "workflows"
SHELL_SCRIPTS = sorted(WORKFLOWS.rglob("*.sbatch")) + sorted(WORKFLOWS.rglob("*.sh"))
CRON_FILES = sorted(WORKFLOWS.rglob("*.crontab")) + sorted(WORKFLOWS.rglob("*.scrontab"))
UNITS = sorted(WORKFLOWS.rglob("*.service")) + sorted(WORKFLOWS.rglob("*.timer"))
YAML_FILES = sorted(WORKFLOWS.rglob("*.yaml"))
PYTHON_FILES = sorted(WORKFLOWS.rglob("*.py"))
READMES = sorted(WORKFLOWS.rglob("README.md"))

#: Options that recipes may use before ``holefill <command> --help`` lists them (work merged
#: in parallel); only ``run --resume`` may ever go here, and it is merged already.
NOT_YET_MERGED: dict[str, set[str]] = {}

_SHELL_END = {";", "&", "&&", "||", "|", ")", ">", ">>", "2>&1", "<", "<<<", "2>"}


def test_the_recipes_are_there():
    assert SHELL_SCRIPTS and CRON_FILES and UNITS and YAML_FILES and PYTHON_FILES
    assert (WORKFLOWS / "README.md").exists()
    for folder in ("slurm", "schedule", "kubernetes"):
        assert (WORKFLOWS / folder / "README.md").exists()


@pytest.mark.parametrize("script", SHELL_SCRIPTS, ids=lambda p: p.name)
def test_shell_scripts_parse(script):
    result = subprocess.run(["bash", "-n", str(script)], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


@pytest.mark.parametrize("script", SHELL_SCRIPTS, ids=lambda p: p.name)
def test_batch_scripts_stop_with_sigterm_and_resume(script):
    text = script.read_text()
    if "jobqueue_run.py" in text:  # the driver job: the holefill command is in the script it runs
        text += (WORKFLOWS / "slurm" / "jobqueue_run.py").read_text()
    assert "--resume" in text and "--no-progress" in text
    # a stop before the time limit that follows the job's own limit (not a fixed --signal lead)
    assert "time_left_s" in text and "kill -USR1" in text, "no stop before the time limit"
    assert not re.search(r"^#SBATCH --signal", text, re.M), "a fixed lead fires at once when --time is shortened"
    assert 'echo "holefill: exit $status ($(meaning "$status"))"' in text, "the exit status is not logged"
    assert "kill -TERM" in text and "scontrol requeue" in text and "#SBATCH --requeue" in text


def test_systemd_units_verify(tmp_path):
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze not installed")
    holefill = Path(sys.executable).with_name("holefill")
    for unit in UNITS:  # the recipe's install paths and user do not exist here
        text = unit.read_text().replace("/opt/holefill/.venv/bin/holefill", str(holefill))
        text = re.sub(r"^(User|Group)=.*$", r"\1=root", text, flags=re.M)
        (tmp_path / unit.name).write_text(text)
    result = subprocess.run(
        [analyze, "verify", *(str(tmp_path / u.name) for u in UNITS)], capture_output=True, text=True, timeout=60
    )
    problems = [line for line in result.stderr.splitlines() if "holefill" in line]
    assert result.returncode == 0 and not problems, result.stderr


def test_systemd_service_retries_with_resume_but_not_bad_input():
    service = (WORKFLOWS / "schedule" / "holefill-nightly.service").read_text()
    settings = dict(line.split("=", 1) for line in service.splitlines() if "=" in line and not line.startswith("#"))
    assert "--resume" in settings["ExecStart"]
    assert settings["Restart"] == "on-failure" and settings["KillMode"] == "mixed"
    assert set(settings["RestartPreventExitStatus"].split()) == {"2", "3", "4", "5"}
    assert "TimeoutStartSec" in settings and "TimeoutStopSec" in settings


def _cron_entries(path: Path) -> list[str]:
    return [
        line
        for line in path.read_text().splitlines()
        if line.strip() and not line.lstrip().startswith("#") and not re.match(r"^[A-Z_]+=", line)
    ]


_FIELD_RANGES = ((0, 59), (0, 23), (1, 31), (1, 12), (0, 7))


def _valid_cron_field(field: str, low: int, high: int) -> bool:
    for item in field.split(","):
        base, _, step = item.partition("/")
        if step and not step.isdigit():
            return False
        if base == "*":
            continue
        bounds = base.split("-")
        if not all(b.isdigit() and low <= int(b) <= high for b in bounds) or len(bounds) > 2:
            return False
    return True


@pytest.mark.parametrize("path", CRON_FILES, ids=lambda p: p.name)
def test_cron_lines_have_five_time_fields_and_a_command(path):
    entries = _cron_entries(path)
    assert entries
    for line in entries:
        fields = line.split(None, 5)
        assert len(fields) == 6, line
        for field, (low, high) in zip(fields[:5], _FIELD_RANGES):
            assert _valid_cron_field(field, low, high), f"{field!r} in {line!r}"
        assert re.search(r"(?<!\\)%", fields[5]) is None, f"unescaped % (cron reads it as a newline): {line}"


def test_cron_entry_runs_under_flock_and_timeout():
    run = next(line for line in _cron_entries(WORKFLOWS / "schedule" / "holefill.crontab") if " run " in line)
    assert "flock -n" in run and "timeout --kill-after=" in run and "--resume" in run


def test_scrontab_options_are_sbatch_options():
    text = (WORKFLOWS / "schedule" / "holefill.scrontab").read_text()
    options = re.findall(r"^#SCRON (\S+)", text, re.M)
    assert options and all(o.startswith("--") for o in options)
    assert any(o.startswith("--signal=B:TERM@") for o in options) and any(o.startswith("--time=") for o in options)
    assert "exec " in _cron_entries(WORKFLOWS / "schedule" / "holefill.scrontab")[0]


def test_kubernetes_cronjob():
    yaml = pytest.importorskip("yaml")
    documents = [d for d in yaml.safe_load_all((WORKFLOWS / "kubernetes" / "cronjob.yaml").read_text()) if d]
    (cronjob,) = documents
    assert cronjob["apiVersion"] == "batch/v1" and cronjob["kind"] == "CronJob"
    spec = cronjob["spec"]
    assert spec["concurrencyPolicy"] == "Forbid" and spec["startingDeadlineSeconds"] > 0
    assert len(spec["schedule"].split()) == 5
    job = spec["jobTemplate"]["spec"]
    assert job["activeDeadlineSeconds"] > 0 and job["backoffLimit"] >= 1
    (fail_rule,) = [r for r in job["podFailurePolicy"]["rules"] if r["action"] == "FailJob"]
    assert set(fail_rule["onExitCodes"]["values"]) == {2, 3, 4, 5}
    pod = job["template"]["spec"]
    assert pod["restartPolicy"] == "Never" and pod["terminationGracePeriodSeconds"] >= 60
    (container,) = pod["containers"]
    command = " ".join(container.get("command", []) + container.get("args", []))
    assert "exec holefill run" in command and "--resume" in command
    assert f'"host": "{pod["hostname"]}"' in command  # the stale-lock check matches the pod's hostname


def test_jobqueue_script_compiles_and_explains_itself_without_dask_jobqueue():
    script = WORKFLOWS / "slurm" / "jobqueue_run.py"
    compile(script.read_text(), str(script), "exec")
    result = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and "--jobs" in result.stdout


# -- every holefill command and option used in a recipe exists -------------------------------


def _shell_invocations(text: str) -> list[list[str]]:
    """Token lists that start at a ``holefill`` word (any path ending in /holefill)."""
    text = re.sub(r"\\\n", " ", text)  # line continuations
    found = []
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("#") and not line.startswith("#SCRON"):
            continue
        try:
            tokens = shlex.split(line, comments=True)
        except ValueError:
            continue
        for i, token in enumerate(tokens):
            # a command word, not an option's value (crontab -u holefill)
            if (token == "holefill" or token.endswith("/holefill")) and not (i and tokens[i - 1].startswith("-")):
                words = []
                for word in tokens[i + 1 :]:
                    if word in _SHELL_END or word.startswith((">", "2>")):
                        break
                    words.append(word)
                found.append(words)
    return found


def _python_invocations(text: str) -> list[list[str]]:
    """The ``command`` lists of a Python recipe (``command = [holefill, "run", ...]``, ``command += [...]``)."""
    words: list[str] = []
    for node in ast.walk(ast.parse(text)):
        target = getattr(node, "target", None) or (node.targets[0] if isinstance(node, ast.Assign) else None)
        if isinstance(target, ast.Name) and target.id == "command" and isinstance(node.value, ast.List):  # type: ignore[attr-defined]
            words += [e.value for e in node.value.elts if isinstance(e, ast.Constant) and isinstance(e.value, str)]  # type: ignore[attr-defined]
    return [words] if words else []


def _readme_blocks(text: str) -> str:
    return "\n".join(re.findall(r"```(?:sh|bash|shell)\n(.*?)```", text, re.S))


def _invocations() -> list[tuple[str, list[str]]]:
    found = []
    for path in SHELL_SCRIPTS + CRON_FILES + UNITS + YAML_FILES:
        found += [(path.name, words) for words in _shell_invocations(path.read_text())]
    for path in READMES:
        found += [
            (str(path.relative_to(WORKFLOWS)), words) for words in _shell_invocations(_readme_blocks(path.read_text()))
        ]
    for path in PYTHON_FILES:
        found += [(path.name, words) for words in _python_invocations(path.read_text())]
    return found


def _options(help_text: str) -> set[str]:
    options = set()
    for line in help_text.splitlines():
        match = re.match(r"\s+(-[^\s].*?)(?:\s{2,}|$)", line)
        if match:
            for part in re.split(r"[,/]\s*", match.group(1)):
                name = part.strip().split(" ")[0]
                if name.startswith("-"):
                    options.add(name)
    return options


def _help(*command: str) -> str:
    result = CliRunner().invoke(main, [*command, "--help"])
    assert result.exit_code == 0, result.output
    return result.output


def test_every_holefill_option_in_the_recipes_exists():
    invocations = _invocations()
    commands = {words[0] for _, words in invocations if words and not words[0].startswith("-")}
    assert {"run", "plan"} <= commands, f"the options check found too few invocations: {invocations}"
    global_options = _options(_help())
    known = {command: _options(_help(command)) | NOT_YET_MERGED.get(command, set()) for command in commands}
    problems = []
    for where, words in invocations:
        while words and words[0].startswith("-"):  # holefill -q run ...
            if words[0] not in global_options:
                problems.append(f"{where}: holefill {words[0]}: no such global option")
            words = words[1:]
        if not words:
            continue
        command, rest = words[0], words[1:]
        if command not in known:
            problems.append(f"{where}: holefill {command}: no such command")
            continue
        for word in rest:
            option = word.split("=", 1)[0]
            if (
                option.startswith("-")
                and option != "-"
                and not re.match(r"^-\d", option)
                and option not in known[command]
            ):
                problems.append(f"{where}: holefill {command} {option}: no such option")
    assert not problems, "\n".join(problems)


def test_every_holefill_run_in_a_recipe_resumes():
    runs = [(where, words) for where, words in _invocations() if "run" in words[:2]]
    assert len(runs) >= 6
    assert all("--resume" in words for where, words in runs if not where.endswith("README.md")), runs


def test_the_options_check_sees_continuations_and_redirections():
    text = "x=1\n/opt/v/bin/holefill -q run a b \\\n  --out o --resume >> log 2>&1 # --not-an-option\n"
    assert _shell_invocations(text) == [["-q", "run", "a", "b", "--out", "o", "--resume"]]


def test_the_allow_list_is_only_for_what_is_not_merged_yet():
    run_options = _options(_help("run"))
    assert {"--out", "--config", "--set", "--workers", "--scheduler", "--no-progress"} <= run_options
    assert set(NOT_YET_MERGED) <= {"run"} and NOT_YET_MERGED.get("run", set()) <= {"--resume"}


STUB_JOBQUEUE = """
import pathlib, sys, time
MARK = pathlib.Path(sys.argv[1]).parent
class SLURMCluster:
    scheduler_address = "tcp://stub:8786"
    def __init__(self, **kwargs):
        (MARK / "options").write_text(repr(sorted(kwargs.items())))
    def scale(self, jobs):
        pass
    def close(self):
        (MARK / "closed").write_text("yes")
"""

STUB_DISTRIBUTED = """
import pathlib, sys, time
class Client:
    def __init__(self, cluster):
        pass
    def __enter__(self):
        return self
    def __exit__(self, *exc):
        return False
    def wait_for_workers(self, n):
        (pathlib.Path(sys.argv[1]).parent / "waiting").write_text("yes")
        time.sleep(600)  # no worker job starts
"""


def test_jobqueue_driver_cancelled_while_waiting_for_workers_closes_its_cluster(tmp_path):
    """A TERM before holefill starts stopped nothing for 30 s, and the worker jobs started afterwards."""
    stubs = tmp_path / "stubs"
    (stubs / "dask_jobqueue").mkdir(parents=True)
    (stubs / "distributed").mkdir()
    (stubs / "dask_jobqueue" / "__init__.py").write_text(STUB_JOBQUEUE)
    (stubs / "distributed" / "__init__.py").write_text(STUB_DISTRIBUTED)
    script = WORKFLOWS / "slurm" / "jobqueue_run.py"
    env = {**os.environ, "PYTHONPATH": str(stubs)}
    env.pop("SLURM_JOB_ID", None)
    driver = subprocess.Popen(
        [sys.executable, str(script), str(tmp_path / "out"), "in"], env=env, stderr=subprocess.PIPE, text=True
    )
    started = time.monotonic()
    while not (tmp_path / "waiting").exists():
        assert driver.poll() is None and time.monotonic() - started < 60, driver.communicate()
        time.sleep(0.05)
    driver.send_signal(signal.SIGTERM)
    _, err = driver.communicate(timeout=10)
    assert driver.returncode == 130, err
    assert (tmp_path / "closed").exists()  # the cluster closed: pending worker jobs cancelled
    options = (tmp_path / "options").read_text()
    assert "'walltime', '12:30:00'" in options and "--lifetime" in options and "--signal" not in options


def _run_cron_line(line: str, tmp_path: Path, status: int) -> subprocess.CompletedProcess:
    """The nightly cron command, as cron's bash runs it, with its paths in ``tmp_path`` and a stub holefill."""
    stub = tmp_path / "holefill"
    stub.write_text(f"#!/bin/bash\necho 'holefill output'\nexit {status}\n")
    stub.chmod(0o755)
    command = line.split(None, 5)[5].replace("\\%", "%").replace("/var/log/holefill", str(tmp_path / "logs"))
    command = command.replace("/var/lock", str(tmp_path)).replace("/opt/holefill/.venv/bin/holefill", str(stub))
    return subprocess.run(["bash", "-c", command], capture_output=True, text=True, timeout=60)


@pytest.mark.skipif(shutil.which("flock") is None or shutil.which("timeout") is None, reason="needs flock, timeout")
def test_cron_night_creates_its_log_folder_and_mails_one_line_when_it_fails_or_is_skipped(tmp_path):
    run = next(line for line in _cron_entries(WORKFLOWS / "schedule" / "holefill.crontab") if " run " in line)
    done = _run_cron_line(run, tmp_path, 0)
    assert done.returncode == 0 and done.stdout == "" and done.stderr == ""  # cron mails nothing
    assert "holefill output" in next((tmp_path / "logs").glob("nightly-*.log")).read_text()
    failed = _run_cron_line(run, tmp_path, 3)
    assert failed.stdout.startswith("holefill: exit 3 ") and "nightly-" in failed.stdout  # cron mails this line
    holder = subprocess.Popen(["flock", str(tmp_path / "holefill-nightly.lock"), "sleep", "30"])
    time.sleep(0.5)  # the previous night still runs
    skipped = _run_cron_line(run, tmp_path, 0)
    holder.kill()
    assert skipped.stdout.startswith("holefill: night skipped")
