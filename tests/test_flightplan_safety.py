"""Flight plans a pilot accepts (issue 17): take-off on open ground, straight lanes, clearance, durations."""

from __future__ import annotations

import json
import math
import zipfile

import laspy
import numpy as np
import pytest
import scipy.ndimage as ndi
import shapely
from affine import Affine

from pipeline.flightplan import CoverageParams, FlightParams, HoleInput, plan_mission
from pipeline.flightplan.takeoff import TakeoffParams, check_home, choose_takeoff, disc_filter, open_ground
from pipeline.flightplan.takeoff_search import BoxGrid, GroundGrid
from pipeline.io.vector import read_layer

PARAMS = CoverageParams(
    altitude_agl_m=50.0, fov_deg=60.0, side_overlap=0.3, run_in_m=15.0, turnaround_m=8.0, margin_m=4.0
)
CRS_2154 = "EPSG:2154"
SIZE = 1200
TRANSFORM = Affine(1, 0, 0.0, 0, -1, float(SIZE))  # x 0..1200, y 0..1200, 1 m pixels


def _xy():
    cols, rows = np.meshgrid(np.arange(SIZE) + 0.5, np.arange(SIZE) + 0.5)
    return cols, SIZE - rows


def _forest():
    """Gently sloping ground under 25 m canopy everywhere but a clearing around (250, 900)."""
    x, y = _xy()
    ground = 100.0 + 0.01 * x
    clearing = np.hypot(x - 250.0, y - 900.0) < 40.0
    dsm = np.where(clearing, ground + 0.2, ground + 25.0).astype(float)
    return dsm, ground, clearing


def _independent_least_clearance(sortie, dsm, radius_m=3.0):
    """Brute force: points every 0.5 m along each leg against every pixel within the radius."""
    least = math.inf
    x, y = _xy()
    for a, b in zip(sortie.waypoints[:-1], sortie.waypoints[1:]):
        n = max(2, int(math.dist((a.x, a.y), (b.x, b.y)) / 0.5) + 1)
        for f in np.linspace(0.0, 1.0, n):
            px, py, h = a.x + f * (b.x - a.x), a.y + f * (b.y - a.y), a.height_m + f * (b.height_m - a.height_m)
            c0, c1 = max(0, int(px - radius_m) - 1), min(SIZE, int(px + radius_m) + 2)
            r0, r1 = max(0, int(SIZE - py - radius_m) - 1), min(SIZE, int(SIZE - py + radius_m) + 2)
            near = np.hypot(x[r0:r1, c0:c1] - px, y[r0:r1, c0:c1] - py) <= radius_m
            if near.any():
                least = min(least, float(h - dsm[r0:r1, c0:c1][near].max()))
    return least


def test_home_in_a_forest_is_the_clearing_at_the_ground_points_height():
    dsm, ground, clearing = _forest()
    hole = shapely.box(600, 600, 800, 640)
    dsm[int(SIZE - 640) : int(SIZE - 600), 600:800] = np.nan
    params = FlightParams(coverage=PARAMS, min_area_m2=0.0)
    plan = plan_mission(
        [HoleInput(1, hole, "missed_coverage", hole.area)],
        dsm,
        TRANSFORM,
        crs_wkt=CRS_2154,
        params=params,
        ground=GroundGrid(ground),
    )
    hx, hy = plan.home
    assert math.hypot(hx - 250.0, hy - 900.0) < 40.0 - params.takeoff.clear_radius_m + 1.0  # inside the clearing
    assert plan.home_ground_m == pytest.approx(100.0 + 0.01 * hx, abs=0.5)  # the ground, not the 25 m canopy
    assert plan.home_source == "ground points" and plan.home_warning == ""
    for w in plan.sorties[0].waypoints:
        assert w.altitude_m == pytest.approx(w.height_m - plan.home_ground_m)


def test_open_ground_farther_than_a_pilot_walks_from_the_holes_is_not_sought():
    """The clearing lies 1 km from the hole: beyond ``TAKEOFF_MAX_M`` the search does not go (it
    reads windows around the holes, not the survey's span); the home comes from the DSM, with a warning."""
    from pipeline.flightplan.takeoff_search import TAKEOFF_MAX_M

    dsm, ground, _ = _forest()
    hole = shapely.box(1100, 100, 1150, 140)
    dsm[int(SIZE - 140) : int(SIZE - 100), 1100:1150] = np.nan
    assert hole.distance(shapely.Point(250.0, 900.0)) > 2 * TAKEOFF_MAX_M
    plan = plan_mission(
        [HoleInput(1, hole, "missed_coverage", hole.area)],
        dsm,
        TRANSFORM,
        crs_wkt=CRS_2154,
        params=FlightParams(coverage=PARAMS, min_area_m2=0.0),
        ground=GroundGrid(ground),
        snap_home=True,
    )
    assert plan.home_source == "DSM (no ground points)"
    assert "no open ground" in plan.home_warning
    # with no hole to re-fly there is no take-off to seek, and nothing to warn of
    nothing = plan_mission(
        [HoleInput(1, hole, "missed_coverage", hole.area)],
        dsm,
        TRANSFORM,
        crs_wkt=CRS_2154,
        params=FlightParams(coverage=PARAMS, min_area_m2=10 * hole.area),
        ground=GroundGrid(ground),
        snap_home=True,
    )
    assert not nothing.sorties and nothing.home_warning == ""


def test_of_two_clusters_of_holes_the_take_off_is_the_open_ground_nearest_to_either():
    """Holes near the clearing and holes 1 km away: two search windows, the clearing wins."""
    dsm, ground, clearing = _forest()
    near, far = shapely.box(330, 880, 360, 900), shapely.box(1100, 100, 1150, 140)
    for box in (near, far):
        x0, y0, x1, y1 = (int(v) for v in box.bounds)
        dsm[SIZE - y1 : SIZE - y0, x0:x1] = np.nan
    plan = plan_mission(
        [HoleInput(1, near, "missed_coverage", near.area), HoleInput(2, far, "missed_coverage", far.area)],
        dsm,
        TRANSFORM,
        crs_wkt=CRS_2154,
        params=FlightParams(coverage=PARAMS, min_area_m2=0.0),
        ground=GroundGrid(ground),
    )
    hx, hy = plan.home
    assert math.hypot(hx - 250.0, hy - 900.0) < 40.0
    assert plan.home_source == "ground points"


@pytest.mark.parametrize("radius", [0.0, 1.0, 2.5, 4.0, 7.3, 10.0])
def test_the_disc_filter_is_scipy_s_footprint_filter_with_a_disc(radius):
    """Row by row, the same extremes as the footprint filter: NaN-free floats with infinities, both edge modes, bytes."""
    rng = np.random.default_rng(int(radius * 10))
    values = rng.normal(size=(37, 53))
    values[rng.random(values.shape) < 0.1] = np.inf
    values[rng.random(values.shape) < 0.1] = -np.inf
    r = int(math.floor(radius))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    disc = xx * xx + yy * yy <= radius * radius + 1e-9
    for mode, cval in (("nearest", 0.0), ("constant", np.inf), ("constant", -np.inf)):
        got = disc_filter(values, radius, maximum=True, mode=mode, cval=cval)
        np.testing.assert_array_equal(got, ndi.maximum_filter(values, footprint=disc, mode=mode, cval=cval))
        got = disc_filter(values, radius, maximum=False, mode=mode, cval=cval)
        np.testing.assert_array_equal(got, ndi.minimum_filter(values, footprint=disc, mode=mode, cval=cval))
    wet = (rng.random(values.shape) < 0.02).astype(np.uint8)
    got = disc_filter(wet, radius, maximum=True, mode="constant", cval=0)
    np.testing.assert_array_equal(got, ndi.maximum_filter(wet, footprint=disc, mode="constant", cval=0))


def test_open_ground_excludes_obstacles_water_slopes_and_voids():
    dsm = np.full((100, 100), 10.0)
    ground = np.full((100, 100), 10.0)
    water = np.zeros((100, 100))
    transform = Affine(1, 0, 0, 0, -1, 100)
    params = TakeoffParams()
    assert open_ground(dsm, ground, water, transform, params=params)[50, 50]
    tree = dsm.copy()
    tree[55, 55] = 15.0
    assert not open_ground(tree, ground, water, transform, params=params)[50, 50]
    wet = water.copy()
    wet[58, 50] = 3
    assert not open_ground(dsm, ground, wet, transform, params=params)[50, 50]
    void = dsm.copy()
    void[45, 45] = np.nan
    assert not open_ground(void, ground, water, transform, params=params)[50, 50]
    steep = 10.0 + 0.2 * np.arange(100)[None, :] + np.zeros((100, 1))  # 11 degrees
    assert not open_ground(steep, steep, water, transform, params=params)[50, 50]


@pytest.mark.parametrize("seed", range(6))
def test_take_off_searched_in_growing_boxes_is_the_whole_grid_search(seed):
    """choose_takeoff's growing boxes pick the pixel one search over the whole grid picks: the
    open-ground pixel nearest the holes, ties to the nearest to their centre (obstacles, water
    and voids scattered at random; open ground near, far or nowhere)."""
    rng = np.random.default_rng(seed)
    shape = (420, 700)  # blocks of 256 pixels: whole ones and cut ones at both edges
    ground = 50.0 + rng.normal(0, 0.02, shape)
    dsm = ground.copy()
    crowded = [0.0, 0.02, 0.2, 0.6, 0.9, 1.0][seed]  # share of pixels under a 5 m obstacle
    dsm[rng.random(shape) < crowded / 30] += 5.0  # one obstacle pixel blocks a 10 m disc
    dsm[rng.random(shape) < 0.001] = np.nan
    water = (rng.random(shape) < 0.0005).astype(np.int32)
    targets = np.zeros(shape, bool)
    r, c = rng.integers(100, 300, 2)
    targets[r : r + 15, c : c + 40] = True
    transform = Affine(0.5, 0, 1000, 0, -0.5, 2000)
    params = TakeoffParams()
    found = choose_takeoff(dsm, ground, water, transform, targets, params=params)
    fit = open_ground(dsm, ground, water, transform, params=params)
    if not fit.any():
        assert found is None
        return
    rows, cols = np.nonzero(targets)
    distance = ndi.distance_transform_edt(~targets)
    offset = np.hypot(np.arange(shape[0])[:, None] - rows.mean(), np.arange(shape[1])[None, :] - cols.mean())
    score = np.where(fit, np.round(distance) * (1 + dsm.size) + offset / (1 + offset.max()), np.inf)
    br, bc = np.unravel_index(int(np.argmin(score)), shape)
    assert found is not None
    assert found.xy == (1000 + 0.5 * (bc + 0.5), 2000 - 0.5 * (br + 0.5))
    assert found.ground_m == ground[br, bc]


def test_a_box_grid_reads_and_writes_as_an_array_does():
    """The ground grids of a take-off hold only the boxes read: the same values as a full array."""
    rng = np.random.default_rng(3)
    grid, array = BoxGrid((50, 60), np.nan), np.full((50, 60), np.nan)
    for _ in range(6):
        r0, c0 = rng.integers(0, 45, 2)
        r1, c1 = r0 + rng.integers(1, 20), c0 + rng.integers(1, 20)
        values = rng.normal(size=(min(r1, 50) - r0, min(c1, 60) - c0))
        grid[r0:r1, c0:c1], array[r0:r1, c0:c1] = values, values
    assert np.array_equal(grid[:, :], array, equal_nan=True)
    assert np.array_equal(grid[5:33, 40:90], array[5:33, 40:90], equal_nan=True)
    assert grid.shape == array.shape
    r, c = np.argwhere(np.isfinite(array))[0]
    assert grid[int(r), int(c)] == array[r, c] and np.isnan(grid[49, 59]) == np.isnan(array[49, 59])


def test_a_chosen_home_on_a_canopy_is_kept_with_its_ground_height_and_a_warning():
    dsm, ground, _ = _forest()
    takeoff = check_home(dsm, ground, TRANSFORM, (700.5, 300.5), params=TakeoffParams())
    assert takeoff.xy == (700.5, 300.5)
    assert takeoff.ground_m == pytest.approx(107.005, abs=0.01)
    assert "roof or canopy" in takeoff.warning and "25.0 m" in takeoff.warning


def _hill_and_tower():
    x, y = _xy()
    dsm = 50.0 + 80.0 * np.exp(-((x - 600.0) ** 2 + (y - 600.0) ** 2) / (2 * 120.0**2))
    dsm[(np.abs(x - 300.0) < 1.5) & (np.abs(y - 450.0) < 1.5)] = 140.0  # a 90 m tower on the way
    return dsm


def test_every_leg_clears_the_hill_and_the_tower_by_the_minimum():
    dsm = _hill_and_tower()
    holes = [shapely.box(550, 560, 700, 600), shapely.box(900, 300, 960, 420)]
    params = FlightParams(coverage=PARAMS, min_area_m2=0.0)
    plan = plan_mission(
        [HoleInput(i + 1, h, "missed_coverage", h.area) for i, h in enumerate(holes)],
        dsm,
        TRANSFORM,
        crs_wkt=CRS_2154,
        params=params,
        home=(150.0, 300.0),
    )
    for sortie in plan.sorties:
        least = _independent_least_clearance(sortie, dsm)
        assert least >= params.min_clearance_m
        assert sortie.least_clearance_m == pytest.approx(least, abs=1.5)  # pixels vs samples


def test_a_tower_on_the_transit_leg_is_cleared_by_the_minimum():
    """The tower stands on the leg from take-off to the first lane (placed there from a first plan):
    the leg climbs over it by the minimum, checked point by point against the pixels within 3 m."""
    x, y = _xy()
    dsm = 50.0 + 0.0 * x
    hole = shapely.box(900, 800, 1000, 840)
    params = FlightParams(coverage=PARAMS, min_area_m2=0.0)
    plan_kwargs = dict(crs_wkt=CRS_2154, params=params, home=(150.0, 200.0))
    first = plan_mission([HoleInput(1, hole, "missed_coverage", hole.area)], dsm, TRANSFORM, **plan_kwargs)
    a, b = first.sorties[0].waypoints[:2]
    tx, ty = (a.x + b.x) / 2, (a.y + b.y) / 2
    tower = (np.abs(x - tx) < 1.5) & (np.abs(y - ty) < 1.5)
    dsm = np.where(tower, 150.0, dsm)  # 100 m above the ground, on the leg
    plan = plan_mission([HoleInput(1, hole, "missed_coverage", hole.area)], dsm, TRANSFORM, **plan_kwargs)
    (sortie,) = plan.sorties
    near_tower = [w for w in sortie.waypoints if math.dist((w.x, w.y), (tx, ty)) < math.dist((a.x, a.y), (b.x, b.y))]
    assert near_tower  # the same route: the leg passes the tower
    least = _independent_least_clearance(sortie, dsm)
    assert least >= params.min_clearance_m
    assert _independent_least_clearance(sortie, np.where(tower, dsm, -np.inf)) >= params.min_clearance_m
    assert _independent_least_clearance(sortie, np.where(tower, dsm, -np.inf)) < 60.0  # the tower was in reach


def test_a_plan_below_the_minimum_clearance_is_refused_naming_the_leg():
    dsm = _hill_and_tower()
    hole = shapely.box(550, 560, 700, 600)
    params = FlightParams(coverage=PARAMS, min_area_m2=0.0, min_clearance_m=55.0)
    with pytest.raises(ValueError, match=r"sortie 1, leg \d+ .* by \d+\.\d m < flightplan.min_clearance_m = 55"):
        plan_mission(
            [HoleInput(1, hole, "missed_coverage", hole.area)],
            dsm,
            TRANSFORM,
            crs_wkt=CRS_2154,
            params=params,
            home=(150.0, 300.0),
        )


def test_lanes_on_a_slope_are_one_inclined_line_within_the_gradient():
    x, _ = _xy()
    dsm = 100.0 + 0.3 * x  # a 17 degree slope, lanes along it
    hole = shapely.box(400, 590, 800, 610)
    params = FlightParams(coverage=PARAMS, min_area_m2=0.0, max_climb_gradient=0.15)
    plan = plan_mission(
        [HoleInput(1, hole, "missed_coverage", hole.area, azimuth_deg=90.0)],
        dsm,
        TRANSFORM,
        crs_wkt=CRS_2154,
        params=params,
        home=(300.0, 600.0),
    )
    lane = [w for w in plan.sorties[0].waypoints if w.actions[0] in ("lane_start", "lane_end")]
    (a, b) = lane[:2]
    gradient = abs(b.height_m - a.height_m) / math.dist((a.x, a.y), (b.x, b.y))
    assert gradient == pytest.approx(0.15, abs=1e-3)
    assert not any("terrain" in w.actions for w in plan.sorties[0].waypoints)
    assert _independent_least_clearance(plan.sorties[0], dsm) >= params.min_clearance_m


def test_durations_include_turns_and_speed_changes():
    dsm = np.full((SIZE, SIZE), 40.0)
    hole = shapely.box(500, 400, 700, 560)  # several lanes
    holes = [HoleInput(1, hole, "missed_coverage", hole.area)]

    def duration(acceleration):
        params = FlightParams(coverage=PARAMS, min_area_m2=0.0, acceleration_m_s2=acceleration, setup_time_s=0)
        plan = plan_mission(holes, dsm, TRANSFORM, crs_wkt=CRS_2154, params=params, home=(300.0, 300.0))
        return plan.sorties[0].duration_s, len(plan.sorties[0].lanes)

    slow, lanes = duration(2.0)
    fast, _ = duration(1e9)
    turn = 2 * math.sqrt(2) * 6.0 / 2.0  # two right-angle corners at 6 m/s and 2 m/s2
    assert lanes >= 3
    assert slow - fast >= (lanes - 1) * turn * 0.9


def test_demo_take_off_on_the_ground_clearance_and_continuous_turns(tmp_path):
    from click.testing import CliRunner

    from pipeline.cli import main

    out = tmp_path / "demo"
    result = CliRunner().invoke(main, ["demo", "--out", str(out)])
    assert result.exit_code == 0, result.output
    plan = json.loads((out / "manifest.json").read_text())["flightplan"]
    assert plan["sorties"] >= 1 and plan["home_height_from"] == "ground points"
    hx, hy = plan["home"]
    z = []
    for tile in (out / "survey" / "tiles").glob("*.laz"):
        las = laspy.read(tile)
        near = (np.hypot(las.x - hx, las.y - hy) < 2.0) & (las.classification == 2)
        z.append(np.asarray(las.z[near]))
    assert abs(np.median(np.concatenate(z)) - plan["home_ground_m"]) < 1.0
    assert all(c >= 20.0 for c in plan["sortie_min_clearance_m"])
    route = read_layer(out / "flightplan.gpkg", "route")
    assert (route["min_clearance_m"] >= 20.0).all()
    kmz = next(out.glob("flightplan*.kmz"))
    with zipfile.ZipFile(kmz) as z_:
        wpml = z_.read("wpmz/waylines.wpml").decode()
    assert "toPointAndPassWithContinuityCurvature" in wpml and "Stop" not in wpml


@pytest.mark.parametrize("seed", range(8))
def test_take_off_windows_labelled_by_box_groups_are_the_whole_grid_labelling(seed):
    """The take-off windows come from the holes' clusters labelled within their areas' boxes
    (not over the span): the same windows as one labelling of the whole grid, touching and
    overlapping areas, clusters that join across boxes and areas far apart included."""
    from pipeline.flightplan.takeoff_search import area_boxes, merged_boxes, rasterize_areas, target_windows

    rng = np.random.default_rng(seed)
    shape, transform = (600, 900), Affine(1.0, 0, 0, 0, -1.0, 600)
    areas = []
    for _ in range(rng.integers(2, 9)):
        x, y = rng.uniform(0, 880), rng.uniform(0, 580)
        w, h = rng.uniform(2, 120), rng.uniform(2, 60)
        areas.append(shapely.affinity.rotate(shapely.box(x, y, x + w, y + h), rng.uniform(0, 90)))
    targets = rasterize_areas(areas, shape, transform)
    reach = int(rng.integers(3, 60))
    labels, _ = ndi.label(targets)
    whole = [
        [max(sl[0].start - reach, 0), max(sl[1].start - reach, 0),
         min(sl[0].stop + reach, shape[0]), min(sl[1].stop + reach, shape[1])]
        for sl in ndi.find_objects(labels) if sl is not None
    ]  # fmt: skip
    grouped = target_windows(targets, reach, area_boxes(areas, shape, transform))
    assert grouped == merged_boxes(whole)  # the merge is shared: the labelling is what differs


@pytest.mark.parametrize("seed", range(6))
def test_the_take_off_s_targets_held_by_area_are_the_whole_grid_mask(seed):
    """AreaMask: any slice (and the mean target pixel) as the whole grid's mask gives it, overlapping,
    rotated and far-apart areas and areas off the grid included, without that mask."""
    from pipeline.flightplan.takeoff_search import AreaMask, _mean_pixel, rasterize_areas

    rng = np.random.default_rng(100 + seed)
    shape, transform = (500, 700), Affine(1.0, 0, 0, 0, -1.0, 500)
    areas = []
    for _ in range(rng.integers(1, 8)):
        x, y = rng.uniform(-50, 690), rng.uniform(-50, 490)
        w, h = rng.uniform(1, 150), rng.uniform(1, 80)
        areas.append(shapely.affinity.rotate(shapely.box(x, y, x + w, y + h), rng.uniform(0, 90)))
    whole = rasterize_areas(areas, shape, transform)
    held = AreaMask(areas, shape, transform)
    assert held.shape == shape
    for _ in range(30):
        r0, c0 = int(rng.integers(0, shape[0])), int(rng.integers(0, shape[1]))
        r1, c1 = int(rng.integers(r0, shape[0] + 20)), int(rng.integers(c0, shape[1] + 20))
        assert np.array_equal(held[r0:r1, c0:c1], whole[r0:r1, c0:c1])
    assert np.array_equal(held[:, :], whole)
    rows, cols = np.nonzero(whole)
    expected = (float(rows.mean()), float(cols.mean())) if len(rows) else None
    assert _mean_pixel(held, held.boxes) == expected


def test_a_window_of_a_surface_reads_what_the_window_array_holds():
    """WindowOf: pixels and slices (clipped at the window's edges, empty ones included) as the
    window cut from the surface gives them; outside the window, an error, not a wrap-around."""
    from pipeline.flightplan.takeoff_search import WindowOf

    rng = np.random.default_rng(5)
    surface = rng.normal(size=(120, 90))
    surface[rng.random(surface.shape) < 0.1] = np.nan
    box = (17, 9, 101, 70)
    window, view = surface[17:101, 9:70], WindowOf(surface, box)
    assert view.shape == window.shape and view.size == window.size
    for _ in range(50):
        a, b = sorted(int(v) for v in rng.integers(-5, 95, 2))
        c, d = sorted(int(v) for v in rng.integers(-5, 70, 2))
        a, c = max(a, 0), max(c, 0)
        assert np.array_equal(view[a:b, c:d], window[a:b, c:d], equal_nan=True)
    assert np.array_equal(view[:, :], window, equal_nan=True)
    r, c = 40, 33
    assert np.array_equal(view[r, c], window[r, c], equal_nan=True)
    with pytest.raises(IndexError):
        view[-1, 0]


@pytest.mark.parametrize("density", [0.0005, 0.01, 0.2, 0.7])
def test_the_take_off_s_rounded_distances_are_scipy_s(density):
    """rounded_distance: the whole-pixel distance to the nearest target, as scipy's EDT rounded, on
    random windows (single rows and columns, sparse and dense targets, a window with none)."""
    from pipeline.flightplan.takeoff_search import rounded_distance

    rng = np.random.default_rng(int(density * 1e4))
    for _ in range(80):
        shape = tuple(int(n) for n in rng.integers(1, 70, 2))
        targets = rng.random(shape) < density
        if not targets.any():
            assert np.isinf(rounded_distance(targets)).all()
            targets[rng.integers(shape[0]), rng.integers(shape[1])] = True
        expected = np.round(ndi.distance_transform_edt(~targets)).astype(np.float32)
        assert np.array_equal(rounded_distance(targets), expected)


@pytest.mark.parametrize("seed", range(4))
def test_area_pixels_are_the_areas_pixel_centres(seed):
    """A box's pixels whose centres lie in an area: the centres tested one by one on a grid of each
    (rotated areas, a DSM whose pixels are not 1 m, a box outside the area, an empty box)."""
    from pipeline.flightplan.takeoff_search import _area_pixels

    rng = np.random.default_rng(seed)
    transform = Affine(0.5, 0, 1000.0, 0, -0.5, 2000.0)
    area = shapely.affinity.rotate(shapely.box(1010, 1960, 1010 + rng.uniform(3, 20), 1975), rng.uniform(0, 90))
    for box in [(0, 0, 120, 110), (10, 15, 60, 70), (100, 100, 110, 110), (5, 5, 5, 9)]:
        r0, c0, r1, c1 = box
        rows, cols = np.mgrid[r0:r1, c0:c1]
        x, y = transform.a * (cols + 0.5) + transform.c, transform.e * (rows + 0.5) + transform.f
        expected = shapely.contains_xy(area, x, y)
        got = _area_pixels(area, box, transform)
        assert got.shape == (r1 - r0, c1 - c0) and np.array_equal(got, expected)
    assert _area_pixels(area, (0, 0, 120, 110), transform).any()
