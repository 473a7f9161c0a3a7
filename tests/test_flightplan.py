"""Flight-plan kernels: coverage, lane direction, route improvement, sorties, heights."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import shapely
from affine import Affine

from pipeline.errors import CRSError
from pipeline.flightplan import (
    CoverageParams,
    FlightParams,
    HoleInput,
    cluster_holes,
    greedy_route,
    improve_route,
    lane_sections,
    pattern_ends,
    plan_mission,
    plan_pattern,
    route_length,
    split_sorties,
    swath_width,
)
from pipeline.flightplan.altitude import ellipsoid_transformer, vertical_crs_for
from pipeline.flightplan.route import sortie_duration

PARAMS = CoverageParams(
    altitude_agl_m=50.0, fov_deg=60.0, side_overlap=0.3, run_in_m=15.0, turnaround_m=8.0, margin_m=4.0
)
CRS_2154 = "EPSG:2154"


def _random_holes(rng, n, extent=3000.0):
    holes = []
    for _ in range(n):
        x, y = rng.uniform(0, extent, 2)
        box = shapely.box(x, y, x + rng.uniform(10, 250), y + rng.uniform(4, 60))
        holes.append(shapely.affinity.rotate(box, rng.uniform(0, 180)))
    return holes


def _covered(lanes, spacing_m):
    """Union of lanes buffered by half the effective swath (+1 mm: adjacent bands touch exactly,
    and the float rounding of their shared edge would leave zero-area cracks)."""
    return shapely.union_all([lane.line().buffer(spacing_m / 2 + 1e-3) for lane in lanes])


def _flat_dsm(height=40.0, size=4000, origin=(-500.0, 3500.0)):
    return np.full((size, size), height, dtype=np.float32), Affine(1, 0, origin[0], 0, -1, origin[1])


def test_swath_and_spacing_follow_the_formula():
    assert swath_width(50, 60) == pytest.approx(2 * 50 * math.tan(math.radians(30)))
    assert PARAMS.spacing_m == pytest.approx(PARAMS.swath_m * 0.7)
    with pytest.raises(ValueError, match="fov_deg"):
        swath_width(50, 180)


@pytest.mark.parametrize("seed", range(6))
def test_every_hole_is_covered_by_its_lanes(seed):
    rng = np.random.default_rng(seed)
    for hole in _random_holes(rng, 20):
        pattern = plan_pattern(hole, params=PARAMS)
        covered = _covered(pattern.lanes, pattern.spacing_m)
        assert covered.contains(hole)
        assert covered.contains(pattern.rectangle.buffer(-1e-6))


def test_lanes_are_parallel_to_the_rectangle_long_side():
    hole = shapely.affinity.rotate(shapely.box(0, 0, 300, 40), 33, origin=(0, 0))
    pattern = plan_pattern(hole, params=PARAMS)
    rect = shapely.minimum_rotated_rectangle(hole.buffer(PARAMS.margin_m))
    coords = np.asarray(rect.exterior.coords)
    sides = [coords[1] - coords[0], coords[2] - coords[1]]
    long_side = max(sides, key=np.linalg.norm)
    long_azimuth = math.degrees(math.atan2(long_side[0], long_side[1])) % 180
    for lane in pattern.lanes:
        assert lane.azimuth_deg % 180 == pytest.approx(long_azimuth, abs=1e-6)
    assert pattern.azimuth_deg == pytest.approx((90 - 33) % 180, abs=1e-6)
    # far fewer lanes than an axis-aligned box would need
    assert len(pattern.lanes) <= math.ceil((40 + 2 * PARAMS.margin_m) / PARAMS.spacing_m)


def test_an_imposed_azimuth_sets_the_lanes_and_still_covers():
    hole = shapely.box(0, 0, 200, 30)
    pattern = plan_pattern(hole, params=PARAMS, azimuth_deg=45.0)
    assert all(lane.azimuth_deg % 180 == pytest.approx(45.0) for lane in pattern.lanes)
    covered = _covered(pattern.lanes, pattern.spacing_m)
    assert covered.contains(hole)


def test_lanes_extend_by_the_run_in():
    pattern = plan_pattern(shapely.box(0, 0, 100, 10), params=PARAMS)
    for lane in pattern.lanes:
        assert lane.length_m == pytest.approx(100 + 2 * PARAMS.margin_m + 2 * PARAMS.run_in_m)


def test_holes_closer_than_one_spacing_merge():
    spacing = PARAMS.spacing_m
    a = shapely.box(0, 0, 50, 10)
    b = shapely.box(0, 10 + 0.5 * spacing, 50, 20 + 0.5 * spacing)
    c = shapely.box(0, 1000, 50, 1010)
    assert cluster_holes([a, b, c], spacing) == [[0, 1], [2]]
    far = shapely.box(0, 10 + 1.5 * spacing, 50, 20 + 1.5 * spacing)
    assert cluster_holes([a, far], spacing) == [[0], [1]]


@pytest.mark.parametrize("seed", range(8))
def test_improved_route_is_never_longer_than_greedy(seed):
    rng = np.random.default_rng(100 + seed)
    patterns = [plan_pattern(h, params=PARAMS, pattern_id=i) for i, h in enumerate(_random_holes(rng, 25))]
    ends = [pattern_ends(p) for p in patterns]
    home = (1500.0, 1500.0)
    greedy = greedy_route(ends, home)
    improved = improve_route(greedy, ends, home)
    assert sorted(v.pattern for v in improved) == list(range(len(patterns)))
    assert route_length(improved, ends, home) <= route_length(greedy, ends, home) + 1e-9


def test_reversed_variant_swaps_entry_and_exit():
    pattern = plan_pattern(shapely.box(0, 0, 200, 90), params=PARAMS)
    ends = pattern_ends(pattern)
    assert len(pattern.lanes) > 1 and len(ends.entries) == 4
    for v, w in enumerate(ends.reverse):
        assert ends.entries[w] == pytest.approx(ends.exits[v])
        assert ends.exits[w] == pytest.approx(ends.entries[v])


def test_sorties_stay_under_the_time_limit_and_keep_every_pattern():
    rng = np.random.default_rng(7)
    patterns = [plan_pattern(h, params=PARAMS, pattern_id=i) for i, h in enumerate(_random_holes(rng, 30))]
    ends = [pattern_ends(p) for p in patterns]
    home = (1500.0, 1500.0)
    route = improve_route(greedy_route(ends, home), ends, home)
    limit = 900.0
    sorties = split_sorties(
        route, ends, home, lane_speed_m_s=5, transit_speed_m_s=12, setup_time_s=60, max_flight_time_s=limit
    )
    assert len(sorties) > 1
    assert sorted(v.pattern for s in sorties for v in s) == list(range(len(patterns)))
    for visits in sorties:
        assert sortie_duration(visits, ends, home, 5, 12, 60) <= limit


def test_mission_lists_occluded_holes_with_the_reason_and_respects_the_limit():
    rng = np.random.default_rng(3)
    geoms = _random_holes(rng, 24, extent=2500)
    holes = [HoleInput(i + 1, g, "occlusion" if i % 5 == 0 else "missed_coverage", g.area) for i, g in enumerate(geoms)]
    dsm, transform = _flat_dsm()
    params = FlightParams(coverage=PARAMS, max_flight_time_s=700.0, min_area_m2=0.0)
    plan = plan_mission(holes, dsm, transform, crs_wkt=CRS_2154, params=params, home=(1200.0, 1200.0))
    occluded = [d for d in plan.decisions if d.cause == "occlusion"]
    assert occluded and all(not d.planned and "occlusion" in d.reason for d in occluded)
    assert all(d.planned for d in plan.decisions if d.cause == "missed_coverage")
    assert len(plan.sorties) > 1
    assert all(s.duration_s <= 700.0 for s in plan.sorties)
    assert plan.improved_length_m <= plan.greedy_length_m + 1e-9
    flown = {h for s in plan.sorties for fl in s.lanes for h in fl.hole_ids}
    assert flown == {d.hole_id for d in plan.decisions if d.planned}
    for s in plan.sorties:  # every sortie starts and ends at home
        assert (s.waypoints[0].x, s.waypoints[0].y) == pytest.approx((1200.0, 1200.0))
        assert (s.waypoints[-1].x, s.waypoints[-1].y) == pytest.approx((1200.0, 1200.0))


def test_a_pattern_too_long_for_one_sortie_is_cut_into_parts():
    hole = shapely.box(0, 0, 1500, 600)
    dsm, transform = _flat_dsm()
    params = FlightParams(coverage=PARAMS, max_flight_time_s=600.0, min_area_m2=0.0)
    plan = plan_mission(
        [HoleInput(1, hole, "missed_coverage", hole.area)],
        dsm,
        transform,
        crs_wkt=CRS_2154,
        params=params,
        home=(750.0, -100.0),
    )
    assert len(plan.sorties) > 1 and all(s.duration_s <= 600.0 for s in plan.sorties)
    lanes = [fl.lane for s in plan.sorties for fl in s.lanes]
    covered = _covered(lanes, PARAMS.spacing_m)
    assert covered.contains(hole)


def test_lane_heights_follow_the_highest_surface_under_the_swath():
    dsm, transform = _flat_dsm(10.0, size=400, origin=(0.0, 400.0))
    # a 30 m building 20 m beside the lane, inside the swath: it sets the height
    dsm[195:205, 150:170] = 30.0
    sections = lane_sections(dsm, transform, (0.0, 220.0), (400.0, 220.0), half_width_m=25.0, terrain_step_m=5.0)
    assert len(sections) == 3
    assert [round(s.surface_max_m) for s in sections] == [10, 30, 10]
    assert sections[1].start[0] <= 150 and sections[1].end[0] >= 170
    # outside the swath it does not count
    far = lane_sections(dsm, transform, (0.0, 300.0), (400.0, 300.0), half_width_m=25.0, terrain_step_m=5.0)
    assert [round(s.surface_max_m) for s in far] == [10]


def test_waypoint_heights_clear_the_surface_by_the_agl():
    dsm, transform = _flat_dsm(20.0)
    dsm[:, 1500:1550] = 45.0  # a ridge from x = 1000 to 1050, across the hole
    hole = shapely.box(800, 1000, 1300, 1040)
    params = FlightParams(coverage=PARAMS, min_area_m2=0.0)
    plan = plan_mission(
        [HoleInput(1, hole, "missed_coverage", hole.area)],
        dsm,
        transform,
        crs_wkt=CRS_2154,
        params=params,
        home=(700.0, 900.0),
    )
    waypoints = plan.sorties[0].waypoints
    assert plan.home_ground_m == pytest.approx(20.0)
    for w in waypoints:
        assert w.altitude_m == pytest.approx(w.height_m - 20.0)  # relative to take-off
    scanning = [w for w in waypoints if w.lane_index is not None]
    assert min(w.height_m for w in scanning) >= 20.0 + PARAMS.altitude_agl_m - 1e-6
    assert max(w.height_m for w in scanning) == pytest.approx(45.0 + PARAMS.altitude_agl_m)
    # one straight line per lane: the ridge raises the whole lane, no waypoint follows it
    assert not any("terrain" in w.actions for w in waypoints)
    for index in {w.lane_index for w in scanning}:
        lane = [w.height_m for w in scanning if w.lane_index == index and w.actions[0].startswith("lane")]
        assert max(lane) - min(lane) < 1e-6


def test_known_point_lambert93_origin_is_3e_46_5n():
    # Lambert-93 (EPSG:2154) is defined with its origin (700000, 6600000) at 3 deg E, 46.5 deg N
    dsm, transform = _flat_dsm(100.0, size=800, origin=(699600.0, 6600400.0))
    hole = shapely.box(700000, 6600000, 700100, 6600020)
    plan = plan_mission(
        [HoleInput(1, hole, "missed_coverage", hole.area)],
        dsm,
        transform,
        crs_wkt=CRS_2154,
        params=FlightParams(coverage=PARAMS, min_area_m2=0.0),
        home=(700000.0, 6600000.0),
    )
    assert plan.home_lonlat == pytest.approx((3.0, 46.5), abs=1e-9)
    assert plan.sorties[0].waypoints[0].lon == pytest.approx(3.0, abs=1e-9)
    assert plan.sorties[0].waypoints[0].lat == pytest.approx(46.5, abs=1e-9)


def test_ellipsoidal_heights_are_refused_without_the_geoid_grid_or_correct_with_it():
    crs = vertical_crs_for("EPSG:2154", "EPSG:5720")  # NGF-IGN69 heights
    paris = (652000.0, 6862000.0)
    try:
        convert = ellipsoid_transformer(crs, probe=paris)
    except CRSError as e:
        assert "geoid grid" in str(e) and "takeoff" in str(e)
        return
    # with the grid (RAF18), the ellipsoidal height in Paris is about 44 m above the IGN69 height
    h = convert(np.array([paris[0]]), np.array([paris[1]]), np.array([100.0]))[0]
    assert 40.0 < h - 100.0 < 50.0


def test_a_crs_without_vertical_datum_is_refused_for_ellipsoidal_heights():
    with pytest.raises(CRSError, match="vertical"):
        ellipsoid_transformer(vertical_crs_for("EPSG:2154", ""), probe=(652000.0, 6862000.0))


def test_flightplan_kernels_import_no_io_library():
    code = (
        "import sys, pipeline.flightplan; "
        "bad = [m for m in ('rasterio', 'pyogrio', 'geopandas', 'laspy', 'dask') if m in sys.modules]; "
        "print(','.join(bad))"
    )
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == "", f"pipeline.flightplan imports {loaded}"


def test_a_lane_over_a_void_wider_than_its_swath_flies_above_the_surface_beside_it():
    """A missed strip 200 m wide: no DSM under the lane's 40 m corridor; the lane clears what stands beside the strip."""
    from pipeline.flightplan.altitude import lane_line

    dsm = np.full((400, 600), 20.0)
    dsm[:, 200:400] = np.nan  # the strip, x 200-400 m (1 m pixels)
    dsm[50:60, 150:160] = 35.0  # a house on the west bank
    dsm[300:310, 420:430] = 28.0  # and one on the east bank
    transform = Affine(1.0, 0.0, 0.0, 0.0, -1.0, 400.0)
    first, last = lane_line(
        dsm, transform, (300.0, 0.0), (300.0, 400.0),
        half_width_m=20.0, altitude_agl_m=50.0, max_gradient=0.1, slope_gain_m=5.0,
    )  # fmt: skip
    assert first == last == pytest.approx(35.0 + 50.0)  # the highest beside the strip, the lane level
    with pytest.raises(ValueError, match="no DSM height"):
        lane_line(
            np.full((10, 10), np.nan), transform, (0.0, 0.0), (5.0, 5.0),
            half_width_m=2.0, altitude_agl_m=50.0, max_gradient=0.1, slope_gain_m=5.0,
        )  # fmt: skip


def test_patterns_are_placed_neighbour_after_neighbour():
    """The DSM's blocks are cached while they fit: the patterns are visited in Z order of their centres."""
    from pipeline.flightplan.mission import _z_order

    rng = np.random.default_rng(5)
    corners = [(0, 0), (0, 9000), (9000, 0), (9000, 9000)]
    points, cluster = [], []
    for k, (x, y) in enumerate(corners):
        for _ in range(6):
            points.append(shapely.Point(x + rng.uniform(0, 500), y + rng.uniform(0, 500)))
            cluster.append(k)
    shuffled = rng.permutation(len(points))
    order = _z_order([points[i] for i in shuffled])
    visited = [cluster[shuffled[i]] for i in order]
    assert sorted(order) == list(range(len(points)))
    # each corner's patterns in one run, whatever order they came in
    runs = [visited[0]] + [b for a, b in zip(visited, visited[1:]) if a != b]
    assert sorted(runs) == [0, 1, 2, 3]
    assert _z_order([]) == [] and _z_order([shapely.Point(1, 2)]) == [0]
