"""COPC at scale: one COPC file read by many tasks, each octree node decoded once, same products."""

from __future__ import annotations

import json
import os
import signal
from collections import Counter
from pathlib import Path

import laspy
import numpy as np
import pytest
import shapely

from pipeline.config import load_config
from pipeline.errors import ConfigError, InputDataError
from pipeline.io.copc import iter_copc_nodes, read_copc_octree, write_copc
from pipeline.io.las import read_header
from pipeline.io.raster import read_raster
from pipeline.io.vector import list_layers, write_layer
from pipeline.plan import plan_survey
from pipeline.run import run_survey
from pipeline.survey.scan import scan_survey
from pipeline.synth import generate_survey, preset
from tests.test_resume import holefill, same_outputs, wait_for_kept_tiles

IGN_TILES = "ign_tile_770*.laz"


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """A synthetic survey as 12 LAZ tiles, and the same points as one COPC file."""
    folder = tmp_path_factory.mktemp("copc")
    survey = generate_survey(
        folder / "tiles", preset("demo", width_m=400.0, height_m=300.0, tile_size_m=100.0, seed=11)
    )
    tiles = sorted(str(p) for p in (folder / "tiles").glob("*.laz"))
    copc = folder / "survey.copc.laz"
    write_copc(tiles, copc, max_node_points=8_000)
    return {"tiles": tiles, "copc": str(copc), "points": survey.n_points, "folder": folder}


def millimetres(x, y, z, classification) -> np.ndarray:
    """Points as integer millimetres and class (files may store them with other offsets)."""
    return np.column_stack([np.round(np.asarray(v) * 1000).astype(np.int64) for v in (x, y, z)] + [classification])


def sorted_rows(rows: list[np.ndarray]) -> np.ndarray:
    table = np.concatenate(rows)
    return table[np.lexsort(table.T[::-1])]


def points_of(paths) -> np.ndarray:
    """Every point's coordinates and class, sorted: a multiset to compare files by."""
    rows = []
    for path in paths:
        las = laspy.read(path)
        rows.append(millimetres(las.x, las.y, las.z, np.asarray(las.classification, np.int64)))
    return sorted_rows(rows)


def test_written_copc_reads_back_in_laspy_and_node_by_node(synthetic):
    copc = synthetic["copc"]
    expected = points_of(synthetic["tiles"])
    with laspy.CopcReader.open(copc) as reader:  # an independent reader of the format
        whole = reader.query()
        assert len(whole) == len(expected) == synthetic["points"]
    octree = read_copc_octree(copc)
    assert octree.nodes["level"].max() >= 2 and len(octree.nodes) > 20
    assert int(octree.nodes["point_count"].sum()) == len(expected)
    header = read_header(copc)
    assert header.format == "COPC" and header.copc is not None and header.point_format == 6
    # every node decoded once, in two disjoint halves, gives every point exactly once
    nodes = [(int(n["offset"]), int(n["byte_size"]), int(n["point_count"])) for n in octree.nodes]
    rows = []
    for half in (nodes[::2], nodes[1::2]):
        for chunk in iter_copc_nodes(copc, half, 20_000):
            rows.append(millimetres(*chunk.coordinates(), chunk.classification.astype(np.int64)))
    np.testing.assert_array_equal(sorted_rows(rows), expected)
    # the node cubes hold their points
    boxes = octree.node_bounds()
    assert (boxes[:, 2] > boxes[:, 0]).all()


def test_a_corrupt_chunk_is_named(synthetic, tmp_path):
    broken = tmp_path / "broken.copc.laz"
    data = bytearray(Path(synthetic["copc"]).read_bytes())
    node = read_copc_octree(synthetic["copc"]).nodes[3]
    data[int(node["offset"]) : int(node["offset"]) + 64] = bytes(64)
    broken.write_bytes(bytes(data))
    with pytest.raises(InputDataError, match="broken.copc.laz: COPC chunks cannot be decoded"):
        for _ in iter_copc_nodes(
            broken, [(int(node["offset"]), int(node["byte_size"]), int(node["point_count"]))], 10**5
        ):
            pass


def plan_for(path: str, *overrides: str):
    config = load_config(overrides=["grid.resolution_m=1.0", *overrides])
    return plan_survey(scan_survey([path]), config)


@pytest.mark.parametrize("cell_m", [50.0, 100.0, 200.0])
def test_every_node_is_read_by_exactly_one_task(synthetic, cell_m):
    copc = synthetic["copc"]
    plan = plan_for(copc, f"grid.cell_size_m={cell_m}", "rasterize.copc_split=true")
    octree = read_copc_octree(copc)
    assigned = Counter(node for read in plan.reads for node in read.nodes)
    listed = {(int(n["offset"]), int(n["byte_size"]), int(n["point_count"])) for n in octree.nodes}
    assert set(assigned) == listed and set(assigned.values()) == {1}
    assert sum(read.point_count for read in plan.reads) == synthetic["points"]
    file_window = plan.tile_windows[0]
    roles = Counter(read.role for read in plan.reads)
    assert roles["top"] == 1 and roles["cell"] == len(plan.reads) - 1
    # one cell task per cell of the file: the top task hands each its points
    assert sorted(r.cell for r in plan.reads if r.role == "cell") == sorted(plan.grid.cell_indices_under(file_window))
    for read, window in zip(plan.reads, plan.read_windows):
        if read.role == "top":  # it bins nothing: no window, in no cell's merge
            assert window.is_empty and all(read_index != 0 for r in plan.reads_of_cell.values() for read_index in r)
            continue
        assert window.intersection(file_window) == window and not window.is_empty
        # no larger than its cell grown by half a cell (a node centred in it), and a pixel
        assert window.width <= 2 * plan.grid.cell_px + 2 and window.height <= 2 * plan.grid.cell_px + 2
    # a cell's merge reads only the tasks whose window meets its halo
    for cell in plan.cells:
        for i in plan.reads_of_cell[cell.id]:
            assert not plan.read_windows[i].intersection(cell.halo_window).is_empty


def test_read_tasks_grow_with_the_cells_the_file_spans(synthetic):
    copc = synthetic["copc"]
    counts = {cell_m: len(plan_for(copc, f"grid.cell_size_m={cell_m}").reads) for cell_m in (50.0, 100.0, 200.0, 500.0)}
    assert counts[50.0] > counts[100.0] > counts[200.0] > counts[500.0] == 1  # auto: one cell, one task
    assert len(plan_for(copc, "grid.cell_size_m=50", "rasterize.copc_split=false").reads) == 1
    cells_50 = len(plan_for(copc, "grid.cell_size_m=50").cells)
    assert counts[50.0] >= cells_50 // 2  # about one task per cell, plus the octree's top
    # LAZ tiles are never split: one task per file
    assert len(plan_for(synthetic["tiles"][0], "grid.cell_size_m=50", "rasterize.copc_split=true").reads) == 1


def run(inputs, out, client, *overrides, aoi=None):
    config = load_config(
        overrides=["grid.resolution_m=1.0", "grid.cell_size_m=50", "flightplan.enabled=false", *overrides]
    )
    return run_survey(inputs, out, config, client=client, aoi=aoi)


@pytest.mark.slow
def test_split_copc_gives_the_products_of_the_whole_file_and_of_the_laz_tiles(synthetic, tmp_path, dask_client):
    copc = synthetic["copc"]
    area = tmp_path / "area.gpkg"  # one survey area for all: the LAZ tiles' union has slivers between tiles
    write_layer(
        area, "area", [{"id": 1}], [shapely.box(*read_header(copc).bounds)], crs_wkt=scan_survey([copc]).crs_wkt
    )
    split = run([copc], tmp_path / "split", dask_client, "rasterize.copc_split=true", aoi=area)
    whole = run([copc], tmp_path / "whole", dask_client, "rasterize.copc_split=false", aoi=area)
    tiles = run(synthetic["tiles"], tmp_path / "tiles", dask_client, aoi=area)
    manifest = json.loads((tmp_path / "split" / "manifest.json").read_text())
    (entry,) = manifest["inputs"]
    assert entry["points_read"] == read_header(copc).point_count == synthetic["points"]
    assert entry["read_tasks"] > 20 and split.cells == whole.cells == tiles.cells
    assert split.points_read == whole.points_read == tiles.points_read
    assert split.points_used == whole.points_used == tiles.points_used
    assert split.holes["listed"] > 0
    # the footprint's density, counted by stage 1 in whichever read tasks decode the points, is one
    densities = [
        json.loads((tmp_path / name / "manifest.json").read_text())["grid"]["sizing"]["density"]
        for name in ("split", "whole", "tiles")
    ]
    assert densities[0]["area_source"] == "data footprint" and densities[0] == densities[1] == densities[2]
    same_outputs(tmp_path / "whole", tmp_path / "split", estimated=True)
    assert "holes" in list_layers(tmp_path / "split" / "holes.gpkg")
    same_outputs(
        tmp_path / "tiles", tmp_path / "split", skip_layers=("tiles",), estimated=True
    )  # the tiles layer lists other files


@pytest.mark.slow
def test_split_copc_without_an_aoi_equals_the_whole_file(synthetic, tmp_path, dask_client):
    copc = synthetic["copc"]
    run([copc], tmp_path / "split", dask_client, "rasterize.copc_split=true", "grid.cell_size_m=32")
    run([copc], tmp_path / "whole", dask_client, "rasterize.copc_split=false", "grid.cell_size_m=32")
    same_outputs(tmp_path / "whole", tmp_path / "split", estimated=True)


@pytest.mark.slow
def test_killed_split_run_resumes_to_the_same_outputs(synthetic, tmp_path):
    copc = synthetic["copc"]
    settings = ["--set", "rasterize.copc_split=true", "--set", "grid.cell_size_m=50", "--set", "grid.resolution_m=1"]
    reference = tmp_path / "reference"
    done = holefill(copc, "--out", str(reference), *settings)
    assert done.wait(timeout=300) == 0, done.communicate()
    out = tmp_path / "out"
    killed = holefill(copc, "--out", str(out), *settings)
    wait_for_kept_tiles(out, 6, killed)
    os.killpg(killed.pid, signal.SIGKILL)
    killed.wait(timeout=30)
    kept = list(out.glob(".holefill-partial-*/work/done/rasterize-*-part*.npz"))
    assert len(kept) >= 6  # split tasks keep their results under file + fingerprint + part
    resumed = holefill(copc, "--out", str(out), "--resume", *settings)
    _, err = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, err
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["summary"]["resumed_tasks"] >= 6
    assert manifest["inputs"][0]["points_read"] == synthetic["points"]
    same_outputs(reference, out)


@pytest.mark.realdata
@pytest.mark.slow
def test_real_tiles_merged_into_one_copc(shared_data, tmp_path, dask_client):
    """Six adjacent IGN LiDAR HD tiles (point format 8, colour) as one COPC, split by 25 m cells."""
    tiles = sorted(str(p) for p in shared_data.glob(IGN_TILES))
    copc = tmp_path / "ign.copc.laz"
    write_copc(tiles, copc, max_node_points=5_000)
    np.testing.assert_array_equal(points_of([copc]), points_of(tiles))
    overrides = ("grid.resolution_m=0.5", "grid.cell_size_m=25", "holes.enabled=false", "flightplan.enabled=false")
    config = load_config(overrides=[*overrides, "rasterize.copc_split=true"])
    split = run_survey([str(copc)], tmp_path / "split", config, client=dask_client)
    whole = run_survey(
        [str(copc)], tmp_path / "whole", config.replace("rasterize", copc_split=False), client=dask_client
    )
    laz = run_survey(tiles, tmp_path / "laz", config, client=dask_client)
    assert split.points_read == whole.points_read == laz.points_read == sum(read_header(t).point_count for t in tiles)
    manifest = json.loads((tmp_path / "split" / "manifest.json").read_text())
    assert manifest["inputs"][0]["read_tasks"] >= 24  # 6 x 4 cells of 25 m, and the octree's top
    dsm = [read_raster(tmp_path / name / "dsm.vrt")[0] for name in ("split", "whole", "laz")]
    np.testing.assert_array_equal(dsm[0], dsm[1])
    np.testing.assert_array_equal(dsm[0], dsm[2])


def test_copc_split_setting_is_validated():
    assert load_config().rasterize.copc_split == "auto"
    assert load_config(overrides=["rasterize.copc_split=true"]).rasterize.copc_split is True
    with pytest.raises(ConfigError, match=r"rasterize.copc_split = 'yes' is invalid; expected true, false or 'auto'"):
        load_config(overrides=["rasterize.copc_split=yes"])


@pytest.mark.slow
def test_a_corrupt_top_node_loses_only_its_points_with_on_error_skip(synthetic, tmp_path, dask_client):
    """--on-error skip: the file is listed as skipped, the points its cell tasks read stay in the DSM."""
    copc = synthetic["copc"]
    plan = plan_for(copc, "grid.cell_size_m=50", "rasterize.copc_split=true")
    (top,) = [read for read in plan.reads if read.role == "top"]
    offset, _, top_points = top.nodes[0]
    broken = tmp_path / "broken.copc.laz"
    data = bytearray(Path(copc).read_bytes())
    data[offset : offset + 64] = bytes(64)  # the root node's LAZ chunk
    broken.write_bytes(bytes(data))
    summary = run([str(broken)], tmp_path / "out", dask_client, "rasterize.copc_split=true", "survey.on_error=skip")
    assert [Path(s["path"]).name for s in summary.skipped] == ["broken.copc.laz"]
    assert "COPC chunks cannot be decoded" in summary.skipped[0]["reason"]
    top_total = sum(n[2] for n in top.nodes)
    assert summary.points_read == synthetic["points"] - top_total > synthetic["points"] // 2
    dsm, _, _ = read_raster(tmp_path / "out" / "dsm.vrt")
    assert np.isfinite(dsm).mean() > 0.5  # the DSM holds the rest of the file
