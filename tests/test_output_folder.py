"""The output folder: never read back as input, and never a folder of someone else's files replaced unasked."""

from __future__ import annotations

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
    assert sorted(p.name for p in (out / "points").iterdir()) == ["a.laz", "b.laz"]
    # a repaired point cloud named as an input is refused: its run would replace it
    result = run(runner, out / "points" / "a.laz", "--out", out, "--set", "output.points=true", "--set", "grid.resolution_m=2")
    assert result.exit_code == 3 and "lies in a folder this run writes" in result.output
