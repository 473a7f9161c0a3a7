"""The sensor's geometry on small synthetic scans: trajectory sums and fit, swaths, lines of sight."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.ndimage as ndi
import shapely

from pipeline.sensor.sight import (
    BLOCKED,
    OUTSIDE_SWATHS,
    SEEN,
    ground_targets,
    pixels_beside_steps,
    shadow_contradictions,
    sight_classes,
)
from pipeline.sensor.sums import COLUMNS, TrajectorySums, trajectory_sums
from pipeline.sensor.trajectory import fit_flight_lines, swath_polygon

ORIGIN = (1000.0, 2000.0, 0.0)


def _scan(*, height=500.0, half_angle=20.0, line=7, t0=1.0e5, seconds=10.0, pairs=True, angles=True, seed=0):
    """Pulses of a line flying east at 60 m/s over flat ground at z = 10, trees 15 m tall in half the pulses."""
    rng = np.random.default_rng(seed)
    n = int(seconds * 2000)
    t = t0 + np.sort(rng.uniform(0, seconds, n))
    angle = rng.uniform(-half_angle, half_angle, n)
    sx = ORIGIN[0] + 60.0 * (t - t0)
    sy = np.full(n, ORIGIN[1] - 300.0)
    ground = 10.0
    offset = (height - ground) * np.tan(np.radians(angle))  # across track: +y to the north (left)
    xg, yg = sx, sy + offset
    tree = rng.random(n) < 0.5 if pairs else np.zeros(n, bool)
    # first return 15 m up the ray where a tree stands; last return on the ground
    up = 15.0
    x1 = xg - 0.0
    y1 = yg - up * np.tan(np.radians(angle))
    z1 = np.full(n, ground + up)
    rows = []
    for i in range(n):
        if tree[i]:
            rows.append((x1[i], y1[i], z1[i], t[i], 1, 2, angle[i]))
            rows.append((xg[i], yg[i], ground, t[i], 2, 2, angle[i]))
        else:
            rows.append((xg[i], yg[i], ground, t[i], 1, 1, angle[i]))
    a = np.array(rows)
    scan_angle = a[:, 6].astype(np.float32) if angles else np.zeros(len(a), np.float32)
    return dict(
        x=a[:, 0], y=a[:, 1], z=a[:, 2], line=np.full(len(a), line, np.uint16), gps_time=a[:, 3],
        return_number=a[:, 4].astype(np.uint8), number_of_returns=a[:, 5].astype(np.uint8), scan_angle_deg=scan_angle,
        keep=np.ones(len(a), bool),
    )  # fmt: skip


def _fit(points_list, **kwargs):
    sums = TrajectorySums.merged([TrajectorySums(*trajectory_sums(**p, origin=ORIGIN)) for p in points_list])
    return fit_flight_lines(sums.lines, sums.bins, sums.values, origin=ORIGIN, nominal_fov_deg=40.0, **kwargs)


def test_trajectory_from_multiple_returns_finds_the_sensor():
    (line,) = _fit([_scan(angles=False)])
    assert line.method == "multiple_returns"
    assert line.line == 7
    assert abs(np.median(line.sensor[:, 2]) - 500.0) < 5.0
    assert np.all(np.abs(line.sensor[:, 1] - (ORIGIN[1] - 300.0)) < 5.0)
    assert abs(line.azimuth_deg - 90.0) < 1.0  # east


def test_trajectory_from_scan_angles_alone():
    (line,) = _fit([_scan(pairs=False)])
    assert line.method == "scan_angle"
    assert abs(np.median(line.sensor[:, 2]) - 500.0) < 5.0
    swath = (500.0 - 10.0) * math.tan(math.radians(20.0))
    assert abs(line.half_width_left - swath) < 0.05 * swath
    assert abs(line.half_width_right - swath) < 0.05 * swath


def test_nominal_height_where_nothing_else_is_known():
    (line,) = _fit([_scan(pairs=False, angles=False)])
    assert line.method == "nominal"
    swath = 2 * (500.0 - 10.0) * math.tan(math.radians(20.0))
    assert abs(line.flying_height - swath / (2 * math.tan(math.radians(20.0)))) < 0.1 * swath


def test_sums_do_not_depend_on_how_the_points_are_cut():
    scan = _scan(seed=3)
    whole = TrajectorySums(*trajectory_sums(**scan, origin=ORIGIN))
    half = len(scan["x"]) // 2
    parts = [{k: v[:half] for k, v in scan.items()}, {k: v[half:] for k, v in scan.items()}]
    cut = TrajectorySums.merged([TrajectorySums(*trajectory_sums(**p, origin=ORIGIN)) for p in parts])
    assert np.array_equal(whole.lines, cut.lines) and np.array_equal(whole.bins, cut.bins)
    # a pulse whose two returns are cut apart is lost to the rays; everything else adds up
    assert np.allclose(whole.values[:, 0], cut.values[:, 0])


def test_pulses_whose_returns_are_stored_apart_are_paired_by_their_time():
    """A file sorted in space (or read by octree node) keeps a pulse's returns apart: the same rays."""
    scan = _scan(seed=4)
    in_order = TrajectorySums(*trajectory_sums(**scan, origin=ORIGIN))
    order = np.random.default_rng(1).permutation(len(scan["x"]))
    shuffled = {key: value[order] for key, value in scan.items()}
    apart = TrajectorySums(*trajectory_sums(**shuffled, origin=ORIGIN))
    pair_n = list(COLUMNS).index("pair_n")
    assert in_order.values[:, pair_n].sum() > 5000
    np.testing.assert_array_equal(apart.values[:, pair_n], in_order.values[:, pair_n])
    # every sum and the hull's extent (which of two returns on one extreme is kept follows their order)
    summed = [i for i, name in enumerate(COLUMNS) if name[0] not in "xye"]
    np.testing.assert_allclose(apart.values[:, summed], in_order.values[:, summed], rtol=1e-9, atol=1e-6)
    (line,) = _fit([shuffled | {"scan_angle_deg": np.zeros(len(order), np.float32)}])
    assert line.method == "multiple_returns"
    assert abs(np.median(line.sensor[:, 2]) - 500.0) < 5.0


def test_one_id_flown_twice_is_two_passes():
    first = _scan(seconds=6.0)
    second = _scan(seconds=6.0, t0=1.0e5 + 100.0, seed=1)
    second["y"] = second["y"] + 600.0
    lines = _fit([first, second])
    assert [(line.line, line.part) for line in lines] == [(7, 0), (7, 1)]


def test_swath_covers_the_returns():
    scan = _scan(pairs=False)
    (line,) = _fit([scan])
    swath = swath_polygon(line)
    import shapely

    inside = shapely.contains_xy(swath.buffer(1e-6), scan["x"], scan["y"])
    # the bins' hulls join returns (an inner hull): a few returns between two extreme ones lie just outside
    assert inside.mean() > 0.99


def test_line_of_sight_behind_a_wall():
    """A 20 m wall; the sensor to the east: the ground just west of it is hidden, east of it seen."""
    size, pixel = 60, 1.0
    zmax = np.zeros((size, size))
    zmax[:, 30] = 20.0
    candidates = np.zeros((size, size), bool)
    candidates[30, 27] = True  # 3 m west of the 20 m wall: in its shadow (the ray climbs 4 m a metre)
    candidates[30, 40] = True  # east of the wall
    candidates[30, 5] = True  # far west: outside the swath
    zmax[candidates] = np.nan
    measured = np.isfinite(zmax)
    targets = ground_targets(np.nan_to_num(zmax), measured, candidates, step=2.5, pixel_size=1.0)
    swaths = np.ones((1, size, size), bool)
    swaths[0, :, :10] = False
    track = np.array([[100.0, 30.0, 300.0], [100.0, -90.0, 300.0]])  # flies south, x = 100 (east of the window)
    classes = sight_classes(
        candidates, zmax, targets, swaths, [track], origin_xy=(0.0, 60.0), pixel_size=pixel, reach=60.0
    )
    assert classes[30, 27] == BLOCKED
    assert classes[30, 40] == SEEN
    assert classes[30, 5] == OUTSIDE_SWATHS
    assert classes[0, 0] == 0


def test_the_shadows_beside_a_wall_tell_the_sensor_s_height():
    """A 20 m wall 70 m across track from a sensor 200 m up: its shadow is 7 m long (20 x 70 / 200).

    A trajectory 100 m up casts it 14 m, over ground that returned points; one 400 m up casts it
    3.5 m, and leaves the rest of the void in view: the true height contradicts fewest pixels.
    """
    size = 60
    zmax = np.zeros((size, size))
    zmax[:, 30] = 20.0
    zmax[:, 23:30] = np.nan  # x 23-30 m: the shadow, 7 m
    measured = np.isfinite(zmax)
    zmin = np.where(measured, zmax, np.nan)
    zmin[:, 30] = 0.0  # the wall's foot returned too: its pixel spans the step
    swaths = np.ones((1, size, size), bool)
    beside = pixels_beside_steps(zmax, zmin, measured, step=2.5, near_px=16, pixel_size=1.0)

    def contradicting(height: float) -> int:
        track = np.array([[100.0, 200.0, height], [100.0, -140.0, height]])  # flies south at x = 100
        blocked, seen, judged = shadow_contradictions(
            zmax, measured, beside, swaths, [track], origin_xy=(0.0, 60.0), pixel_size=1.0, reach=60.0
        )
        assert judged > 0
        return blocked + seen

    low, true, high = contradicting(100.0), contradicting(200.0), contradicting(400.0)
    assert true < low and true < high, (low, true, high)
    assert true <= 2 * size  # at most the shadow's last column, where the ray grazes the wall's top


def test_a_second_line_from_the_other_side_sees_the_shadow():
    size = 60
    zmax = np.zeros((size, size))
    zmax[:, 30] = 20.0
    candidates = np.zeros((size, size), bool)
    candidates[30, 27] = True
    zmax[candidates] = np.nan
    targets = ground_targets(np.nan_to_num(zmax), np.isfinite(zmax), candidates, step=2.5, pixel_size=1.0)
    east = np.array([[100.0, 30.0, 300.0], [100.0, -90.0, 300.0]])
    west = np.array([[-40.0, 30.0, 300.0], [-40.0, -90.0, 300.0]])
    swaths = np.ones((2, size, size), bool)
    classes = sight_classes(
        candidates, zmax, targets, swaths, [east, west], origin_xy=(0.0, 60.0), pixel_size=1.0, reach=60.0
    )
    assert classes[30, 27] == SEEN


def test_the_first_surface_of_a_void_is_the_water_s_only_where_most_returns_beside_it_are():
    """A void on a lake lies at the water; one on the bank, with a few of the lake's returns beside it, on the bank."""
    from pipeline.sensor.sight import surface_tops

    zmax = np.full((20, 20), 5.0)  # the bank, 5 m above the lake
    water = np.zeros((20, 20), bool)
    water[:, :10] = True  # the lake, west half
    zmax[water] = 0.0
    void = np.zeros((20, 20), bool)
    void[10, 4] = True  # on the lake
    void[10, 11] = True  # on the bank, one pixel from the lake's edge returns
    zmax[void] = np.nan
    tops = surface_tops(zmax, np.isfinite(zmax), void, pixel_size=1.0, water=water)
    assert tops[10, 4] == pytest.approx(0.0)
    assert tops[10, 11] > 2.5  # the bank's level where its returns are the most (here 2 of 3 columns)


def test_a_pixel_s_class_does_not_depend_on_the_window_beyond_its_reach():
    """Rays stop at the reach and clear the heights within it: a tower 70 m away, and the size of the
    window around the reach, change nothing (a 4 m2 void at a Delft scan's edge was blocked with
    250 m cells and not with 50 m ones: the window's highest roof decided when its ray left the grid)."""
    rng = np.random.default_rng(5)
    size, reach = 200, 30.0
    zmax = rng.uniform(0.0, 3.0, (size, size))
    zmax[:, 150:160] = 60.0  # a tower block 70-80 m east of the candidates
    zmax[95:105, 84:86] = 8.0  # a wall just east of them
    candidates = np.zeros((size, size), bool)
    candidates[90:110, 80:84] = True
    candidates[2, 80:84] = True  # near the grid's north edge: their rays leave it
    zmax[candidates] = np.nan
    targets = ground_targets(np.nan_to_num(zmax), np.isfinite(zmax), candidates, step=2.5, pixel_size=1.0)
    track = np.array([[300.0, 250.0, 150.0], [300.0, -250.0, 150.0]])  # east of the window, flying south

    def classes(rows, cols):
        window = (slice(*rows), slice(*cols))
        return sight_classes(
            candidates[window], zmax[window], targets[window], np.ones((1, rows[1] - rows[0], cols[1] - cols[0]), bool),
            [track], origin_xy=(float(cols[0]), float(size - rows[0])), pixel_size=1.0, reach=reach,
        )  # fmt: skip

    whole = classes((0, size), (0, size))
    near = classes((0, 140), (50, 114))  # the candidates' rows and columns grown by the reach
    np.testing.assert_array_equal(near, whole[0:140, 50:114])
    assert (whole[candidates] == BLOCKED).any() and (whole[candidates] == SEEN).any()


def test_the_largest_scan_angle_from_the_swath_s_edges_where_none_is_recorded():
    """Multiple returns place the sensor; the swath's edges and their heights give the scanner's angle."""
    (line,) = _fit([_scan(angles=False)])
    assert abs(line.max_scan_angle_deg - 20.0) < 1.0
    (recorded,) = _fit([_scan()])
    assert recorded.max_scan_angle_deg == pytest.approx(20.0, abs=0.01)


def test_a_side_with_no_return_of_its_own_does_not_measure_the_scanner_s_angle():
    """Returns right of the track only, 20 m off it and beyond (the survey's edge, not given here):
    the left side's farthest return lies across the track, which measures no angle (it made a
    19.5 degree scanner 3.9 in a simulated scan); the right side alone gives 20 degrees."""
    full = _scan(angles=False)
    right = full["y"] <= ORIGIN[1] - 300.0 - 20.0
    (line,) = _fit([{key: value[right] for key, value in full.items()}])
    assert line.method == "multiple_returns"
    assert abs(line.max_scan_angle_deg - 20.0) < 1.0


@pytest.mark.parametrize("pairs", [True, False])
def test_a_swath_cut_by_the_survey_s_edge_keeps_its_track_and_width(pairs):
    """Points north of a boundary 60 m left of line 7's track are not in the survey: the cut side
    neither narrows its swath nor, without rays or angles, pulls its track towards the data (the
    uncut line 8, 400 m south, gives the half-width a line cut all along lacks)."""
    full = _scan(pairs=pairs, angles=False)
    track_y = ORIGIN[1] - 300.0
    cut = track_y + 60.0
    inside = full["y"] <= cut
    points = {key: value[inside] for key, value in full.items()}
    other = _scan(pairs=pairs, angles=False, line=8, seed=1)
    other["y"] = other["y"] - 400.0
    extent = shapely.box(ORIGIN[0] - 100.0, track_y - 900.0, ORIGIN[0] + 800.0, cut)
    swath = (500.0 - 10.0) * math.tan(math.radians(20.0))  # 178 m each side on the ground
    lines = {line.line: line for line in _fit([points, other], extent=extent)}
    cut_line = lines[7]
    assert np.all(np.abs(cut_line.sensor[:, 1] - track_y) < 2.0), cut_line.sensor[:, 1] - track_y
    assert abs(cut_line.half_width_right - swath) < 0.05 * swath
    assert abs(cut_line.half_width_left - swath) < 0.05 * swath  # the side cut all along reaches as far
    if not pairs:
        # without the extent the cut side is taken for the swath's edge: the track at the returns' middle
        blind = {line.line: line for line in _fit([points, other])}[7]
        assert np.median(np.abs(blind.sensor[:, 1] - track_y)) > 30.0


def test_a_side_cut_at_a_slant_counts_as_cut():
    """A bin of a line flying 249 degrees over the survey's south edge (y = 0), seen in a simulated
    scan over Delft: the cut runs at 21 degrees to the track, so the left side's farthest return
    across the track lies 2 m inside the edge (six spacings), while the cut's own vertices lie on it."""
    from pipeline.sensor.trajectory import _INDEX, _cropped_sides

    hull = np.array(
        [[306.5, 2.1], [285.9, 57.3], [281.6, 67.0], [278.9, 68.8], [278.9, 68.8], [278.9, 68.8], [258.2, 59.0],
         [258.2, 59.0], [258.2, 59.0], [280.1, 0.2], [280.1, 0.2], [280.1, 0.2], [289.6, 0.0], [306.5, 2.1],
         [306.5, 2.1], [306.5, 2.1]]
    )[None]  # fmt: skip
    values = np.zeros((1, len(_INDEX)))
    values[0, _INDEX["n"]] = 15_324
    heading = np.radians(249.0)
    left = np.array([-math.cos(heading), math.sin(heading)])  # 90 degrees left of the heading (x east, y north)
    track = np.array([282.0, 32.9])
    across = np.einsum("kvd,d->kv", hull - track, left)
    along = np.einsum("kvd,d->kv", hull - track, np.array([math.sin(heading), math.cos(heading)]))
    boundary = shapely.boundary(shapely.box(-1000.0, 0.0, 1000.0, 1000.0))
    assert across[0].argmax() == 0  # the farthest return left of the track: 2.1 m inside the edge
    assert _cropped_sides(values, hull, across, along, boundary)[0].tolist() == [True, False]


def test_a_side_beside_a_boundary_near_the_track_is_not_cut():
    """A line flown just outside the survey: the boundary runs along it, 20 m right of the track. The
    left side lies wholly beyond it (cut); the right side's returns reach 90 m, and the boundary
    touches that side's inner end only: not cut."""
    from pipeline.sensor.trajectory import _INDEX, _cropped_sides

    angles = np.linspace(0.0, 2.0 * np.pi, 16, endpoint=False)
    # the bin's returns: x 0..30 along the track (east), y from -20 (the boundary) to -90 (the edge)
    hull = np.column_stack([15.0 + 15.0 * np.cos(angles), -55.0 + 35.0 * np.sin(angles)])[None]
    values = np.zeros((1, len(_INDEX)))
    values[0, _INDEX["n"]] = 5_000
    left = np.array([0.0, 1.0])
    across = np.einsum("kvd,d->kv", hull, left)
    along = np.einsum("kvd,d->kv", hull, np.array([1.0, 0.0]))
    boundary = shapely.boundary(shapely.box(-1000.0, -1000.0, 1000.0, -20.0))
    assert _cropped_sides(values, hull, across, along, boundary)[0].tolist() == [True, False]


def test_the_survey_extent_closes_the_seams_between_tiles():
    """Header boxes end at their outermost points: neighbours 0.01 m apart are one extent, a real gap stays."""
    from pipeline.stages.sensor_geometry import survey_extent

    tiles = [(0.0, 0.0, 99.99, 99.99), (100.0, 0.0, 199.99, 99.99), (0.0, 100.0, 99.99, 199.99)]
    extent = survey_extent(tiles, 1.0)
    assert extent.geom_type == "Polygon" and len(extent.interiors) == 0
    assert extent.area == pytest.approx(3 * 99.99 * 99.99, rel=1e-3)
    apart = survey_extent([(0.0, 0.0, 100.0, 100.0), (110.0, 0.0, 200.0, 100.0)], 1.0)
    assert apart.geom_type == "MultiPolygon"


def test_a_void_the_tiles_enclose_is_no_edge_of_the_survey():
    """A missed strip whose tiles' data stops at its edges leaves a hole in their boxes: not the survey's edge."""
    from pipeline.stages.sensor_geometry import survey_extent

    # 100 m tiles around the middle square, cut into two 50 m tiles whose data stops 10 m short of their border
    boxes = [
        (x, y, x + 100.0, y + 100.0)
        for x in (0.0, 100.0, 200.0)
        for y in (0.0, 100.0, 200.0)
        if (x, y) != (100.0, 100.0)
    ]
    boxes += [(100.0, 100.0, 140.0, 200.0), (160.0, 100.0, 200.0, 200.0)]
    extent = survey_extent(boxes, 1.0)
    assert extent.geom_type == "Polygon" and len(extent.interiors) == 0
    assert extent.area == pytest.approx(300.0 * 300.0)
    assert not shapely.boundary(extent).intersects(shapely.Point(140.0, 150.0).buffer(5.0))


def test_a_recorded_angle_the_returns_exceed_is_not_the_scanner_s():
    """IGN's lidar-prod extract records 0-4 degrees over a swath 110 m wide: the returns' own edges win."""
    from pipeline.sensor.trajectory import _largest_angle

    assert _largest_angle(4.002, 20.0) == 20.0
    assert _largest_angle(20.0, 20.3) == 20.3  # a whole-degree rank refined within its half degree
    assert _largest_angle(20.0, 15.0) == 20.0  # a cropped swath measures low: the record stands
    assert _largest_angle(23.0, 22.42) == 22.5  # just below the rank's half degree: its nearest angle
    assert _largest_angle(23.0, 23.7) == 23.5
    assert _largest_angle(20.5, 21.5) == 20.5  # within the slack: the record stands
    assert math.isnan(_largest_angle(math.nan, math.nan))


def _ground_targets_whole_box(zmin, measured, where, *, step, pixel_size):
    """ground_targets with each radius's minimum filter over the whole box of the pixels asked for."""
    from pipeline.sensor.sight import TARGET_RADII_M

    out = np.full(zmin.shape, np.nan)
    rows, cols = np.nonzero(where)
    if len(rows) == 0:
        return out
    values = np.where(measured, zmin, np.inf).astype(np.float64)
    current = np.full(len(rows), np.inf)
    for radius in sorted({max(1, round(r / pixel_size)) for r in TARGET_RADII_M}):
        r0, r1 = max(rows.min() - radius, 0), min(rows.max() + radius + 1, zmin.shape[0])
        c0, c1 = max(cols.min() - radius, 0), min(cols.max() + radius + 1, zmin.shape[1])
        low = ndi.minimum_filter(values[r0:r1, c0:c1], size=2 * radius + 1, mode="constant", cval=np.inf)
        here = low[rows - r0, cols - c0]
        lower = np.isfinite(here) & (~np.isfinite(current) | (here < current - step))
        current = np.where(lower, here, current)
    out[rows, cols] = np.where(np.isfinite(current), current, np.nan)
    return out


@pytest.mark.parametrize("seed", range(10))
def test_ground_targets_band_by_band_are_the_whole_box_s(seed, monkeypatch):
    """The ground under the pixels asked for, filtered band by band of rows, is the whole box's, value
    for value (bands of 1 row to wider than the box, float32 and float64 heights, any pixel size)."""
    from pipeline.sensor import sight

    rng = np.random.default_rng(seed)
    monkeypatch.setattr(sight, "TARGET_BAND_ROWS", int(rng.choice([1, 3, 7, 16, 512])))
    h, w = rng.integers(5, 160, 2)
    zmin = rng.normal(10, 5, (h, w)).astype(np.float32 if seed % 2 else np.float64)
    measured = rng.random((h, w)) < rng.uniform(0.05, 0.95)
    where = (rng.random((h, w)) < rng.uniform(0.002, 0.3)) & ~measured
    pixel_size = float(rng.choice([0.25, 0.5, 1.0, 2.0]))
    got = sight.ground_targets(zmin, measured, where, step=2.5, pixel_size=pixel_size)
    want = _ground_targets_whole_box(zmin, measured, where, step=2.5, pixel_size=pixel_size)
    assert np.array_equal(got, want, equal_nan=True)
