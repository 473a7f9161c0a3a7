"""Tests of pipeline.synth: synthetic surveys whose holes have known causes.

Every survey here is small (well under a second to generate); the module-scoped
fixtures share the ones several tests read.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import affine
import laspy
import numpy as np
import pytest
import shapely

from pipeline.io.vector import read_layer
from pipeline.synth import (
    CLASS_BUILDING,
    CLASS_GROUND,
    CLASS_HIGH_VEGETATION,
    RIVER_BANK_HEIGHT_M,
    Buildings,
    HoleCause,
    SurfaceKind,
    SurveySpec,
    Trees,
    build_scene,
    flight_lines,
    generate_survey,
    preset,
    write_truth,
)
from pipeline.synth.pulses import WATER_EDGE_M
from pipeline.synth.scenes import cause_scene

# Default-density survey small enough for tests: 320 m x 120 m, ~300k points.
SMALL = dict(width_m=320.0, height_m=120.0, tile_size_m=80.0)


@pytest.fixture(scope="module")
def unit_survey(tmp_path_factory):
    return generate_survey(tmp_path_factory.mktemp("unit"), preset("unit"))


@pytest.fixture(scope="module")
def small_survey(tmp_path_factory):
    spec = SurveySpec(**SMALL, building_density=6.0)
    return generate_survey(tmp_path_factory.mktemp("small"), spec)


def read_points(survey):
    """Decoded points of all tiles, as one structured dict."""
    parts = [laspy.read(path) for path in survey.tiles]
    return {
        "x": np.concatenate([np.asarray(p.x) for p in parts]),
        "y": np.concatenate([np.asarray(p.y) for p in parts]),
        "z": np.concatenate([np.asarray(p.z) for p in parts]),
        "gps_time": np.concatenate([np.asarray(p.gps_time) for p in parts]),
        "classification": np.concatenate([np.asarray(p.classification) for p in parts]),
        "point_source_id": np.concatenate([np.asarray(p.point_source_id) for p in parts]),
        "return_number": np.concatenate([np.asarray(p.return_number) for p in parts]),
        "number_of_returns": np.concatenate([np.asarray(p.number_of_returns) for p in parts]),
    }


def bin_points(spec, x, y):
    """Points per truth pixel, binned on the absolute lattice as the pipeline does."""
    rows, cols = spec.shape
    col = np.floor(x / spec.resolution).astype(np.int64) - round(spec.x_min / spec.resolution)
    row = round(spec.y_max / spec.resolution) - 1 - np.floor(y / spec.resolution).astype(np.int64)
    assert col.min() >= 0 and col.max() < cols and row.min() >= 0 and row.max() < rows
    return np.bincount(row * cols + col, minlength=rows * cols).reshape(rows, cols)


def sorted_points(survey):
    points = read_points(survey)
    table = np.column_stack(
        [np.round(points[k] * 100).astype(np.int64) for k in ("x", "y", "z")]
        + [np.round((points["gps_time"] - 3e8) * 1e6).astype(np.int64), points["classification"]]
    )
    return table[np.lexsort(table.T[::-1])]


# -- files ---------------------------------------------------------------------------


def test_tiles_are_valid_laz_with_crs_and_correct_headers(unit_survey):
    spec = unit_survey.spec
    assert [p.name for p in unit_survey.tiles] == ["synth_500000_5000000.laz", "synth_500096_5000000.laz"]
    total = 0
    for path in unit_survey.tiles:
        las = laspy.read(path)
        header = las.header
        assert str(header.version) == "1.4" and header.point_format.id == 6
        assert header.point_count == len(las.points) > 0
        assert header.parse_crs().to_epsg() == 32631
        assert np.allclose(header.scales, 0.01)
        x, y, z = np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)
        assert np.allclose(header.mins, [x.min(), y.min(), z.min()])
        assert np.allclose(header.maxs, [x.max(), y.max(), z.max()])
        # every point inside its tile, named after the lower-left corner
        x0, y0 = (float(v) for v in path.stem.split("_")[1:])
        assert x.min() >= x0 and x.max() < min(x0 + spec.tile_size_m, spec.x_max)
        assert y.min() >= y0 and y.max() < min(y0 + spec.tile_size_m, spec.y_max)
        assert np.all(np.diff(las.gps_time) >= 0)
        total += len(las.points)
    assert total == unit_survey.n_points


def test_las_1_2_uncompressed(tmp_path):
    spec = preset("unit", las_version="1.2", compress=False, width_m=96.0, missed_line=None)
    survey = generate_survey(tmp_path, spec)
    assert [p.suffix for p in survey.tiles] == [".las"]
    las = laspy.read(survey.tiles[0])
    assert str(las.header.version) == "1.2" and las.header.point_format.id == 1
    assert las.header.parse_crs().to_epsg() == 32631
    assert np.abs(las.scan_angle_rank).max() <= spec.scan_angle_deg + 5
    assert np.array_equal(bin_points(spec, np.asarray(las.x), np.asarray(las.y)), survey.point_count)


def test_point_attributes_are_plausible(small_survey):
    points = read_points(small_survey)
    classes = set(np.unique(points["classification"]).tolist())
    # water (9): returns from the water's edge (pipeline.synth.pulses.WATER_EDGE_M)
    assert {CLASS_GROUND, CLASS_HIGH_VEGETATION, CLASS_BUILDING} <= classes <= {2, 5, 6, 9}
    # canopy first returns followed by ground last returns
    first, last = points["return_number"], points["number_of_returns"]
    assert np.all(first <= last) and set(np.unique(last)) == {1, 2}
    second = first == 2
    assert np.all(points["classification"][second] == CLASS_GROUND)
    assert np.count_nonzero(second) == np.count_nonzero((first == 1) & (last == 2))
    # each point comes from a flown line whose swath holds it
    lines = {line.line_id: line for line in small_survey.flight_lines}
    for line_id in np.unique(points["point_source_id"]):
        line = lines[int(line_id)]
        assert line.flown
        x = points["x"][points["point_source_id"] == line_id]
        assert np.all(np.abs(x - line.x) <= line.half_swath_m + 0.01)
        # GPS time runs along the line in the direction flown
        t = points["gps_time"][points["point_source_id"] == line_id]
        y = points["y"][points["point_source_id"] == line_id]
        assert (np.corrcoef(t, y)[0, 1] > 0.99) == line.northbound


# -- truth ---------------------------------------------------------------------------


def test_truth_shapes_and_transform(unit_survey):
    spec = unit_survey.spec
    shape = (48, 64)
    assert spec.shape == shape
    assert unit_survey.truth_dsm.shape == unit_survey.hole_cause.shape == unit_survey.point_count.shape == shape
    assert unit_survey.truth_dsm.dtype == np.float32 and unit_survey.hole_cause.dtype == np.uint8
    assert unit_survey.transform == affine.Affine(2.0, 0.0, 500_000.0, 0.0, -2.0, 5_000_096.0)
    assert unit_survey.transform @ (shape[1], shape[0]) == (spec.x_max, spec.y_min)
    assert unit_survey.crs == "EPSG:32631"
    assert np.all(np.isfinite(unit_survey.truth_dsm))
    assert np.array_equal(unit_survey.hole_mask, unit_survey.hole_cause != HoleCause.NONE)


@pytest.mark.parametrize("survey_name", ["unit_survey", "small_survey"])
def test_hole_mask_is_exactly_the_empty_pixels(survey_name, request):
    survey = request.getfixturevalue(survey_name)
    points = read_points(survey)
    count = bin_points(survey.spec, points["x"], points["y"])
    assert np.array_equal(count, survey.point_count)
    assert np.array_equal(count == 0, survey.hole_mask)
    assert count.sum() == survey.n_points


def test_every_cause_present_in_unit_preset(unit_survey):
    counts = unit_survey.cause_counts()
    # the box scenes make the first four; NO_RETURN and COVERED come from pipeline.simulate and the DTM
    simulated = (HoleCause.NONE, HoleCause.OCCLUSION, HoleCause.WATER, HoleCause.MISSED_COVERAGE)
    assert all(counts[cause] > 0 for cause in simulated), counts
    assert counts[HoleCause.NO_RETURN] == counts[HoleCause.COVERED] == 0
    assert unit_survey.n_points < 20_000


def test_missed_line_leaves_a_strip_of_missed_coverage(unit_survey):
    spec, cause = unit_survey.spec, unit_survey.hole_cause
    flown = [line for line in unit_survey.flight_lines if line.flown]
    assert len(flown) == len(unit_survey.flight_lines) - 1
    centres = (np.arange(spec.shape[1]) + 0.5) * spec.resolution
    left = centres - spec.resolution / 2
    right = centres + spec.resolution / 2
    # pixel columns entirely outside every flown swath: all holes, missed unless water
    outside = np.ones(len(centres), dtype=bool)
    for line in flown:
        outside &= (right <= line.u - line.half_swath_m) | (left >= line.u + line.half_swath_m)
    assert outside.sum() >= 10  # a real strip, 20 m at least
    strip = cause[:, outside]
    assert np.all(np.isin(strip, [HoleCause.MISSED_COVERAGE, HoleCause.WATER]))
    assert np.mean(strip == HoleCause.MISSED_COVERAGE) > 0.8
    # and missed coverage nowhere else than near the strip
    missed_columns = np.flatnonzero((cause == HoleCause.MISSED_COVERAGE).any(axis=0))
    strip_columns = np.flatnonzero(outside)
    assert missed_columns.min() >= strip_columns.min() - 1 and missed_columns.max() <= strip_columns.max() + 1


def test_water_holes_are_over_the_river(unit_survey):
    spec, river = unit_survey.spec, unit_survey.scene.river
    rows, cols = np.nonzero(unit_survey.hole_cause == HoleCause.WATER)
    u = (cols + 0.5) * spec.resolution
    v = spec.height_m - (rows + 0.5) * spec.resolution
    distance = np.abs(river.offset(u, v))
    assert np.all(distance < river.half_width + spec.resolution)
    # no point comes from well inside the water: only from its edge (WATER_EDGE_M), classified water
    points = read_points(unit_survey)
    offset = np.abs(river.offset(points["x"] - spec.x_min, points["y"] - spec.y_min))
    assert not (offset < river.half_width - WATER_EDGE_M - 0.5).any()
    assert np.all(points["classification"][offset < river.half_width - 0.5] == 9)
    # the river crosses the whole scene: water pixels in every column
    assert np.all((unit_survey.hole_cause == HoleCause.WATER).any(axis=0))
    # its outline, in CRS coordinates, holds the water pixels' centres
    polygon = unit_survey.water_polygon()
    x, y = unit_survey.transform @ (cols + 0.5, rows + 0.5)
    inside = shapely.contains_xy(polygon, x, y)
    assert inside.mean() > 0.9


def shadow_scene_survey(tmp_path):
    """Flat ground, one line over x < 140 m, a 25 m tall block west and one east of it."""
    spec = SurveySpec(
        width_m=200.0,
        height_m=60.0,
        tile_size_m=100.0,
        terrain_relief_m=0.0,
        building_density=0.0,
        tree_density=0.0,
        water=False,
        missed_line=None,
        pulse_spacing_m=0.5,
    )
    roof = 50.0 + 25.0
    buildings = Buildings.from_records(
        [
            # west of the sensor (u = 98.1): shadow on its west side
            dict(center_u=30.0, center_v=15.0, half_length=10.0, half_width=10.0, angle=0.0, eave_z=roof),
            # east of the sensor: shadow on its east side
            dict(center_u=117.5, center_v=45.0, half_length=7.5, half_width=10.0, angle=0.0, eave_z=roof),
        ]
    )
    scene = dataclasses.replace(build_scene(spec), buildings=buildings, trees=Trees.empty())
    return generate_survey(tmp_path, spec, scene=scene)


def test_buildings_cast_occlusion_on_the_side_away_from_the_sensor(tmp_path):
    survey = shadow_scene_survey(tmp_path)
    spec = survey.spec
    lines = survey.flight_lines
    assert len(lines) == 2 and lines[0].u + lines[0].half_swath_m < 210 and lines[1].u - lines[1].half_swath_m > 140
    sensor_u, sensor_z, height = lines[0].u, lines[0].sensor_z, 25.0
    occluded = survey.hole_cause == HoleCause.OCCLUSION
    assert survey.cause_counts()[HoleCause.MISSED_COVERAGE] == survey.cause_counts()[HoleCause.WATER] == 0

    def expected(edge_u, rows, east):
        # ground is hidden within height * d / (H - roof) beyond the far wall
        length = height * abs(edge_u - sensor_u) / (sensor_z - 75.0)
        full = np.zeros(spec.shape, dtype=bool)  # pixels entirely in the shadow
        near = np.zeros(spec.shape, dtype=bool)  # pixels touching it
        col = np.arange(spec.shape[1])
        if east:
            full[rows, (col >= edge_u) & (col + 1 <= edge_u + length)] = True
            near[rows, (col >= edge_u) & (col < edge_u + length)] = True
        else:
            full[rows, (col + 1 <= edge_u) & (col >= edge_u - length)] = True
            near[rows, (col + 1 <= edge_u) & (col + 1 > edge_u - length)] = True
        return full, near

    # truth rows count from the north: v in [5, 25) -> rows 35..54, v in [35, 55) -> rows 5..24
    west_full, west_near = expected(20.0, slice(35, 55), east=False)
    east_full, east_near = expected(125.0, slice(5, 25), east=True)
    assert west_full.sum() >= 6 * 20 and east_full.sum() >= 2 * 20
    assert np.all(occluded[west_full]) and np.all(occluded[east_full])
    assert not np.any(occluded & ~(west_near | east_near))
    # the roofs themselves are covered
    assert np.all(survey.point_count[35:55, 21:39] > 0) and np.all(survey.point_count[5:25, 111:124] > 0)
    west_footprint = survey.building_footprints()[0]
    assert west_footprint.bounds == pytest.approx((spec.x_min + 20, spec.y_min + 5, spec.x_min + 40, spec.y_min + 25))


def test_no_spurious_empty_pixels(small_survey, unit_survey):
    # an empty pixel that some line mostly sees would be a sampling accident
    for survey in (small_survey, unit_survey):
        fully_seen_but_empty = survey.hole_mask & (survey.visible_fraction >= 1.0)
        assert not fully_seen_but_empty.any()
    spurious = small_survey.hole_mask & (small_survey.visible_fraction >= 0.5)
    assert spurious.mean() < 0.001
    # ... and the default spacing leaves holes only for real reasons
    assert small_survey.cause_counts()[HoleCause.OCCLUSION] > 0


# -- determinism and tiling ----------------------------------------------------------


def test_deterministic_for_a_seed(tmp_path, unit_survey):
    again = generate_survey(tmp_path / "again", unit_survey.spec)
    assert np.array_equal(again.truth_dsm, unit_survey.truth_dsm)
    assert np.array_equal(again.hole_cause, unit_survey.hole_cause)
    assert np.array_equal(sorted_points(again), sorted_points(unit_survey))
    other = generate_survey(tmp_path / "other", dataclasses.replace(unit_survey.spec, seed=1))
    assert not np.array_equal(other.truth_dsm, unit_survey.truth_dsm)


def test_scene_and_points_do_not_depend_on_tiling(tmp_path):
    spec = SurveySpec(**{**SMALL, "tile_size_m": 100.0})
    big = generate_survey(tmp_path / "t100", spec)
    small = generate_survey(tmp_path / "t50", dataclasses.replace(spec, tile_size_m=50.0))
    assert len(big.tiles) < len(small.tiles)
    for name in ("truth_dsm", "hole_cause", "point_count", "visible_fraction"):
        assert np.array_equal(getattr(big, name), getattr(small, name)), name
    assert big.n_points == small.n_points
    assert np.array_equal(sorted_points(big), sorted_points(small))


def test_keep_truth_false_writes_the_same_points(tmp_path, unit_survey):
    lean = generate_survey(tmp_path, unit_survey.spec, keep_truth=False)
    assert lean.truth_dsm is None and lean.hole_cause is None and lean.hole_mask is None
    assert lean.n_points == unit_survey.n_points
    assert np.array_equal(sorted_points(lean), sorted_points(unit_survey))


def test_tiles_entirely_over_water_are_not_written(tmp_path):
    spec = preset("unit", width_m=64.0, height_m=32.0, tile_size_m=16.0, missed_line=None, water_width_m=20.0)
    scene = build_scene(spec)
    river = dataclasses.replace(scene.river, center_v=8.0, meander_amplitude=0.0)
    survey = generate_survey(tmp_path, spec, scene=dataclasses.replace(scene, river=river))
    # southern tile row (v in [0, 16)) lies under water
    assert len(survey.tiles) == 4
    assert all(path.stem.endswith("_5000016") for path in survey.tiles)
    assert np.all(survey.hole_cause[8:] == HoleCause.WATER)


def test_stale_tiles_in_the_folder_are_reported(tmp_path):
    spec = preset("unit", width_m=64.0, tile_size_m=32.0, missed_line=None)
    generate_survey(tmp_path, spec)
    with pytest.warns(UserWarning, match="not written by this survey"):
        generate_survey(tmp_path, dataclasses.replace(spec, tile_size_m=64.0))


# -- specification -------------------------------------------------------------------


def test_presets():
    assert preset("unit").resolution == 2.0
    assert preset("bench", width_m=4000.0).width_m == 4000.0
    assert preset("demo", seed=7).seed == 7
    with pytest.raises(ValueError, match="unknown preset"):
        preset("huge")


@pytest.mark.parametrize(
    "fields, message",
    [
        (dict(resolution=0.333), "resolution"),
        (dict(width_m=400.5), "width_m"),
        (dict(tile_size_m=75.5), "tile_size_m"),
        (dict(pulse_spacing_m=0.6), "too sparse"),
        (dict(las_version="1.3"), "las_version"),
        (dict(side_overlap=1.0), "side_overlap"),
        (dict(river_fall_m_per_km=-1.0), "river_fall_m_per_km"),
        (dict(river_fall_m_per_km=float("nan")), "river_fall_m_per_km"),
        (dict(lakes=-1), "lakes"),
        (dict(lakes=1.5), "lakes"),
        (dict(canal=1), "canal"),
    ],
)
def test_invalid_specs_are_rejected(fields, message):
    with pytest.raises(ValueError, match=message):
        SurveySpec(**fields)


def test_missed_line_must_leave_a_gap():
    with pytest.raises(ValueError, match="no uncovered strip"):
        flight_lines(SurveySpec(side_overlap=0.55))
    with pytest.raises(ValueError, match="does not exist"):
        flight_lines(SurveySpec(missed_line=9))
    # the default geometry: a gap of swath * (1 - 2 * overlap)
    lines = flight_lines(SurveySpec())
    gap = (lines[2].u - lines[2].half_swath_m) - (lines[0].u + lines[0].half_swath_m)
    assert gap == pytest.approx(2 * lines[0].half_swath_m * (1 - 2 * 0.3))
    assert not lines[1].flown and math.isclose(lines[1].x - lines[0].x, lines[2].x - lines[1].x)


def test_sensor_must_clear_the_scene(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(ValueError, match="flight_altitude_m"):
            generate_survey(tmp_path, preset("unit", flight_altitude_m=20.0, missed_line=None))


# -- water bodies and missed strips of the cause scenes ---------------------------------


def water_pixel_uv(survey, cause=HoleCause.WATER):
    """Local (u, v) of the centres of the truth pixels of a cause."""
    spec = survey.spec
    rows, cols = np.nonzero(survey.hole_cause == cause)
    return (cols + 0.5) * spec.resolution, spec.height_m - (rows + 0.5) * spec.resolution


@pytest.mark.parametrize("fall", [2.0, 5.0, 10.0])
def test_a_sloped_river_falls_west_to_east_with_its_banks(tmp_path, fall):
    spec = cause_scene(f"river_fall_{fall:g}")
    survey = generate_survey(tmp_path, spec)
    river = survey.scene.river
    assert river.fall == pytest.approx(fall / 1000.0)
    # the truth DSM is the water level over the water: a pixel holds the highest of its fine cells
    u, v = water_pixel_uv(survey)
    inside = np.abs(river.offset(u, v)) < river.half_width - spec.resolution
    rows, cols = np.nonzero(survey.hole_cause == HoleCause.WATER)
    level = survey.truth_dsm[rows, cols][inside]
    expected = river.level(u[inside])
    assert np.all(np.abs(level - expected) <= fall / 1000.0 * spec.resolution / 2 + 1e-4)
    slope = np.polyfit(u[inside], level, 1)[0]
    assert slope == pytest.approx(-fall / 1000.0, rel=0.01)
    # the banks follow the water: the shore is 0.3 m above the local level all along the river
    along = np.linspace(0.0, spec.width_m, 50)
    for side in (-1.0, 1.0):
        shore_v = river.centerline_v(along) + side * (river.half_width + 1e-6)
        shore = survey.scene.ground_height(along, shore_v) - river.level(along)
        assert np.allclose(shore, RIVER_BANK_HEIGHT_M, atol=1e-6)
    # the water stays under the terrain beside it everywhere
    assert np.all(river.level(along) < survey.scene.terrain.height(along, river.centerline_v(along)) - 0.99)


def test_lakes_are_water_with_a_flat_level_and_a_contour_shore(tmp_path):
    survey = generate_survey(tmp_path, cause_scene("lakes"))
    spec, scene = survey.spec, survey.scene
    lakes = scene.lakes
    assert scene.river is None and len(lakes) == 3
    assert np.all((20.0 <= 2 * lakes.semi_minor) & (2 * lakes.semi_major <= 80.0))
    # inside the extent with their banks, clear of each other's banks
    reach = lakes.reach
    assert np.all((lakes.center_u - reach >= 0) & (lakes.center_u + reach <= spec.width_m))
    assert np.all((lakes.center_v - reach >= 0) & (lakes.center_v + reach <= spec.height_m))
    gaps = np.hypot(*(np.subtract.outer(c, c) for c in (lakes.center_u, lakes.center_v))) - np.add.outer(reach, reach)
    assert np.all(gaps[~np.eye(3, dtype=bool)] >= 0)
    # every water pixel is a lake's, its truth DSM that lake's level
    u, v = water_pixel_uv(survey)
    assert len(u) > 3 * 200 / 4
    rows, cols = np.nonzero(survey.hole_cause == HoleCause.WATER)
    near = np.zeros(len(u), dtype=bool)
    for index in range(len(lakes)):
        _, radius = lakes._radial(index, u, v)
        at_lake = radius < 1.0 + spec.resolution / lakes.semi_minor[index]
        near |= at_lake
        full = radius < 1.0 - spec.resolution / lakes.semi_minor[index]
        assert np.all(survey.truth_dsm[rows[full], cols[full]] == np.float32(lakes.water_level[index]))
        # the shore is a contour line 0.3 m above the water
        ring = lakes.polygons(step_deg=4.0)[index]
        centre = np.array([lakes.center_u[index], lakes.center_v[index]])
        shore = centre + (ring - centre) * 1.0001
        heights = scene.ground_height(shore[:, 0], shore[:, 1]) - lakes.water_level[index]
        assert np.allclose(heights, RIVER_BANK_HEIGHT_M, atol=0.01)
    assert np.all(near)
    # no building or tree stands in a lake or on its shore
    waters = shapely.union_all([p for _, p in survey.water_polygons()])
    assert not any(footprint.intersects(waters) for footprint in survey.building_footprints())
    trees = shapely.points(scene.trees.center_u + spec.x_min, scene.trees.center_v + spec.y_min)
    assert not np.any(shapely.dwithin(trees, waters, scene.trees.crown_radius))
    with pytest.raises(ValueError, match="SurveySpec.lakes: only"):
        build_scene(preset("unit", lakes=20))


def test_a_canal_runs_between_quay_walls_and_rows_of_tall_houses(tmp_path):
    survey = generate_survey(tmp_path, cause_scene("canal"))
    spec, scene = survey.spec, survey.scene
    canal = scene.canal
    assert 8.0 <= 2 * canal.half_width <= 15.0 and 1.5 <= canal.quay_height <= 2.0 and 3.0 <= canal.street <= 6.0
    # water exactly over the canal, every pixel column across it water from south to north
    u, v = water_pixel_uv(survey)
    assert np.all(np.abs(u - canal.center_u) < canal.half_width + spec.resolution)
    columns = np.flatnonzero(
        np.abs((np.arange(spec.shape[1]) + 0.5) * spec.resolution - canal.center_u) < canal.half_width - 1
    )
    assert len(columns) >= 2 and np.all(survey.hole_cause[:, columns] == HoleCause.WATER)
    assert np.all(survey.truth_dsm[:, columns] == np.float32(canal.water_level))
    # quay walls: the street beside the water is flat at the quay top
    v_line = np.linspace(0.0, spec.height_m, 40)
    for side in (-1.0, 1.0):
        street_u = canal.center_u + side * (canal.half_width + canal.street / 2)
        assert np.allclose(scene.ground_height(np.full(40, street_u), v_line), canal.quay_z)
    # a row of 10-20 m houses along each quay, facades a street's width from the water
    houses = scene.buildings
    facade = np.abs(houses.center_u - canal.center_u) - houses.half_length
    row = np.isclose(facade, canal.half_width + canal.street)
    for side in (-1.0, 1.0):
        mine = row & (np.sign(houses.center_u - canal.center_u) == side)
        assert mine.sum() >= spec.height_m / 20
        height = houses.ridge_z[mine] - canal.quay_z
        assert np.all((height >= 10.0 - 1e-9) & (height <= 20.0 + 1e-9))
        # side by side along the whole quay: gaps of at most 3 m
        south, north = houses.center_v[mine] - houses.half_width[mine], houses.center_v[mine] + houses.half_width[mine]
        order = np.argsort(south)
        assert np.all(south[order][1:] - north[order][:-1] <= 3.0 + 1e-9)
        assert south.min() <= 0.0 and north.max() >= spec.height_m - 16.0
    # other buildings and trees keep out of the canal's zone
    others = ~row
    assert np.all(
        np.abs(houses.center_u[others] - canal.center_u) - houses.bounding_radius[others] > canal.flat_half_width
    )
    # the houses' scan shadows fall on the street between the facades and the water
    occluded_u, _ = water_pixel_uv(survey, HoleCause.OCCLUSION)
    on_street = np.abs(occluded_u - canal.center_u) < canal.half_width + canal.street
    assert on_street.sum() > 0
    names = [name for name, _ in survey.water_polygons()]
    assert names == ["canal"]


def test_cause_scenes_with_water_bodies_do_not_depend_on_tiling(tmp_path):
    spec = preset(
        "unit", width_m=320.0, height_m=240.0, tile_size_m=80.0, lakes=1, canal=True, river_fall_m_per_km=10.0,
        missed_line=None,
    )  # fmt: skip
    big = generate_survey(tmp_path / "t80", spec)
    small = generate_survey(tmp_path / "t48", dataclasses.replace(spec, tile_size_m=48.0))
    assert big.scene.lakes is not None and big.scene.canal is not None and big.scene.river is not None
    for name in ("truth_dsm", "hole_cause", "point_count", "visible_fraction"):
        assert np.array_equal(getattr(big, name), getattr(small, name)), name
    assert np.array_equal(sorted_points(big), sorted_points(small))
    # and any window of the scene is sampled exactly as the whole
    scene, cell = big.scene, 0.5
    whole = scene.rasterize(-20, -10, 360, 340, cell)
    part = scene.rasterize(95, 133, 77, 61, cell)
    for name in ("surface", "hard_surface", "kind", "object_index"):
        assert np.array_equal(getattr(part, name), getattr(whole, name)[143:204, 115:192]), name
    assert {SurfaceKind.WATER, SurfaceKind.BUILDING} <= set(np.unique(whole.kind))
    # the truth names every water body
    water = read_layer(write_truth(big, tmp_path / "truth")["water"], "water")
    assert list(water["name"]) == ["river", "lake 1", "canal"]
    lakes = big.scene.lakes
    assert water.geometry.iloc[1].area == pytest.approx(math.pi * lakes.semi_major[0] * lakes.semi_minor[0], rel=0.01)


def missed_strip_u(survey):
    """The local eastings (west, east) of the pixel columns outside every flown swath."""
    spec = survey.spec
    centres = (np.arange(spec.shape[1]) + 0.5) * spec.resolution
    outside = np.ones(len(centres), dtype=bool)
    for line in survey.flight_lines:
        if line.flown:
            outside &= ~line.covers(centres)
    columns = np.flatnonzero(outside)
    assert len(columns) and np.all(np.diff(columns) == 1)
    return columns[0] * spec.resolution, (columns[-1] + 1) * spec.resolution


@pytest.mark.parametrize("name, along", [("strip_across_tiles", False), ("strip_along_tile_edge", True)])
def test_missed_strips_across_tiles_and_along_a_tile_edge(tmp_path, name, along):
    survey = generate_survey(tmp_path, cause_scene(name))
    spec = survey.spec
    west, east = missed_strip_u(survey)
    assert east - west > 60.0  # a strip most of a swath wide, running the whole height
    edges = np.arange(0.0, spec.width_m + 1, spec.tile_size_m)
    inside = edges[(edges > west) & (edges < east)]
    assert len(inside) == (1 if along else 0)
    # across: it crosses every tile row inside one tile column; along: the tiles' header bounds
    # on both sides of the edge stop at the strip, so it lies between the tiles' extents
    assert spec.height_m / spec.tile_size_m >= 3
    x_west, x_east = spec.x_min + west, spec.x_min + east
    for path in survey.tiles:
        with laspy.open(path) as reader:
            x0, x1 = reader.header.mins[0], reader.header.maxs[0]
        beside = x1 <= x_west + spec.resolution or x0 >= x_east - spec.resolution
        assert beside or not along, path.name
    strip = survey.hole_cause[:, round(west / spec.resolution) : round(east / spec.resolution)]
    assert np.mean(strip == HoleCause.MISSED_COVERAGE) > 0.95
