"""End to end on small LAZ surveys: the DSM must not depend on how the survey is cut."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import rasterio

from pipeline.config import load_config
from pipeline.errors import InputDataError, OutputError
from pipeline.io.intermediate import load_cell_statistics
from pipeline.io.raster import NODATA, read_raster
from pipeline.io.vector import list_layers, read_layer
from pipeline.run import run_survey

from .lasfiles import random_points, write_points

BOUNDS = (1000.0, 2000.0, 1100.0, 2080.0)


@pytest.fixture(scope="module")
def survey_points():
    rng = np.random.default_rng(7)
    return random_points(rng, 40_000, BOUNDS)


def write_tiling(folder: Path, points, tiling: str) -> list[str]:
    """Write the same points cut in different ways."""
    x, y, z = points
    folder.mkdir(parents=True, exist_ok=True)
    if tiling == "one":
        groups = [np.ones(len(x), bool)]
    elif tiling == "quadrants":  # boundaries not on the pixel lattice
        groups = [
            (x < 1047.3) & (y < 2041.7), (x >= 1047.3) & (y < 2041.7),
            (x < 1047.3) & (y >= 2041.7), (x >= 1047.3) & (y >= 2041.7),
        ]  # fmt: skip
    elif tiling == "strips":  # overlapping flight strips: points in the overlap split between them
        rng = np.random.default_rng(3)
        first = (x < 1040) | ((x < 1065) & (rng.random(len(x)) < 0.5))
        groups = [first, ~first]
    paths = []
    for i, select in enumerate(groups):
        paths.append(str(write_points(folder / f"{tiling}_{i}.laz", x[select], y[select], z[select])))
    return paths


def assemble_cells(out: Path, grid_shape) -> dict[str, np.ndarray]:
    """The merged statistics of every cell core, put back together over the whole grid."""
    manifest = json.loads((out / "manifest.json").read_text())
    width, height = manifest["grid"]["width"], manifest["grid"]["height"]
    full = {name: None for name in ("zmax", "zmin", "count", "voxels")}
    for path in sorted((out / "work" / "cells").glob("*.npz")):
        stats = load_cell_statistics(path)
        for name in full:
            if full[name] is None:
                full[name] = np.zeros((height, width), getattr(stats, name).dtype)
        # cores do not overlap; halos do and agree
        w = stats.window
        for name in full:
            full[name][w.row_off : w.row_end, w.col_off : w.col_end] = getattr(stats, name)
    return full


def run(inputs, out, client, *overrides):
    config = load_config(overrides=["grid.resolution_m=1.0", "output.keep_intermediate=true", *overrides])
    return run_survey(inputs, out, config, client=client)


@pytest.mark.slow
@pytest.mark.parametrize("align", ["edge", "center"])
def test_dsm_does_not_depend_on_cell_size_or_tiling(tmp_path, survey_points, dask_client, align):
    results = {}
    for tiling, cell_m in [("one", 1000.0), ("one", 16.0), ("quadrants", 32.0), ("strips", 20.0)]:
        inputs = write_tiling(tmp_path / "in" / tiling, survey_points, tiling)
        out = tmp_path / f"out_{tiling}_{cell_m:g}"
        run(inputs, out, dask_client, f"grid.cell_size_m={cell_m}", "output.keep_unfilled=true", f"grid.align={align}")
        dsm, transform, _ = read_raster(out / "dsm_unfilled.vrt")
        filled, _, _ = read_raster(out / "dsm.vrt")
        results[(tiling, cell_m)] = (dsm, filled, transform, assemble_cells(out, dsm.shape))
    (reference, ref_filled, ref_transform, ref_stats) = results[("one", 1000.0)]
    # pixel edges, or pixel centres, on multiples of the 1 m pixel
    assert ref_transform.c % 1.0 == (0.0 if align == "edge" else 0.5)
    assert np.isfinite(reference).sum() > 0.8 * reference.size
    assert np.isnan(reference).sum() > 400  # the circular hole and empty pixels are nodata before filling
    assert np.isfinite(ref_filled).sum() > np.isfinite(reference).sum() + 300  # ... and filled after
    for key, (dsm, filled, transform, stats) in results.items():
        assert transform == ref_transform, key
        np.testing.assert_array_equal(dsm, reference, err_msg=str(key))
        # holes are filled whole, whatever the cells: equal up to the solver's rounding. Without
        # --aoi the survey area is the union of the tiles' header bounds, which depends on the
        # tiling at the survey's outer corners (the union of two strips' boxes is not the box of
        # all points): an empty corner pixel is a hole for one tiling and exterior for another.
        inner = (slice(1, -1), slice(1, -1))
        np.testing.assert_array_equal(np.isnan(filled[inner]), np.isnan(ref_filled[inner]), err_msg=str(key))
        np.testing.assert_allclose(filled[inner], ref_filled[inner], atol=1e-4, equal_nan=True, err_msg=str(key))
        for name in ("zmax", "zmin", "count", "voxels"):
            np.testing.assert_array_equal(stats[name], ref_stats[name], err_msg=f"{key} {name}")


@pytest.mark.slow
def test_the_take_off_ground_stage_1_keeps_is_the_ground_points_read_again_whatever_the_tiling(
    tmp_path, survey_points, dask_client
):
    """A run planning flights sums the ground points' heights per pixel while it decodes them (every
    ground point not withheld, the class filter's choice aside); the planner reads those sums from the
    cells instead of decoding the files again: the same mean heights and water points as
    ``read_ground`` over the files, whatever the tiling and the cells."""
    from pipeline.io.flightplan_files import CellGround, read_cell_ground, read_ground
    from pipeline.io.intermediate import load_cell_ground

    x, y, z = survey_points
    rng = np.random.default_rng(11)
    classes = rng.choice(np.array([1, 2, 2, 5, 6, 9], np.uint8), len(x))
    withheld = rng.random(len(x)) < 0.05
    kept = {}
    for tiling, cell_m in [("one", 1000.0), ("quadrants", 32.0), ("strips", 20.0)]:
        folder = tmp_path / "in" / tiling
        folder.mkdir(parents=True)
        groups = {"one": [np.ones(len(x), bool)], "quadrants": [x < 1047.3, x >= 1047.3]}.get(
            tiling, [(x < 1040) | ((x < 1065) & (rng.random(len(x)) < 0.5))]
        )
        if tiling == "strips":
            groups.append(~groups[0])
        inputs = [
            str(write_points(folder / f"{i}.laz", x[g], y[g], z[g], classification=classes[g], withheld=withheld[g]))
            for i, g in enumerate(groups)
        ]
        out = tmp_path / f"out_{tiling}"
        # the filter keeps buildings alone: ground points count for the take-off all the same
        run(inputs, out, dask_client, f"grid.cell_size_m={cell_m}", "filter.keep_classes=[6]", "holes.enabled=true")
        with rasterio.open(out / "dsm.vrt") as dsm:
            transform, shape = dsm.transform, dsm.shape
        cells = []
        for path in sorted((out / "work" / "cells").glob("*.npz")):
            found = load_cell_ground(path)
            assert found is not None, path
            cells.append((str(path), found[0].window))
        from_cells = read_cell_ground(CellGround(tuple(cells), transform), transform, shape)
        assert from_cells is not None
        from_points = read_ground(inputs, transform, shape)
        np.testing.assert_allclose(from_cells[0], from_points[0], rtol=0, atol=1e-9, equal_nan=True)
        np.testing.assert_array_equal(from_cells[1], from_points[1])
        kept[tiling] = from_cells
    assert np.isfinite(kept["one"][0]).sum() > 0.3 * kept["one"][0].size and kept["one"][1].sum() > 100
    for tiling in ("quadrants", "strips"):
        np.testing.assert_allclose(kept[tiling][0], kept["one"][0], rtol=0, atol=1e-9, equal_nan=True)
        np.testing.assert_array_equal(kept[tiling][1], kept["one"][1])


@pytest.mark.slow
def test_outputs_are_valid_cogs_and_layers(tmp_path, survey_points, dask_client):
    inputs = write_tiling(tmp_path / "in", survey_points, "quadrants")
    digests = {p: hashlib.sha256(Path(p).read_bytes()).hexdigest() for p in inputs}
    out = tmp_path / "out"
    summary = run(inputs, out, dask_client, "grid.cell_size_m=25")
    assert summary.points_read == len(survey_points[0])
    assert sorted(p.name for p in out.iterdir()) == [
        "dsm", "dsm.vrt", "fill_distance", "fill_distance.vrt", "fill_mask", "fill_mask.vrt",
        "flightplan.gpkg", "holes.gpkg", "manifest.json", "report.html", "work",
    ]  # fmt: skip
    report = (out / "report.html").read_text()
    assert "By cause" in report and f"{summary.points_read:,}" in report
    tiles = sorted((out / "dsm").glob("*.tif"))
    assert len(tiles) == len(summary.dsm_tiles) > 1
    for tif in tiles:
        with rasterio.open(tif) as ds:
            assert ds.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
            assert ds.crs.to_epsg() == 2154
            assert ds.nodata == NODATA
            assert ds.overviews(1), "COG must carry overviews"
            assert ds.profile["tiled"] and ds.compression is not None
    with rasterio.open(out / "dsm.vrt") as ds:
        assert ds.crs.to_epsg() == 2154 and ds.nodata == NODATA
    assert {"tiles", "cells"} <= set(list_layers(out / "holes.gpkg"))
    tiles_layer = read_layer(out / "holes.gpkg", "tiles")
    assert len(tiles_layer) == 4 and tiles_layer.crs.to_epsg() == 2154
    assert tiles_layer["points_used"].sum() == summary.points_used
    cells_layer = read_layer(out / "holes.gpkg", "cells")
    assert cells_layer["points"].sum() == summary.points_used
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["summary"]["points_read"] == summary.points_read
    # the profile: every lap's wall and client CPU seconds, and each Dask stage's tasks and compute seconds
    profile = manifest["summary"]
    assert set(profile["stage_client_cpu_seconds"]) == set(profile["stage_seconds"]) >= {"scan", "rasterize", "holes"}
    tasks = profile["worker_task_seconds"]
    assert tasks["bin_tiles"]["tasks"] == 4 and tasks["bin_tiles"]["seconds"] > 0
    assert tasks["merge_cells"]["tasks"] == tasks["detect_holes"]["tasks"] == summary.cells
    # the flight plans and the other layers are made while the workers fit the walls (gathered last);
    # the walls' layers and counts join them after, where the manifest has always listed them
    laps = list(profile["stage_seconds"])
    assert laps.index("outputs") < laps.index("flightplan") < laps.index("walls")
    assert {"walls", "vertical_holes", "holes", "flight_lines"} <= set(list_layers(out / "holes.gpkg"))
    holes = list(manifest["holes"])
    after_gaps = holes.index("sampling_gap_area_m2") + 1
    assert holes[after_gaps : after_gaps + 3] == ["vertical_hole_groups", "walls", "height_jump_px"]
    assert manifest["holes"]["walls"] == len(read_layer(out / "holes.gpkg", "walls"))
    # inputs are never modified
    assert digests == {p: hashlib.sha256(Path(p).read_bytes()).hexdigest() for p in inputs}


@pytest.mark.slow
def test_bad_tile_fails_cleanly_or_is_skipped(tmp_path, survey_points, dask_client):
    inputs = write_tiling(tmp_path / "in", survey_points, "quadrants")
    data = Path(inputs[1]).read_bytes()
    Path(inputs[1]).write_bytes(data[: len(data) // 2])
    out = tmp_path / "out"
    with pytest.raises(InputDataError, match="strips|quadrants_1.laz"):
        run(inputs, out, dask_client)
    assert not out.exists(), "a failed run leaves no output behind"
    (tmp_path / "existing").mkdir()
    with pytest.raises(InputDataError):
        run(inputs, tmp_path / "existing", dask_client)
    assert list((tmp_path / "existing").iterdir()) == []
    summary = run(inputs, out, dask_client, "survey.on_error=skip")
    assert [s["path"] for s in summary.skipped] == [inputs[1]]
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["skipped"][0]["path"] == inputs[1]
    status = dict(zip(*read_layer(out / "holes.gpkg", "tiles")[["name", "status"]].values.T))
    assert status["quadrants_1.laz"] == "skipped"


def test_unwritable_output_folder(tmp_path, survey_points):
    inputs = write_tiling(tmp_path / "in", survey_points, "one")
    blocker = tmp_path / "file"
    blocker.write_text("a file where a folder should be")
    with pytest.raises(OutputError, match="output folder cannot be created"):
        run(inputs, blocker / "out", None)


@pytest.mark.slow
def test_unforeseen_worker_error_is_one_line_naming_the_task(dask_client):
    import operator

    from pipeline.errors import TaskError
    from pipeline.run import _Progress, _Runner

    runner = _Runner(dask_client, _Progress(False))
    future = runner.submit(operator.truediv, 1, 0, label="cell 500_1000 (find holes)", key="divide")
    with pytest.raises(TaskError) as caught:
        runner.gather([future], lambda result: None)
    assert str(caught.value) == "cell 500_1000 (find holes): ZeroDivisionError: division by zero"


def _quick(x):
    return x


def _slow(x, *after):
    import time

    time.sleep(0.5)
    return x


def test_a_streaming_stage_s_results_are_seen_while_the_next_stage_runs(dask_client):
    """Stage 1's footprint is counted as soon as its tiles are in, while the workers merge the
    last cells: ``when_gathered`` sees a streaming stage's results before the batch is done."""
    from pipeline.run import _gather_batch, _Progress, _Runner, _StageTimer
    from pipeline.stages.stage import RunState, Stage

    first = Stage(name="first", worker=_quick, gather=lambda state, results: sorted(results), streams=True)
    second = Stage(name="second", worker=_slow, gather=lambda state, results: sorted(results))
    runner = _Runner(dask_client, _Progress(False))
    quick = [runner.submit(_quick, i, label=f"q{i}", key=f"quick-{i}") for i in range(4)]
    slow = [runner.submit(_slow, i, quick[i], label=f"s{i}", key=f"slow-{i}") for i in range(4)]
    seen = []

    def when_first_done(results):
        seen.append((sorted(results), sum(f.done() for f in slow)))

    state = RunState(plan=None, config=load_config(None), staging=None)
    state = _gather_batch(runner, state, [(first, quick), (second, slow)], _StageTimer(0.0), {"first": when_first_done})
    assert seen == [([0, 1, 2, 3], seen[0][1])] and seen[0][1] < 4  # before the second stage was done
    assert state[second] == [0, 1, 2, 3]
