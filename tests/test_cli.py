"""The command line through click's runner, on a real Dask cluster (--scheduler)."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from pipeline.cli import main

from .lasfiles import random_points, write_points


@pytest.fixture
def runner():
    return CliRunner()


def test_config_show_prints_resolved_toml(runner):
    result = runner.invoke(main, ["config", "--show", "--set", "grid.resolution_m=0.25"])
    assert result.exit_code == 0
    assert "resolution_m = 0.25" in result.output and "[survey]" in result.output


def test_bad_override_exits_2_with_one_line(runner, tmp_path):
    result = runner.invoke(main, ["run", str(tmp_path), "--out", str(tmp_path / "o"), "--set", "grid.pixel=1"])
    assert result.exit_code == 2
    assert result.output.strip().splitlines() == [
        "holefill: error: --set grid.pixel=1: unknown key 'grid.pixel'; allowed keys in [grid]: "
        "resolution_m, cell_size_m, halo_px, align"
    ]
    assert not (tmp_path / "o").exists()


def test_missing_crs_exits_3_naming_the_file(runner, tmp_path, rng):
    path = write_points(tmp_path / "nocrs.laz", *random_points(rng, 500), crs=None)
    result = runner.invoke(main, ["run", str(path), "--out", str(tmp_path / "o")])
    assert result.exit_code == 3
    assert "nocrs.laz" in result.output and "--crs" in result.output
    assert not (tmp_path / "o").exists()


def test_empty_input_folder_exits_3(runner, tmp_path):
    (tmp_path / "in").mkdir()
    result = runner.invoke(main, ["run", str(tmp_path / "in"), "--out", str(tmp_path / "o")])
    assert result.exit_code == 3 and "holds no .las or .laz" in result.output


@pytest.mark.slow
def test_run_with_crs_override_on_a_running_scheduler(runner, tmp_path, rng, dask_client):
    points = random_points(rng, 5000)
    path = write_points(tmp_path / "nocrs.laz", *points, crs=None)
    out = tmp_path / "o"
    result = runner.invoke(
        main,
        [
            "run", str(path), "--out", str(out), "--crs", "EPSG:28992",
            "--scheduler", dask_client.scheduler.address, "--set", "grid.cell_size_m=50", "--no-progress",
        ],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    manifest = json.loads((out / "manifest.json").read_text())
    assert "Amersfoort" in manifest["crs"]["name"]
    assert manifest["config"]["survey"]["crs"] == "EPSG:28992"
    assert manifest["summary"]["points_read"] == len(points[0])


def test_halo_narrower_than_detection_needs_stops_before_any_work(runner, tmp_path, rng):
    path = write_points(tmp_path / "a.laz", *random_points(rng, 500))
    result = runner.invoke(main, ["run", str(path), "--out", str(tmp_path / "o"), "--set", "grid.halo_px=4"])
    assert result.exit_code == 2
    assert result.output.strip().splitlines() == [
        "holefill: error: --set grid.halo_px=4: grid.halo_px = 4 is too small; hole detection reads 8 pixels "
        "around each cell (set holes.enabled = false to build the DSM only)"
    ]
    assert not (tmp_path / "o").exists()
    result = runner.invoke(main, ["config", "--set", "grid.halo_px=4", "--set", "holes.enabled=false"])
    assert result.exit_code == 0


def test_crs_given_as_wkt_reaches_the_config_intact(runner, tmp_path, rng):
    from pyproj import CRS

    wkt = CRS.from_epsg(28992).to_wkt()  # quotes, brackets, commas: no TOML string survives them
    path = write_points(tmp_path / "nocrs.laz", *random_points(rng, 500), crs=None)
    result = runner.invoke(main, ["run", str(path), "--out", str(tmp_path / "o"), "--crs", wkt, "--workers", "-1"])
    assert result.exit_code == 2  # --workers -1 is refused after --crs was accepted as it is
    assert "--workers -1: dask.workers = -1 is invalid" in result.output

    from pipeline.cli.options import with_options
    from pipeline.config import load_config

    config = with_options(load_config(), crs=wkt, workers=2)
    assert config.survey.crs == wkt and config.dask.workers == 2


@pytest.mark.slow
def test_quiet_run_says_nothing_and_json_log_is_one_object_per_line(runner, tmp_path, rng, dask_client):
    path = write_points(tmp_path / "a.laz", *random_points(rng, 5000))
    run = ["run", str(path), "--scheduler", dask_client.scheduler.address, "--set", "grid.cell_size_m=50"]
    quiet = runner.invoke(main, ["-q", *run, "--out", str(tmp_path / "q"), "--no-progress"])
    assert quiet.exit_code == 0 and quiet.stderr == "" and (tmp_path / "q" / "manifest.json").exists()
    logged = runner.invoke(main, ["--log-format", "json", *run, "--out", str(tmp_path / "j"), "--no-progress"])
    assert logged.exit_code == 0, logged.output
    records = [json.loads(line) for line in logged.stderr.splitlines()]
    assert records and all({"time", "level", "message"} <= set(r) for r in records)
    done = records[-1]
    manifest = json.loads((tmp_path / "j" / "manifest.json").read_text())
    assert done["event"] == "run_complete" and done["points_read"] == manifest["summary"]["points_read"] > 0
    # an error is one JSON line too, with its exit status; -q keeps it
    failed = runner.invoke(main, ["-q", "--log-format", "json", "run", str(tmp_path / "nothing.laz"), "--out", "o"])
    assert failed.exit_code == 3
    [error] = [json.loads(line) for line in failed.stderr.splitlines()]
    assert error["level"] == "error" and error["exit_status"] == 3 and "nothing.laz" in error["message"]


def test_the_script_exits_with_the_status_and_flushed_output(tmp_path):
    """``python -m pipeline.cli`` leaves by os._exit: the status, the output and the exit handlers still hold."""
    import subprocess
    import sys

    from pipeline import __version__

    def command(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "pipeline.cli", *args], capture_output=True, text=True, timeout=60)

    done = command("--version")
    assert done.returncode == 0 and __version__ in done.stdout
    done = command("config", "--show")  # a page of stdout: written out in full before the process ends
    assert done.returncode == 0 and done.stdout == CliRunner().invoke(main, ["config", "--show"]).output
    done = command("run", str(tmp_path / "none.laz"), "--out", str(tmp_path / "o"))
    assert done.returncode == 3 and "none.laz" in done.stderr and not (tmp_path / "o").exists()
    done = command("--log-format", "json", "run", str(tmp_path), "--out", str(tmp_path / "o"), "--set", "grid.pixel=1")
    assert done.returncode == 2
    assert json.loads(done.stderr.strip().splitlines()[-1])["exit_status"] == 2
