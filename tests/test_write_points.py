"""Repaired point clouds (``output.points``): originals untouched, one synthetic point per filled pixel."""

from __future__ import annotations

import json
from pathlib import Path

import laspy
import numpy as np
import pytest
import rasterio

from pipeline.config import load_config
from pipeline.errors import ConfigError
from pipeline.fill import NOT_FILLED
from pipeline.run import run_survey
from pipeline.stages.write_points import nearest_tile, output_names
from pipeline.synth import generate_survey, preset, write_truth

pytestmark = pytest.mark.slow


def filled_pixels(out: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, rasterio.Affine]:
    """Rows, cols and DSM heights of the filled pixels of a run, with the DSM transform."""
    with rasterio.open(out / "fill_mask.vrt") as mask, rasterio.open(out / "dsm.vrt") as dsm:
        codes, heights, transform = mask.read(1), dsm.read(1), dsm.transform
    rows, cols = np.nonzero((codes > 0) & (codes < NOT_FILLED))
    return rows, cols, heights[rows, cols], transform


def check_repaired(out: Path, inputs: list[Path]) -> int:
    """Every property of the repaired clouds that does not depend on the survey; returns the fill points."""
    rows, cols, heights, transform = filled_pixels(out)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["outputs"]["points"] == [f"points/{p.stem}.laz" for p in inputs]
    added_rows, added_cols, added_z = [], [], []
    for path in inputs:
        original, repaired = laspy.read(path), laspy.read(out / "points" / f"{path.stem}.laz")
        assert repaired.header.version == original.header.version
        assert repaired.point_format.id == original.point_format.id
        assert list(repaired.point_format.dimension_names) == list(original.point_format.dimension_names)
        assert np.array_equal(repaired.header.scales, original.header.scales)
        assert np.array_equal(repaired.header.offsets, original.header.offsets)
        assert repaired.header.parse_crs() == original.header.parse_crs()
        n = len(original)
        for name in original.point_format.dimension_names:  # originals copied unchanged, field by field
            assert np.array_equal(np.asarray(repaired[name][:n]), np.asarray(original[name])), name
        new = repaired.points[n:]
        assert (np.asarray(new.synthetic) == 1).all() and (np.asarray(new.classification) == 1).all()
        assert (np.asarray(new.return_number) == 1).all() and (np.asarray(new.number_of_returns) == 1).all()
        assert repaired.header.point_count == len(repaired)
        by_return = np.bincount(np.asarray(repaired.return_number), minlength=16)[1:16]
        assert np.array_equal(repaired.header.number_of_points_by_return[: len(by_return)], by_return)
        assert np.allclose(repaired.header.mins, [repaired.x.min(), repaired.y.min(), repaired.z.min()])
        r, c = rasterio.transform.rowcol(transform, np.asarray(new.x), np.asarray(new.y))
        added_rows.append(np.asarray(r)), added_cols.append(np.asarray(c)), added_z.append(np.asarray(new.z))
    r, c, z = np.concatenate(added_rows), np.concatenate(added_cols), np.concatenate(added_z)
    # one point per filled pixel, none twice, none lost
    assert len(r) == len(rows)
    assert set(zip(r.tolist(), c.tolist())) == set(zip(rows.tolist(), cols.tolist()))
    # z is the repaired DSM's height at the pixel (to the file's z scale)
    heights_at = dict(zip(zip(rows.tolist(), cols.tolist()), heights.tolist()))
    expected = np.array([heights_at[key] for key in zip(r.tolist(), c.tolist())])
    assert np.abs(z - expected).max() <= 0.006
    return len(r)


def check_rerun(out: Path, tmp_path: Path, client, *overrides: str) -> None:
    """holefill on the repaired clouds without filling has data wherever the first run filled, at its heights."""
    rows, cols, heights, transform = filled_pixels(out)
    again = tmp_path / "rerun"
    config = load_config(overrides=["fill.enabled=false", *overrides])
    run_survey([str(out / "points")], again, config, client=client)
    with rasterio.open(again / "dsm.vrt") as dsm:
        x, y = rasterio.transform.xy(transform, rows, cols)
        r, c = rasterio.transform.rowcol(dsm.transform, x, y)
        values = dsm.read(1, masked=True)[np.asarray(r), np.asarray(c)]
    assert not np.ma.getmaskarray(values).any()
    assert np.abs(values.filled(np.nan) - heights).max() <= 0.006


def crop_east(path: Path, metres: float) -> None:
    """Drop a tile's points in its eastern strip: a gap between tile bounds, inside the survey area."""
    cloud = laspy.read(path)
    cloud.points = cloud.points[np.asarray(cloud.x) < cloud.header.maxs[0] - metres]
    cloud.write(path)


def test_repaired_clouds_of_a_synthetic_survey(tmp_path, dask_client):
    spec = preset("demo", width_m=200.0, height_m=200.0, missed_line=None, building_density=4.0, seed=11)
    survey = generate_survey(tmp_path / "tiles", spec)
    truth = write_truth(survey, tmp_path)
    tiles = sorted((tmp_path / "tiles").glob("*.laz"))
    crop_east(tiles[0], 4.0)
    before = {p: p.read_bytes() for p in tiles}
    out = tmp_path / "out"
    # the cut strip is missed coverage, left for the re-flight by default: filled on request here
    config = load_config(overrides=["output.points=true", "fill.missed_coverage=true"])
    run_survey([str(tmp_path / "tiles")], out, config, client=dask_client, aoi=truth["survey_area"])
    assert {p: p.read_bytes() for p in before} == before  # inputs never modified
    added = check_repaired(out, tiles)
    assert added > 500
    # the gap's pixels lie in no tile's bounds; each went to the nearest tile, none lost (check_repaired)
    header = laspy.open(tiles[0]).header
    first = laspy.read(out / "points" / tiles[0].name)
    assert (np.asarray(first.x[header.point_count :]) > header.maxs[0]).sum() > 50
    check_rerun(out, tmp_path, dask_client)


def test_repaired_cloud_of_a_real_file(shared_data, tmp_path, dask_client):
    path = shared_data / "ign_crop2_water.laz"  # 12 extra-byte dimensions, water
    out = tmp_path / "out"
    overrides = ["grid.resolution_m=0.5", "grid.cell_size_m=16"]
    run_survey([str(path)], out, load_config(overrides=["output.points=true", *overrides]), client=dask_client)
    assert check_repaired(out, [path]) > 100
    check_rerun(out, tmp_path, dask_client, *overrides)


def test_repaired_clouds_of_adjacent_real_tiles(shared_data, tmp_path, dask_client):
    """Six IGN tiles sharing edges (pixel centres on them: ties) and a gap east of the first one."""
    paths = sorted(shared_data.glob("ign_tile_*.laz"))
    out = tmp_path / "out"
    overrides = ["grid.resolution_m=0.5", "grid.cell_size_m=50", "grid.align=center"]
    run_survey([str(p) for p in paths], out, load_config(overrides=["output.points=true", *overrides]),
               client=dask_client)  # fmt: skip
    assert check_repaired(out, paths) > 100
    check_rerun(out, tmp_path, dask_client, *overrides)


def test_fill_points_go_back_to_the_tile_crs(shared_data, tmp_path, dask_client):
    """With --target-crs the DSM is in the target CRS; the added points are in the tile's own CRS."""
    from pyproj import Transformer

    path = shared_data / "lasr_bcts_1.laz"  # NAD83 / BC Albers, LAS 1.2, point format 1
    out = tmp_path / "utm"
    config = load_config(overrides=["output.points=true", 'survey.target_crs="EPSG:26909"'])
    run_survey([str(path)], out, config, client=dask_client)
    rows, cols, heights, transform = filled_pixels(out)
    original, repaired = laspy.open(path).header, laspy.read(out / "points" / path.name)
    assert repaired.header.parse_crs() == original.parse_crs()
    new = repaired.points[original.point_count :]
    assert len(new) == len(rows) > 100
    x, y = Transformer.from_crs(original.parse_crs(), "EPSG:26909", always_xy=True).transform(new.x, new.y)
    r, c = rasterio.transform.rowcol(transform, x, y)
    assert set(zip(np.asarray(r).tolist(), np.asarray(c).tolist())) == set(zip(rows.tolist(), cols.tolist()))
    heights_at = dict(zip(zip(rows.tolist(), cols.tolist()), heights.tolist()))
    expected = np.array([heights_at[key] for key in zip(np.asarray(r).tolist(), np.asarray(c).tolist())])
    assert np.abs(np.asarray(new.z) - expected).max() <= 0.006


def test_points_need_filling():
    with pytest.raises(ConfigError, match="output.points"):
        load_config(overrides=["output.points=true", "fill.enabled=false"])


def test_each_pixel_goes_to_the_nearest_tile_first_in_order_on_ties():
    bounds = np.array([[0, 0, 10, 10], [10, 0, 20, 10], [5, 5, 15, 15], [30, 0, 40, 10]], float)
    x = np.array([5.0, 10.0, 12.0, 25.5, 24.0, 50.0])
    y = np.array([5.0, 5.0, 12.0, 5.0, 5.0, 5.0])
    # inside one; on the shared edge (first wins); inside 1 and 2 overlap... 12,12 is in 2 only;
    # in the gap: nearer to tile 3, nearer to tile 1; far east: tile 3
    assert nearest_tile(x, y, bounds, block=2).tolist() == [0, 0, 2, 3, 1, 3]


def test_output_names_keep_stems_apart():
    assert output_names(["a/t1.laz", "b/t2.las", "c/t1.laz"]) == ["t1_1", "t2", "t1_2"]
