"""Causes from the sensor's geometry on real surveys (skipped without ../shared/data)."""

from __future__ import annotations

import json

import laspy
import numpy as np
import pytest
import shapely

from pipeline.config import load_config
from pipeline.io.vector import read_layer
from pipeline.run import run_survey

pytestmark = pytest.mark.slow


def _cut_squares(src, dst, *, size: float, count: int, seed: int) -> None:
    """Remove every point in ``count`` random squares away from water-class points (a void with no cause)."""
    las = laspy.read(src)
    x, y = np.asarray(las.x), np.asarray(las.y)
    water = np.asarray(las.classification) == 9
    rng = np.random.default_rng(seed)
    keep = np.ones(len(x), bool)
    for _ in range(count):
        for _attempt in range(200):
            cx = rng.uniform(x.min() + size, x.max() - size)
            cy = rng.uniform(y.min() + size, y.max() - size)
            inside = (np.abs(x - cx) < size / 2) & (np.abs(y - cy) < size / 2)
            near = (np.abs(x - cx) < size) & (np.abs(y - cy) < size)
            if inside.sum() > 50 and not (water & near).any():
                break
        keep &= ~inside
    las.points = las.points[keep]
    las.write(dst)


@pytest.mark.parametrize(("name", "crs"), [("ahn3_delft_1", "EPSG:28992"), ("lasr_bcts_2", None)])
def test_voids_cut_into_a_real_survey_are_not_water(name, crs, shared_data, tmp_path, dask_client):
    """Squares cut out of streets, roofs and forest: seen by the lines, no water at their edge."""
    cut = tmp_path / f"{name}.laz"
    _cut_squares(shared_data / f"{name}.laz", cut, size=20.0, count=4, seed=1)
    config = load_config(overrides=[f'survey.crs="{crs}"'] if crs else [])
    out = tmp_path / "out"
    run_survey([str(cut)], out, config, client=dask_client)
    holes = read_layer(out / "holes.gpkg", "holes")
    lines = read_layer(out / "holes.gpkg", "flight_lines")
    assert lines["judged"].all() and len(lines) >= 3
    water = holes[holes["cause"] == "water"]
    assert set(water["cause_rule"]) <= {"water_ring", "water_points", "water_edge"}, water[["area_m2", "cause_rule"]]
    squares = holes[(holes["area_m2"] > 300) & (holes["area_m2"] <= 400)]  # a 20 m square less its rim's pixels
    assert len(squares) == 4, holes[["area_m2", "cause", "cause_rule"]]
    assert set(squares["cause"]) == {"no_return"}


def test_a_canal_with_water_at_its_edge_is_water(shared_data, tmp_path, dask_client):
    """AHN3 Delft: every hole with class-9 returns on its rim is water, the canal between houses too."""
    out = tmp_path / "out"
    run_survey(
        [str(shared_data / "ahn3_delft_1.laz")], out, load_config(overrides=['survey.crs="EPSG:28992"']),
        client=dask_client,
    )  # fmt: skip
    holes = read_layer(out / "holes.gpkg", "holes")
    # the canal between two rows of houses (1,118 m2 with the part the extract's east edge cuts open)
    canal = holes[holes.contains(shapely.Point(84901.5, 447488.5))]
    assert list(canal["cause"]) == ["water"], holes[["area_m2", "cause", "cause_rule"]]
    assert (holes[holes["area_m2"] >= 40]["cause"] != "occlusion").all()


def test_a_ground_model_s_voids_under_buildings_and_trees_are_covered(tmp_path, dask_client):
    """``filter.keep_classes = [2]``: the voids under the roofs and crowns the filter left out are ``covered``."""
    from pipeline.synth import generate_survey, preset

    spec = preset("demo", width_m=300.0, height_m=200.0, water=False, missed_line=None, building_density=5.0, seed=5)
    survey = generate_survey(tmp_path / "tiles", spec)
    out = tmp_path / "out"
    run_survey([str(tmp_path / "tiles")], out, load_config(overrides=["filter.keep_classes=[2]"]), client=dask_client)
    holes = read_layer(out / "holes.gpkg", "holes")
    covered = holes[holes["cause"] == "covered"]
    assert len(covered) >= 5 and covered["area_m2"].sum() > 0.5 * holes["area_m2"].sum(), holes["cause"].value_counts()
    # a covered void lies where the surface stands above the ground: a roof or a crown
    from pipeline.io.raster import geometry_mask

    raised = survey.truth_dsm - np.nanmin(survey.truth_dsm) > 3.0
    for geometry in covered.geometry:
        inside = geometry_mask(geometry, survey.transform, raised.shape)
        assert raised[inside].mean() > 0.5


def test_a_simulated_scan_with_a_missed_line_has_the_same_holes_at_any_cell_size(shared_data, tmp_path, dask_client):
    """Delft, one line dropped, single returns and no scan angles: the shadows that open onto the
    strip are part of its hole (none touches it), and the holes, causes and rules are those of one
    1000 m cell with 50 m cells (rays stop at the sight reach, whatever the window), the field of
    view from the shadows included."""
    import shapely

    from pipeline.simulate import load_terrain, random_scan_params, simulate_scan

    terrain = load_terrain("delft", shared_data)
    scan = simulate_scan(terrain, random_scan_params(15, terrain), tmp_path / "scan")
    found = {}
    for cell_m in (50, 1000):
        out = tmp_path / f"out{cell_m}"
        run_survey([str(tmp_path / "scan" / "tiles")], out, load_config(overrides=[f"grid.cell_size_m={cell_m}"]),
                   client=dask_client)  # fmt: skip
        holes = read_layer(out / "holes.gpkg", "holes")
        found[cell_m] = holes
        # its heights are assumed: the field of view comes from its shadows (flown 54, assumed 40)
        assumed = json.loads((out / "manifest.json").read_text())["holes"]["assumed_heights"]
        assert assumed["from"] == "shadows" and 46 <= assumed["field_of_view_deg"] <= 60, assumed
    strips = found[50][found[50]["cause"] == "missed_coverage"]
    assert len(strips) >= 1 and set(strips["cause_rule"]) == {"coverage_gap"}
    strip = shapely.union_all(strips.geometry.values)
    shadows = found[50][found[50]["cause"] == "occlusion"]
    shared_edge = shadows.geometry.intersection(
        strip
    ).length  # touching at a pixel's corner is no contact (4-connected)
    assert len(shadows) > 50 and not (shared_edge > 0).any(), shadows[shared_edge > 0][["area_m2", "cause_rule"]]
    keys = [
        sorted(zip(h.geometry.area.round(3), h.geometry.centroid.x.round(2), h["cause"], h["cause_rule"]))
        for h in found.values()
    ]
    assert keys[0] == keys[1]
    assert scan.n_points > 1_000_000
