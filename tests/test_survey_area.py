"""The survey area from the tile grid, end to end (issue #8): missed lines between tiles, missing and skipped tiles."""

from __future__ import annotations

import re
import shutil

import numpy as np
import pytest
import shapely

from pipeline.config import load_config
from pipeline.io.raster import geometry_mask
from pipeline.io.vector import list_layers, read_layer
from pipeline.run import run_survey
from pipeline.synth import HoleCause, generate_survey, preset

pytestmark = pytest.mark.slow

#: Synthetic truth on the survey's grid: pin the pixel size and the area rule.
SYNTHETIC = ["grid.resolution_m=2", "holes.min_area_m2=8"]
#: 1 pulse per m2 at 2 m pixels: small surveys, quick runs.
SPARSE = dict(resolution=2.0, pulse_spacing_m=1.0)


def run(tiles, out, client, *overrides):
    run_survey([str(tiles)], out, load_config(overrides=[*SYNTHETIC, *overrides]), client=client)
    return read_layer(out / "holes.gpkg", "holes")


def test_a_line_missed_along_a_tile_boundary_is_a_missed_coverage_hole(tmp_path, dask_client):
    # 50 m tiles: the missed line's strip (x 207..295 m) straddles the tile edge at x = 250 m, so the
    # header bounds of the tiles beside it stop at the strip: it lies between the tiles' extents
    spec = preset("demo", width_m=400.0, height_m=300.0, tile_size_m=50.0, water=False, seed=3, **SPARSE)
    survey = generate_survey(tmp_path / "tiles", spec)
    strip = survey.hole_cause == HoleCause.MISSED_COVERAGE
    assert strip.sum() * 4.0 > 20_000
    holes = run(tmp_path / "tiles", tmp_path / "out", dask_client)
    missed = holes[holes["cause"] == "missed_coverage"]
    assert len(missed) == 1, holes[["area_m2", "cause", "cause_rule"]]
    found = geometry_mask(missed.geometry.iloc[0], survey.transform, strip.shape)
    assert (found & strip).sum() / (found | strip).sum() > 0.95
    area = read_layer(tmp_path / "out" / "holes.gpkg", "survey_area")
    assert area["source"].iloc[0] == "tile grid squares (50)"
    # ... and a re-flight is planned over it
    status = read_layer(tmp_path / "out" / "flightplan.gpkg", "holes_status")
    assert set(status.loc[status["planned"], "hole_id"]) == {int(missed["hole_id"].iloc[0])}
    # the same holes with other cells (the gaps' pixels are a function of the global position only)
    other = run(tmp_path / "tiles", tmp_path / "cells64", dask_client, "grid.cell_size_m=64")
    assert hole_masks(other, survey) == hole_masks(holes, survey)
    # with the tile extents (the behaviour before), the strip vanished
    before = run(tmp_path / "tiles", tmp_path / "before", dask_client, "survey.area=footprint")
    assert (before.loc[before["cause"] == "missed_coverage", "area_m2"] < 1000).all()


def hole_masks(holes, survey) -> list[tuple]:
    shape = survey.hole_cause.shape
    return sorted(
        (tuple(np.flatnonzero(geometry_mask(g, survey.transform, shape))), round(a, 3), c)
        for g, a, c in zip(holes.geometry, holes["area_m2"], holes["cause"])
    )


@pytest.fixture(scope="module")
def three_by_three(tmp_path_factory):
    """A 300 m x 300 m survey in 100 m tiles, every line flown."""
    folder = tmp_path_factory.mktemp("grid3x3")
    spec = preset("demo", width_m=300.0, height_m=300.0, tile_size_m=100.0, water=False, missed_line=None, **SPARSE)
    survey = generate_survey(folder / "tiles", spec)
    middle = folder / "tiles" / "synth_500100_5000100.laz"
    assert middle.exists()
    return folder, survey, middle


def middle_square(survey) -> np.ndarray:
    return geometry_mask(shapely.box(500_100, 5_000_100, 500_200, 5_000_200), survey.transform, survey.hole_cause.shape)


def test_a_missing_tile_inside_the_grid_is_missed_coverage(three_by_three, tmp_path, dask_client):
    folder, survey, middle = three_by_three
    tiles = tmp_path / "tiles"
    shutil.copytree(folder / "tiles", tiles, ignore=shutil.ignore_patterns(middle.name))
    # 50 m cells: four cells hold no tile, planned for the survey area alone
    holes = run(tiles, tmp_path / "out", dask_client, "grid.cell_size_m=50")
    square = middle_square(survey)
    hole = holes[holes["cause_rule"] == "missing_tile"]
    assert len(hole) == 1 and (hole["cause"] == "missed_coverage").all(), holes[["area_m2", "cause", "cause_rule"]]
    found = geometry_mask(hole.geometry.iloc[0], survey.transform, square.shape)
    assert (found & square).sum() / (found | square).sum() > 0.95
    assert (holes["cause"] != "unknown").all()


def test_a_corrupt_tile_is_skipped_exterior_never_an_unknown_hole(three_by_three, tmp_path, dask_client):
    folder, survey, middle = three_by_three
    tiles = tmp_path / "tiles"
    shutil.copytree(folder / "tiles", tiles)
    data = (tiles / middle.name).read_bytes()
    (tiles / middle.name).write_bytes(data[: len(data) // 2])  # the header reads, the points do not decode
    for mode, out in (("auto", tmp_path / "out"), ("footprint", tmp_path / "extents")):
        holes = run(tiles, out, dask_client, "survey.on_error=skip", f"survey.area={mode}")
        square = middle_square(survey)
        inside = [geometry_mask(g, survey.transform, square.shape)[square].sum() for g in holes.geometry]
        assert max(inside, default=0) == 0, (mode, holes[["area_m2", "cause", "cause_rule"]])
        assert (holes["cause"] != "unknown").all() or holes.loc[holes["cause"] == "unknown", "area_m2"].max() < 100
        gpkg = out / "holes.gpkg"
        area = read_layer(gpkg, "survey_area")
        skipped = area[area["status"] == "skipped"]
        assert list(skipped["source"]) == [middle.name]
        assert skipped.geometry.iloc[0].equals(shapely.box(500_100, 5_000_100, 500_200, 5_000_200)) or mode != "auto"
        assert not area.geometry.iloc[0].intersection(skipped.geometry.iloc[0]).area > 0
        tile_rows = read_layer(gpkg, "tiles")
        assert tile_rows.loc[tile_rows["name"] == middle.name, "status"].tolist() == ["skipped"]
        assert "survey_area" in list_layers(gpkg)


def test_a_tile_whose_header_cannot_be_read_is_placed_by_its_name(three_by_three, tmp_path, dask_client):
    folder, survey, middle = three_by_three
    tiles = tmp_path / "tiles"
    shutil.copytree(folder / "tiles", tiles)
    (tiles / middle.name).write_bytes(b"not a las file at all")  # skipped at the scan: no bounds
    holes = run(tiles, tmp_path / "out", dask_client, "survey.on_error=skip")
    square = middle_square(survey)
    assert all(geometry_mask(g, survey.transform, square.shape)[square].sum() == 0 for g in holes.geometry)
    assert (holes["cause_rule"] != "missing_tile").all()
    area = read_layer(tmp_path / "out" / "holes.gpkg", "survey_area")
    skipped = area[area["status"] == "skipped"]
    assert len(skipped) == 1 and skipped.geometry.iloc[0].equals(shapely.box(500_100, 5_000_100, 500_200, 5_000_200))


@pytest.mark.realdata
def test_data_stopping_short_of_its_square_is_missed_coverage(shared_data, tmp_path, dask_client):
    """IGN's six 50 m tiles: one tile's data stops 8.3 m short of its square's east edge.

    Roofs stand beside the strip, but it lies in a delivered tile's square outside every
    tile's extent: missed coverage (rule ``missing_tile``), not an occlusion.
    """
    names = sorted(p for p in shared_data.glob("ign_tile_770*.laz"))
    out = tmp_path / "out"
    run_survey([str(p) for p in names], out, load_config(), client=dask_client)
    holes = read_layer(out / "holes.gpkg", "holes")
    # besides the strip, voids wider across than 4 point spacings (0.8 m here) are listed since
    # issue 21: a 2 x 2 m scan shadow beside a roof
    others = holes[holes["cause"] != "missed_coverage"]
    assert len(holes) - len(others) == 1 and (others["cause"] == "occlusion").all() and (others["area_m2"] <= 10).all()
    hole = holes[holes["cause"] == "missed_coverage"].iloc[0]
    assert (hole["cause"], hole["cause_rule"]) == ("missed_coverage", "missing_tile")
    xmin, _, xmax, _ = hole.geometry.bounds
    assert 770541 <= xmin and xmax <= 770551 and 300 <= hole["area_m2"] <= 420


def test_planned_area_beyond_the_tiles_is_missed_coverage(shared_data, tmp_path, dask_client):
    """A 50 m tile inside a 150 m --aoi: the planned area without data is one hole, missed coverage."""
    import geopandas as gpd

    tile = shared_data / "ign_tile_77055_627760.laz"
    x0, y0 = 770550.0, 6277550.0  # the tile's lower-left corner (its header)
    aoi = tmp_path / "aoi.gpkg"
    gpd.GeoDataFrame(geometry=[shapely.box(x0 - 50, y0 - 50, x0 + 100, y0 + 100)], crs="EPSG:2154").to_file(aoi)
    out = tmp_path / "out"
    run_survey([str(tile)], out, load_config(), aoi=str(aoi), client=dask_client)
    holes = read_layer(out / "holes.gpkg", "holes")
    planned = holes[holes["area_m2"] > 1000]
    assert len(planned) == 1, holes[["area_m2", "cause", "cause_rule"]]
    assert planned.iloc[0]["cause"] == "missed_coverage"
    assert planned.iloc[0]["area_m2"] == pytest.approx(150**2 - 50**2, rel=0.01)


def _one_lake(folder, monkeypatch, *, lake_m: float, scene_m: float):
    """The cause scene ``lakes`` with one lake ``lake_m`` across in a square of ``scene_m``, a few trees."""
    from pipeline.synth import draw
    from pipeline.synth.scenes import cause_scene

    monkeypatch.setattr(draw, "LAKE_SIZE_M", (lake_m, lake_m))
    base = cause_scene("lakes")
    spec = base.__class__(**{
        **base.__dict__, "width_m": scene_m, "height_m": scene_m, "lakes": 1, "building_density": 0.0,
        "tree_density": 5.0, "missed_line": None,
    })  # fmt: skip
    return spec, generate_survey(folder, spec)


def _lake_level(spec, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Where the scene's water is on the DSM's pixels, and its true level there."""
    from pipeline.synth import build_scene

    rows, cols = np.indices(shape)
    return build_scene(spec).water_level((cols + 0.5) * spec.resolution, spec.height_m - (rows + 0.5) * spec.resolution)


def test_tiles_left_out_over_a_lake_are_water_filled_at_its_level(tmp_path, dask_client, monkeypatch):
    """A lake wider than a tile: the delivery leaves out the tiles nothing came back from.

    Their squares are rimmed by the lake's own water returns (``water_ring`` before
    ``missing_tile``), so they are water, filled flat at the lake's level, and the DSM is
    written over the cells that hold no point at all (before: ``missed_coverage`` /
    ``missing_tile``, nodata awaiting a re-flight over open water).
    """
    from pipeline.io.raster import read_raster

    spec, survey = _one_lake(tmp_path / "tiles", monkeypatch, lake_m=300.0, scene_m=420.0)
    names = {p.name for p in (tmp_path / "tiles").glob("*.laz")}
    assert len(names) < 25  # some tiles over the lake returned nothing and were not written
    holes = run(tmp_path / "tiles", tmp_path / "out", dask_client, "grid.cell_size_m=100")
    assert (holes["cause"] == "water").all(), holes[["area_m2", "cause", "cause_rule"]]
    dsm, _, _ = read_raster(tmp_path / "out" / "dsm.vrt")
    is_water, level = _lake_level(spec, dsm.shape)
    voids = is_water & (survey.hole_cause == HoleCause.WATER)
    assert voids.sum() > 15_000
    assert np.isfinite(dsm[voids]).all()  # every void on the lake holds a height, in cells without a point too
    assert np.abs(dsm[voids] - level[voids]).max() < 0.02
    # the same hole and heights with other cells: the level is read from the same water returns
    other = run(tmp_path / "tiles", tmp_path / "cells250", dask_client, "grid.cell_size_m=250")
    assert hole_masks(other, survey) == hole_masks(holes, survey)
    assert list(other["fill_note"]) == list(holes["fill_note"])
    assert np.array_equal(read_raster(tmp_path / "cells250" / "dsm.vrt")[0], dsm, equal_nan=True)


@pytest.mark.parametrize("limit_px", [60 * 60, 25 * 25])
def test_a_lake_wider_than_a_fill_window_is_filled_over_a_coarser_lattice(tmp_path, dask_client, monkeypatch, limit_px):
    """A water hole whose window is over ``MAX_WINDOW_PX`` (here made small: the lake's 4.6 ha
    window) is filled over coarse pixels and painted into its own pixels: every pixel of the
    lake holds a height at its level, as the window filled whole gives it."""
    from pipeline.io.raster import read_raster
    from pipeline.stages import fill_holes

    spec, survey = _one_lake(tmp_path / "tiles", monkeypatch, lake_m=150.0, scene_m=250.0)
    whole = run(tmp_path / "tiles", tmp_path / "whole", dask_client)
    monkeypatch.setattr(fill_holes, "MAX_WINDOW_PX", limit_px)
    coarse = run(tmp_path / "tiles", tmp_path / "coarse", dask_client)
    lake = coarse[coarse["cause"] == "water"]
    assert len(lake) == 1 and lake["fill_status"].iloc[0] == "filled", coarse[["area_m2", "cause", "fill_status"]]
    factor = int(re.search(r"filled over (\d+) x", lake["fill_note"].iloc[0]).group(1))
    assert factor >= (2 if limit_px == 60 * 60 else 3)
    assert "filled over" not in " ".join(whole["fill_note"].fillna(""))
    dsm, _, _ = read_raster(tmp_path / "coarse" / "dsm.vrt")
    reference, _, _ = read_raster(tmp_path / "whole" / "dsm.vrt")
    is_water, level = _lake_level(spec, dsm.shape)
    voids = is_water & (survey.hole_cause == HoleCause.WATER)
    assert voids.sum() > 3_000
    assert np.isfinite(dsm[voids]).all()
    assert np.abs(dsm[voids] - level[voids]).max() < 0.02
    assert np.abs(dsm[voids] - reference[voids]).max() < 0.01
    # the other pixels are the same: measured, or filled by their own (small) holes' tasks
    others = ~voids
    assert np.array_equal(dsm[others], reference[others], equal_nan=True)
