"""Every bad input gives one clear line naming the file and the problem, the documented exit status,
and no half-written output (tested through the command line, as users meet them)."""

from __future__ import annotations

import json
import os
import struct
import time
from pathlib import Path

import numpy as np
import pytest
import shapely
from click.testing import CliRunner

from pipeline.cli import main
from pipeline.io.vector import read_layer, write_layer

from .lasfiles import random_points, write_points


@pytest.fixture
def runner():
    return CliRunner()


def run(runner, *args):
    return runner.invoke(main, ["run", *map(str, args), "--no-progress"])


def one_error_line(result) -> str:
    lines = [line for line in result.output.strip().splitlines() if line.startswith("holefill: error:")]
    assert len(lines) == 1 and "Traceback" not in result.output, result.output
    return lines[0]


def patch(path: Path, offset: int, fmt: str, *values) -> None:
    data = bytearray(path.read_bytes())
    struct.pack_into(fmt, data, offset, *values)
    path.write_bytes(bytes(data))


def test_nan_and_absurd_header_bounds(runner, tmp_path, rng):
    path = write_points(tmp_path / "nan.las", *random_points(rng, 500), version="1.2")
    patch(path, 179, "<d", float("nan"))  # max x
    result = run(runner, path, "--out", tmp_path / "o")
    assert result.exit_code == 3 and "nan.las: header bounds are not finite" in one_error_line(result)
    path = write_points(tmp_path / "far.las", *random_points(rng, 500), version="1.2")
    patch(path, 179, "<d", 460_000.0 + 1100.0)  # max x 460 km east: a box of 4.6e7 m x 80 m for 500 points
    patch(path, 195, "<d", 200_000.0)  # max y
    result = run(runner, path, "--out", tmp_path / "o")
    assert result.exit_code == 3 and "far.las: header bounds span" in one_error_line(result)
    assert not (tmp_path / "o").exists()


def test_header_that_under_reports_its_points_is_refused(runner, tmp_path, rng):
    path = write_points(tmp_path / "short.las", *random_points(rng, 500), version="1.2")
    patch(path, 107, "<I", 300)  # legacy point count: 300 of the records present
    result = run(runner, path, "--out", tmp_path / "o")
    line = one_error_line(result)
    assert result.exit_code == 3 and "short.las: header point count is 300 but the file holds" in line


def test_filter_removing_every_point_and_aoi_outside_the_data(runner, tmp_path, rng):
    path = write_points(tmp_path / "a.laz", *random_points(rng, 2000))
    result = run(runner, path, "--out", tmp_path / "o", "--set", "filter.keep_classes=[9]")
    assert result.exit_code == 3 and "no point is left after filtering" in one_error_line(result)
    assert not (tmp_path / "o").exists()
    aoi = tmp_path / "far.gpkg"
    write_layer(aoi, "aoi", [{"id": 1}], [shapely.box(50_000, 50_000, 50_100, 50_100)], crs_wkt="EPSG:2154")
    result = run(runner, path, "--out", tmp_path / "o", "--aoi", aoi)
    assert result.exit_code == 3 and "does not overlap the data" in one_error_line(result)
    assert not (tmp_path / "o").exists()


def test_water_beside_the_data_and_an_aoi_of_empty_polygons_are_named(runner, tmp_path, rng):
    """Polygons that cannot apply get their own line: most likely a file in another CRS than it says."""
    path = write_points(tmp_path / "a.laz", *random_points(rng, 2000))
    water = tmp_path / "lakes.gpkg"
    write_layer(water, "water", [{"id": 1}], [shapely.box(50_000, 50_000, 50_100, 50_100)], crs_wkt="EPSG:2154")
    result = run(runner, path, "--out", tmp_path / "o", "--water", water)
    line = one_error_line(result)
    assert result.exit_code == 3 and "lakes.gpkg: water polygons do not overlap the survey area" in line
    assert "is the file's CRS right?" in line and not (tmp_path / "o").exists()
    aoi = tmp_path / "empty.gpkg"
    write_layer(aoi, "aoi", [{"id": 1}], [shapely.Polygon()], crs_wkt="EPSG:2154")
    result = run(runner, path, "--out", tmp_path / "o", "--aoi", aoi)
    line = one_error_line(result)
    assert result.exit_code == 3 and "empty.gpkg: AOI file holds only empty polygons" in line
    assert not (tmp_path / "o").exists()


def test_broken_links_are_named_and_skipped(runner, tmp_path, rng):
    folder = tmp_path / "tiles"
    folder.mkdir()
    write_points(folder / "a.laz", *random_points(rng, 2000))
    os.symlink(tmp_path / "gone.laz", folder / "b.laz")
    result = run(runner, folder, "--out", tmp_path / "o")
    assert result.exit_code == 3 and "b.laz: broken symbolic link" in one_error_line(result)
    result = run(runner, folder, "--out", tmp_path / "o", "--on-error", "skip", "--set", "grid.cell_size_m=50")
    assert result.exit_code == 5, result.output  # partial success: outputs written, a tile skipped
    manifest = json.loads((tmp_path / "o" / "manifest.json").read_text())
    assert manifest["skipped"][0]["reason"].startswith("broken symbolic link")


def test_unreachable_scheduler_fails_within_seconds(runner, tmp_path, rng):
    path = write_points(tmp_path / "a.laz", *random_points(rng, 500))
    started = time.monotonic()
    result = run(runner, path, "--out", tmp_path / "o", "--scheduler", "tcp://127.0.0.1:9")
    assert result.exit_code == 1 and "cannot reach the Dask scheduler" in one_error_line(result)
    assert time.monotonic() - started < 30
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_relative_output_folder_on_a_running_scheduler(runner, tmp_path, rng, dask_client, monkeypatch):
    path = write_points(tmp_path / "a.laz", *random_points(rng, 2000))
    monkeypatch.chdir(tmp_path)
    result = run(runner, path, "--out", "relative/out", "--scheduler", dask_client.scheduler.address,
                 "--set", "grid.cell_size_m=50")  # fmt: skip
    assert result.exit_code == 0, result.output
    assert (tmp_path / "relative" / "out" / "manifest.json").exists()


def test_evaluate_a_folder_without_a_run(runner, tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "truth.tif").write_bytes(b"")
    result = runner.invoke(main, ["evaluate", str(tmp_path / "empty"), "--truth", str(tmp_path / "truth.tif")])
    assert result.exit_code == 3 and "holds no finished holefill run" in one_error_line(result)


def test_scores_are_valid_json_when_no_hole_is_scored():
    from pipeline.evaluate.truth import HoleScore

    text = json.dumps(
        HoleScore(iou=1.0, true_hole_px=0, detected_px=0, holes=0, cause_correct=0).as_dict(), allow_nan=False
    )
    assert json.loads(text)["cause_accuracy"] is None


def test_laz_header_that_under_reports_its_points_is_refused(runner, tmp_path, rng):
    """LAS 1.4's 64-bit count (offset 247) halved in a LAZ file: laspy would decode half the points."""
    path = write_points(tmp_path / "half.laz", *random_points(rng, 120_000))  # three LAZ chunks of 50,000
    count = struct.unpack_from("<Q", path.read_bytes(), 247)[0]
    patch(path, 247, "<Q", count // 2)
    result = run(runner, path, "--out", tmp_path / "o")
    line = one_error_line(result)
    assert result.exit_code == 3 and f"half.laz: header point count is {count // 2:,}" in line
    assert "chunk table holds at least 100,001 points" in line
    assert not (tmp_path / "o").exists()


def test_points_outside_the_header_bounds_are_refused(runner, tmp_path, rng):
    path = write_points(tmp_path / "short.las", *random_points(rng, 5000))
    max_x = struct.unpack_from("<d", path.read_bytes(), 179)[0]
    patch(path, 179, "<d", max_x - 5.0)  # max x 5 m short of the points
    result = run(runner, path, "--out", tmp_path / "o")
    line = one_error_line(result)
    assert result.exit_code == 3 and "short.las:" in line and "lie outside the bounds its header declares" in line
    assert not (tmp_path / "o").exists()
    # with --on-error skip it is a skipped tile, named in the manifest and the report's first warnings
    write_points(tmp_path / "good.las", *random_points(rng, 5000, (1100.0, 2000.0, 1200.0, 2080.0)))
    result = run(runner, path, tmp_path / "good.las", "--out", tmp_path / "o", "--on-error", "skip")
    assert result.exit_code == 5, result.output
    manifest = json.loads((tmp_path / "o" / "manifest.json").read_text())
    assert [Path(s["path"]).name for s in manifest["skipped"]] == ["short.las"]


def test_a_tile_that_yields_no_point_is_listed_like_a_skipped_tile(runner, tmp_path, rng):
    folder = tmp_path / "tiles"
    folder.mkdir()
    write_points(folder / "a.laz", *random_points(rng, 5000, (1000.0, 2000.0, 1100.0, 2100.0)))
    x, y, z = random_points(rng, 5000, (1100.0, 2000.0, 1200.0, 2100.0))
    write_points(folder / "b.laz", x, y, z, withheld=np.ones(len(x), bool))  # every point withheld
    result = run(runner, folder, "--out", tmp_path / "o")
    assert result.exit_code == 5, result.output
    assert "skipping" in result.output and "b.laz: no point used" in result.output
    manifest = json.loads((tmp_path / "o" / "manifest.json").read_text())
    assert [Path(s["path"]).name for s in manifest["skipped"]] == ["b.laz"]
    assert manifest["summary"]["points_used"] < manifest["summary"]["points_read"]
    report = (tmp_path / "o" / "report.html").read_text()
    assert "Look at first" in report and "b.laz" in report
    tiles = read_layer(tmp_path / "o" / "holes.gpkg", "tiles")
    assert sorted(tiles["status"]) == ["no points", "ok"]


def test_a_grid_too_fine_for_memory_is_refused_at_planning(runner, tmp_path, rng):
    """0.01 m pixels on a 1 km tile: 1e10 pixels a task; refused with one line before any task runs."""
    path = write_points(tmp_path / "km.laz", *random_points(rng, 5000, (1000.0, 1000.0, 2000.0, 2000.0)))
    result = run(runner, path, "--out", tmp_path / "o", "--set", "grid.resolution_m=0.01")
    line = one_error_line(result)
    assert result.exit_code == 2 and "grid.resolution_m = 0.01" in line and "km.laz: a task over it needs" in line
    assert "--resume" not in result.output and "MemoryError" not in result.output
    assert not (tmp_path / "o").exists()
    # a cell too large for the worker's memory limit names the cell size
    result = run(runner, path, "--out", tmp_path / "o", "--set", "grid.resolution_m=0.5",
                 "--set", "grid.cell_size_m=1000", "--set", 'dask.memory_limit="200MB"')  # fmt: skip
    line = one_error_line(result)
    assert result.exit_code == 2 and "grid.cell_size_m = 1000" in line and "dask.memory_limit = 200MB" in line
    assert not (tmp_path / "o").exists()


def test_tiles_on_two_continents_are_refused_at_planning(runner, tmp_path, rng):
    """France (Lambert-93) and New York (UTM 18N) in one Web Mercator grid: the footprint map would be absurd."""
    france = write_points(tmp_path / "fr.laz", *random_points(rng, 2000, (650_000, 6_860_000, 650_100, 6_860_080)))
    ny = write_points(
        tmp_path / "ny.laz", *random_points(rng, 2000, (585_000, 4_510_000, 585_100, 4_510_080)), crs="EPSG:32618"
    )
    result = run(runner, france, ny, "--out", tmp_path / "o", "--target-crs", "EPSG:3857")
    line = one_error_line(result)
    assert result.exit_code == 3 and "the tiles span 8,4" in line and "footprint map" in line
    assert not (tmp_path / "o").exists()


def _dense_points(bounds=(1000.0, 2000.0, 1100.0, 2080.0), step=0.5):
    """A regular 0.5 m lattice of points: a survey without a hole."""
    minx, miny, maxx, maxy = bounds
    x, y = np.meshgrid(np.arange(minx + step / 2, maxx, step), np.arange(miny + step / 2, maxy, step))
    x, y = np.round(x.ravel(), 2), np.round(y.ravel(), 2)
    return x, y, np.round(50 + 0.01 * x, 2)


def _write_truth(path: Path, manifest: dict, *, shift: float = 0.0, scale: float = 1.0) -> Path:
    import rasterio
    from affine import Affine

    grid = manifest["grid"]
    resolution = grid["resolution"] * scale
    left, top = grid["bounds"][0] + shift * grid["resolution"], grid["bounds"][3]
    width, height = round(grid["width"] / scale), round(grid["height"] / scale)
    profile = dict(driver="GTiff", width=width, height=height, count=1, dtype="uint8", crs=manifest["crs"]["wkt"])
    with rasterio.open(path, "w", transform=Affine(resolution, 0, left, 0, -resolution, top), **profile) as dst:
        dst.write(np.zeros((1, height, width), np.uint8))
    return path


def test_evaluate_a_run_without_holes_and_bad_truths(runner, tmp_path):
    path = write_points(tmp_path / "dense.laz", *_dense_points())
    result = run(runner, path, "--out", tmp_path / "o")
    assert result.exit_code == 0, result.output
    out = tmp_path / "o"
    holes = read_layer(out / "holes.gpkg", "holes")
    assert len(holes) == 0 and {"hole_id", "cause", "area_m2", "fill_status"} <= set(holes.columns)  # schema kept
    for layer in ("hole_parts", "vertical_holes", "walls"):
        assert len(read_layer(out / "holes.gpkg", layer).columns) > 1, layer
    manifest = json.loads((out / "manifest.json").read_text())

    def evaluate(truth):
        return runner.invoke(main, ["evaluate", str(out), "--truth", str(truth)])

    result = evaluate(_write_truth(tmp_path / "truth.tif", manifest))
    assert result.exit_code == 0, result.output
    score = json.loads(result.output)
    assert score["holes"] == 0 and score["iou"] == 1.0
    result = evaluate(_write_truth(tmp_path / "shifted.tif", manifest, shift=0.5))
    assert result.exit_code == 3 and "shifted.tif: truth pixels are shifted off the run's lattice" in one_error_line(
        result
    )
    result = evaluate(_write_truth(tmp_path / "coarse.tif", manifest, scale=2.0))
    assert result.exit_code == 3 and "coarse.tif: truth pixel size" in one_error_line(result)
    (tmp_path / "truth.csv").write_text("x,y,cause\n1,2,3\n")
    result = evaluate(tmp_path / "truth.csv")
    assert result.exit_code == 3 and "truth.csv: truth is not a readable raster" in one_error_line(result)


def test_a_245_character_file_stem_runs(runner, tmp_path, rng):
    """Internal names built from the stem (work folders, kept results, partial copies) are shortened."""
    from pipeline.io.intermediate import INTERNAL_NAME_MAX, internal_name

    stem = "survey_" + "x" * 238
    path = write_points(tmp_path / f"{stem}.laz", *random_points(rng, 3000))
    result = run(runner, path, "--out", tmp_path / "o", "--set", "output.points=true", "--incremental")
    assert result.exit_code == 0, result.output
    assert (tmp_path / "o" / "points" / f"{stem}.laz").exists()  # the user's name is kept where it fits
    assert all(len(p.name) <= INTERNAL_NAME_MAX + 12 for p in (tmp_path / "o" / "work").rglob("*"))
    assert internal_name("short") == "short"
    long_a, long_b = internal_name("a" * 300), internal_name("a" * 299 + "b")
    assert len(long_a.encode()) <= INTERNAL_NAME_MAX and long_a != long_b and long_a.startswith("aaaa")
