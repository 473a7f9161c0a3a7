"""The output folder: never read back as input, and never a folder of someone else's files replaced unasked."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from pipeline.cli import main

from .lasfiles import random_points, write_points


@pytest.fixture
def runner():
    return CliRunner()


@pytest.fixture
def tiles(tmp_path, rng) -> Path:
    folder = tmp_path / "tiles"
    folder.mkdir()
    write_points(folder / "a.laz", *random_points(rng, 4000, (1000.0, 2000.0, 1100.0, 2100.0)))
    write_points(folder / "b.laz", *random_points(rng, 4000, (1100.0, 2000.0, 1200.0, 2100.0)))
    return folder


def run(runner, *args):
    return runner.invoke(main, ["run", *map(str, args), "--no-progress", "--workers", "1"])


def test_a_result_inside_the_input_folder_is_not_read_back(runner, tiles):
    out = tiles / "result"
    for _ in range(2):
        result = run(runner, tiles, "--out", out, "--set", "output.points=true", "--set", "grid.resolution_m=2")
        assert result.exit_code == 0, result.output
        manifest = json.loads((out / "manifest.json").read_text())
        assert sorted(Path(i["path"]).name for i in manifest["inputs"]) == ["a.laz", "b.laz"]
        for entry in manifest["inputs"]:  # hashed by the task that decoded the file
            path = Path(entry["path"])
            assert entry["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
            assert entry["bytes"] == path.stat().st_size and entry["mtime"] == path.stat().st_mtime
    assert sorted(p.name for p in (out / "points").iterdir()) == ["a.laz", "b.laz"]
    # a repaired point cloud named as an input is refused: its run would replace it
    result = run(
        runner, out / "points" / "a.laz", "--out", out, "--set", "output.points=true", "--set", "grid.resolution_m=2"
    )
    assert result.exit_code == 3 and "lies in a folder this run writes" in result.output


def test_user_files_in_the_output_folder_are_not_deleted(runner, tiles, tmp_path):
    out = tmp_path / "out"
    (out / "dsm").mkdir(parents=True)
    (out / "dsm" / "notes.txt").write_text("x")
    result = run(runner, tiles, "--out", out)
    assert result.exit_code == 4 and "dsm/notes.txt is not a holefill product" in result.output
    assert (out / "dsm" / "notes.txt").read_text() == "x" and not (out / "manifest.json").exists()
    # a folder of someone's files, with no holefill result
    other = tmp_path / "other"
    other.mkdir()
    (other / "thesis.tex").write_text("x")
    result = run(runner, tiles, "--out", other)
    assert result.exit_code == 4 and "holds no holefill result (thesis.tex)" in result.output
    assert sorted(p.name for p in other.iterdir()) == ["thesis.tex"]
    # --overwrite says the folder may be replaced
    result = run(runner, tiles, "--out", other, "--overwrite")
    assert result.exit_code == 0, result.output
    assert (other / "thesis.tex").exists() and (other / "manifest.json").exists()


def test_a_result_of_another_survey_is_not_replaced_unless_asked(runner, tiles, tmp_path, rng):
    out = tmp_path / "out"
    assert run(runner, tiles, "--out", out).exit_code == 0
    before = (out / "manifest.json").read_bytes()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    write_points(elsewhere / "c.laz", *random_points(rng, 4000, (1000.0, 2000.0, 1100.0, 2100.0)))
    result = run(runner, elsewhere, "--out", out)  # same configuration, other inputs
    assert result.exit_code == 4 and "holds the result of another survey" in result.output
    assert (out / "manifest.json").read_bytes() == before
    # the same survey with a tile more (a delivery) is the same survey
    write_points(tiles / "c.laz", *random_points(rng, 4000, (1200.0, 2000.0, 1300.0, 2100.0)))
    assert run(runner, tiles, "--out", out).exit_code == 0
    assert run(runner, elsewhere, "--out", out, "--overwrite").exit_code == 0
