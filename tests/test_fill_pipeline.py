"""Filling end to end on synthetic surveys with known ground: by cause, limits, provenance."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio

from pipeline.config import load_config
from pipeline.fill import METHOD_CODES, NOT_FILLED
from pipeline.holes.outlines import label_polygons
from pipeline.io.raster import geometry_mask, read_raster
from pipeline.io.vector import read_layer, write_layer
from pipeline.run import run_survey
from pipeline.synth import HoleCause, build_scene, generate_survey, preset, write_truth

pytestmark = pytest.mark.slow

BUILDINGS = dict(water=False, missed_line=None, building_density=5.0, seed=5)


def true_ground(spec) -> np.ndarray:
    """The scene's ground height at every pixel centre of the truth grid."""
    scene = build_scene(spec)
    rows, cols = np.indices((round(spec.height_m / spec.resolution), round(spec.width_m / spec.resolution)))
    u = (cols + 0.5) * spec.resolution
    v = spec.height_m - (rows + 0.5) * spec.resolution
    return scene.ground_height(u, v)


@pytest.fixture(scope="module")
def buildings_scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("buildings")
    spec = preset("demo", width_m=400.0, height_m=300.0, **BUILDINGS)
    survey = generate_survey(folder / "tiles", spec)
    truth = write_truth(survey, folder)
    return folder, spec, survey, truth


def run(folder, truth, client, name, *overrides, **kwargs):
    out = folder / name
    run_survey([str(folder / "tiles")], out, load_config(overrides=list(overrides)), client=client,
               aoi=truth["survey_area"], **kwargs)  # fmt: skip
    return out


def test_occlusion_holes_are_filled_with_the_hidden_ground(buildings_scene, dask_client):
    folder, spec, survey, truth = buildings_scene
    ground = true_ground(spec)
    occluded = survey.hole_cause == HoleCause.OCCLUSION
    assert occluded.sum() > 300
    errors = {}
    for by_cause in ("true", "false"):
        out = run(folder, truth, dask_client, f"out_{by_cause}", f"fill.by_cause={by_cause}")
        dsm, _, _ = read_raster(out / "dsm.vrt")
        assert np.isfinite(dsm[occluded]).all()
        errors[by_cause] = np.sqrt(np.mean((dsm[occluded] - ground[occluded]) ** 2))
    # from the low side of the rim: the street, not a ramp from the roof (issue target: 1 m)
    assert errors["true"] < 1.0, errors
    assert errors["false"] > 5.0, errors


def test_no_nodata_inside_the_survey_area_but_skipped_holes(buildings_scene, dask_client):
    folder, spec, survey, truth = buildings_scene
    out = run(folder, truth, dask_client, "out_limits", "fill.max_area_m2=50")
    dsm, transform, _ = read_raster(out / "dsm.vrt")
    with rasterio.open(out / "fill_mask.vrt") as mask:
        assert mask.nodata == NOT_FILLED and mask.dtypes[0] == "uint8"
        codes = mask.read(1)
    distance, _, _ = read_raster(out / "fill_distance.vrt")
    area = geometry_mask(read_layer(out / "holes.gpkg", "survey_area").geometry[0], transform, dsm.shape)
    holes = read_layer(out / "holes.gpkg", "holes")
    skipped = holes[holes["fill_status"] == "skipped: too large"]
    assert len(skipped) > 0 and (skipped["area_m2"] > 50).all()
    assert (holes.loc[holes["area_m2"] <= 50, "fill_status"] == "filled").all()
    in_skipped = np.zeros(dsm.shape, bool)
    for geometry in skipped.geometry:
        in_skipped |= geometry_mask(geometry, transform, dsm.shape)
    assert not (np.isnan(dsm) & area & ~in_skipped).any()
    assert np.isnan(dsm[in_skipped]).all() and (codes[in_skipped] == NOT_FILLED).all()
    filled = (codes > 0) & (codes < NOT_FILLED)
    assert filled.sum() > 0 and set(np.unique(codes[filled])) <= set(METHOD_CODES.values())
    # the codes' overviews hold codes of their tile (averaged, 0 and 4 made a 2 no pixel holds)
    for tile in sorted((out / "fill_mask").glob("*.tif")):
        with rasterio.open(tile) as full, rasterio.open(tile, overview_level=0) as overview:
            assert set(np.unique(overview.read(1))) <= set(np.unique(full.read(1))), tile.name
    assert (distance[codes == 0] == 0).all() and (distance[filled] > 0).all()
    assert np.isfinite(dsm[codes == 0]).all()
    # the holes layer says how each hole was filled, in metres
    done = holes[holes["fill_status"] == "filled"]
    assert done["fill_method"].notna().all() and (done["fill_max_distance_m"] > 0).all()


def test_water_is_filled_flat(tmp_path, dask_client):
    spec = preset("demo", width_m=300.0, height_m=200.0, missed_line=None, building_density=0.0, seed=7)
    survey = generate_survey(tmp_path / "tiles", spec)
    truth = write_truth(survey, tmp_path)
    water = survey.hole_cause == HoleCause.WATER
    polygons = label_polygons(water.astype(np.int32), survey.transform)
    write_layer(tmp_path / "water.gpkg", "water", [{"id": 1}], [polygons[1].buffer(1.0)], crs_wkt=spec.crs)
    out = run(tmp_path, truth, dask_client, "out", water=tmp_path / "water.gpkg")
    holes = read_layer(out / "holes.gpkg", "holes")
    river = holes[holes["cause"] == "water"]
    assert len(river) == 1 and river["fill_method"].iloc[0] == "flat"
    dsm, _, _ = read_raster(out / "dsm.vrt")
    assert np.isfinite(dsm[water]).all()
    assert np.ptp(dsm[water]) == 0.0  # hydro-flattened: one height


def test_run_plans_flights_for_the_missed_strip_only(tmp_path, dask_client):
    import json

    spec = preset("demo", width_m=400.0, height_m=300.0, water=False, seed=3)
    survey = generate_survey(tmp_path / "tiles", spec)
    truth = write_truth(survey, tmp_path)
    out = run(tmp_path, truth, dask_client, "out")
    holes = read_layer(out / "holes.gpkg", "holes")
    strips = holes[holes["cause"] == "missed_coverage"]
    assert len(strips) >= 1 and (holes["cause"] == "occlusion").any()
    # missed coverage is not invented: left nodata for the re-flight
    assert (strips["fill_status"] == "skipped: missed coverage").all()
    status = read_layer(out / "flightplan.gpkg", "holes_status")
    planned = set(status.loc[status["planned"], "hole_id"])
    assert planned == set(strips.loc[strips["area_m2"] >= 25, "hole_id"])
    for suffix in ("plan", "waypoints", "kmz", "kml"):
        assert list(out.glob(f"flightplan*.{suffix}")), suffix
    lanes = read_layer(out / "flightplan.gpkg", "flight_lines")
    lane_holes = {int(h) for ids in lanes["hole_ids"] for h in str(ids).split(",") if h}
    assert lane_holes == planned
    # the synthetic survey is flown north-south: the strip's lanes are too, beside the flown lines
    assert all(min(a % 180, 180 - a % 180) < 2.0 for a in strips["azimuth_deg"])
    assert all(min(a % 180, 180 - a % 180) < 2.0 for a in lanes["azimuth_deg"])
    plan = json.loads(next(out.glob("flightplan*.plan")).read_text())
    assert plan["mission"]["items"][0]["command"] == 22
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["flightplan"]["holes_planned"] == len(planned)
    assert sorted(manifest["outputs"]["flightplan"]) == sorted(p.name for p in out.glob("flightplan*"))
