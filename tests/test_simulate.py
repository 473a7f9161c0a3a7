"""The scan simulator: holes arise from the geometry, and the truth says why (pipeline.simulate)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import scipy.ndimage as ndi

from pipeline.simulate import (
    FlightLine,
    ScanParams,
    Surface,
    Terrain,
    load_terrain,
    plan_lines,
    random_scan_params,
    simulate_scan,
    terrain_from_points,
    write_truth,
)
from pipeline.synth import HoleCause

CRS = "EPSG:32631"
X0, Y0 = 500_000.0, 5_000_000.0


def flat_terrain(size_m: float = 200.0, cell: float = 0.5) -> Terrain:
    """Flat open ground at z = 0."""
    n = int(size_m / cell)
    zeros = np.zeros((n, n), np.float32)
    return Terrain("flat", zeros, zeros.copy(), np.zeros((n, n), np.uint8), cell, X0, Y0, CRS)


def with_block_and_pond(terrain: Terrain) -> Terrain:
    """A 20 m tall building at u 100-120, v 60-140; a pond (1 m below the ground) at u 20-60, v 20-60."""
    surface, kind = terrain.surface.copy(), terrain.kind.copy()
    ground = terrain.ground.copy()
    n, cell = terrain.shape[0], terrain.cell_m

    def cells(u0, u1, v0, v1):
        return slice(n - int(v1 / cell), n - int(v0 / cell)), slice(int(u0 / cell), int(u1 / cell))

    surface[cells(100, 120, 60, 140)] = 20.0
    kind[cells(100, 120, 60, 140)] = Surface.BUILDING
    for raster in (surface, ground):
        raster[cells(20, 60, 20, 60)] = -1.0
    kind[cells(20, 60, 20, 60)] = Surface.WATER
    return Terrain("block", surface, ground, kind, cell, terrain.x_min, terrain.y_min, CRS)


def north_line(source_id: int, u: float, altitude: float, terrain: Terrain, gps: float = 1000.0) -> FlightLine:
    x = terrain.x_min + u
    return FlightLine(source_id, (x, terrain.y_min - 30.0), (x, terrain.y_min + terrain.height_m + 30.0), altitude, gps)


def hand_params(lines, **changes) -> ScanParams:
    base = ScanParams(
        seed=5, lines=tuple(lines), fov_deg=60.0, pulses_per_m2=8.0, speed_m_s=50.0, swath_m=115.0, tile_m=100.0
    )
    return dataclasses.replace(base, **changes)


def pixel_counts(scan, resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """Points per pixel and the truth, on the same lattice."""
    truth, transform = scan.truth(resolution)
    col = np.floor(scan.x / resolution).astype(np.int64) - round(transform[2] / resolution)
    row = round(transform[5] / resolution) - 1 - np.floor(scan.y / resolution).astype(np.int64)
    count = np.zeros(truth.shape, np.int64)
    np.add.at(count, (row, col), 1)
    return count, truth


def pixel_centres(truth: np.ndarray, resolution: float, terrain: Terrain) -> tuple[np.ndarray, np.ndarray]:
    """Local (u, v) of every pixel centre of a truth raster over ``terrain``."""
    rows, cols = np.indices(truth.shape)
    return (cols + 0.5) * resolution, terrain.height_m - (rows + 0.5) * resolution


@pytest.fixture(scope="module")
def block_scan(tmp_path_factory):
    """One line flying north at u = 90 m, 100 m up, beside the block; no water returns."""
    terrain = with_block_and_pond(flat_terrain())
    params = hand_params([north_line(7, 90.0, 100.0, terrain)], water_nadir_deg=0.0)
    return simulate_scan(terrain, params, tmp_path_factory.mktemp("block"))


def test_points_behind_a_tall_block_are_missing_and_truth_says_occlusion(block_scan):
    count, truth = pixel_counts(block_scan, 1.0)
    u, v = pixel_centres(truth, 1.0, block_scan.terrain)
    # the block's top at 20 m hides the ground up to 120 + 20 x 30 / 80 = 127.5 m east of the line
    shadow = (u > 121) & (u < 127) & (v > 62) & (v < 138)
    assert shadow.sum() > 300
    assert np.all(count[shadow] == 0)
    assert np.all(truth[shadow] == HoleCause.OCCLUSION)
    lit = (u > 130) & (u < 140) & (v > 62) & (v < 138)  # beyond the shadow, still in the swath (up to 147 m)
    assert np.all(count[lit] > 0) and np.all(truth[lit] == HoleCause.NONE)
    roof = (u > 101) & (u < 119) & (v > 61) & (v < 139)
    assert np.all(count[roof] > 0)


def test_water_returns_nothing_and_truth_says_water(block_scan):
    count, truth = pixel_counts(block_scan, 1.0)
    u, v = pixel_centres(truth, 1.0, block_scan.terrain)
    pond = (u > 33) & (u < 59) & (v > 21) & (v < 59)  # the swath reaches 90 - 101 tan(30 deg) = 31.7 m
    assert np.all(count[pond] == 0)
    assert np.all(truth[pond] == HoleCause.WATER)


def test_near_nadir_water_returns_are_class_9(tmp_path):
    terrain = with_block_and_pond(flat_terrain())
    params = hand_params([north_line(3, 40.0, 100.0, terrain)], water_nadir_deg=6.0, water_return=1.0)
    scan = simulate_scan(terrain, params, tmp_path)
    import laspy

    classes = np.concatenate([np.asarray(laspy.read(path).classification) for path in scan.tiles])
    assert np.any(classes == 9)
    count, truth = pixel_counts(scan, 1.0)
    u, v = pixel_centres(truth, 1.0, terrain)
    far_from_nadir = (u > 52) & (u < 59) & (v > 21) & (v < 59)  # more than 6 degrees off: 10.5 m at 100 m
    assert np.all(count[far_from_nadir] == 0) and np.all(truth[far_from_nadir] == HoleCause.WATER)


def test_outside_the_swath_is_missed_coverage(block_scan):
    count, truth = pixel_counts(block_scan, 1.0)
    u, _ = pixel_centres(truth, 1.0, block_scan.terrain)
    # swath on the ground: 90 +- 100 tan(30 deg) = 32.3 .. 147.7 m
    outside = (u < 31) | (u > 149)
    assert np.all(count[outside] == 0) and np.all(truth[outside] == HoleCause.MISSED_COVERAGE)


def test_dark_patches_return_nothing_and_truth_says_no_return(tmp_path):
    terrain = flat_terrain()
    patch = ((X0 + 80.0, Y0 + 80.0), (X0 + 100.0, Y0 + 80.0), (X0 + 100.0, Y0 + 100.0), (X0 + 80.0, Y0 + 100.0))
    params = hand_params([north_line(12, 90.0, 100.0, terrain)], dark_patches=(patch,))
    scan = simulate_scan(terrain, params, tmp_path)
    count, truth = pixel_counts(scan, 1.0)
    u, v = pixel_centres(truth, 1.0, terrain)
    inside = (u > 81) & (u < 99) & (v > 81) & (v < 99)
    assert np.all(count[inside] == 0) and np.all(truth[inside] == HoleCause.NO_RETURN)
    assert np.all(truth[~inside & (count > 0)] == HoleCause.NONE)


def test_vegetation_gives_multiple_returns_and_single_returns_keeps_the_first(tmp_path):
    terrain = flat_terrain(100.0)
    surface, kind = terrain.surface.copy(), terrain.kind.copy()
    surface[40:160, 40:160], kind[40:160, 40:160] = 15.0, Surface.VEGETATION
    forest = dataclasses.replace(terrain, surface=surface, kind=kind)
    line = north_line(4, 50.0, 100.0, forest)
    multiple = simulate_scan(forest, hand_params([line], penetration=0.8, tile_m=50.0), tmp_path / "multiple")
    single = simulate_scan(forest, hand_params([line], single_returns=True, tile_m=50.0), tmp_path / "single")
    import laspy

    def fields(scan):
        las = [laspy.read(path) for path in scan.tiles]
        return {
            name: np.concatenate([np.asarray(getattr(f, name)) for f in las])
            for name in ("number_of_returns", "return_number", "classification")
        }

    many, one = fields(multiple), fields(single)
    assert many["number_of_returns"].max() >= 2
    assert np.all(many["return_number"] <= many["number_of_returns"])
    last = (many["return_number"] == many["number_of_returns"]) & (many["number_of_returns"] > 1)
    assert np.all(many["classification"][last] == 2)  # ground under the canopy
    assert np.all(one["number_of_returns"] == 1) and np.all(one["return_number"] == 1)


def test_dropped_line_leaves_a_strip_with_no_points_where_truth_says_missed_coverage(tmp_path):
    terrain = flat_terrain(300.0, 1.0)
    seed = next(
        s
        for s in range(50)
        if random_scan_params(s, terrain).dropped and not random_scan_params(s, terrain).dark_patches
    )
    params = random_scan_params(seed, terrain)
    scan = simulate_scan(terrain, params, tmp_path)
    resolution = 2.0 if params.pulses_per_m2 < 4 else 1.0
    count, truth = pixel_counts(scan, resolution)
    u, v = pixel_centres(truth, resolution, terrain)
    x, y = u + terrain.x_min, v + terrain.y_min

    def margin_outside(line):  # > 0 outside the line's swath, metres
        heading = math.radians(line.heading_deg)
        across = (x - line.start[0]) * math.cos(heading) - (y - line.start[1]) * math.sin(heading)
        return np.abs(across) - line.altitude_m * math.tan(math.radians(params.fov_deg) / 2)

    outside = np.min([margin_outside(line) for line in params.lines], axis=0)
    in_gap = margin_outside(params.dropped[0]) < 0
    strip = (outside > resolution) & in_gap
    assert strip.sum() * resolution**2 > 1000  # a strip of several pixels, the scene's length
    assert np.all(count[strip] == 0) and np.all(truth[strip] == HoleCause.MISSED_COVERAGE)
    covered = outside < -resolution
    assert np.all(count[covered] > 0) and np.all(truth[covered] == HoleCause.NONE)
    assert np.all(count[truth == HoleCause.MISSED_COVERAGE] == 0)


def test_same_seed_same_scan_and_ids_with_gaps_preserved(tmp_path):
    import laspy

    terrain = with_block_and_pond(flat_terrain())
    assert random_scan_params(11, terrain) == random_scan_params(11, terrain)
    assert random_scan_params(11, terrain) != random_scan_params(12, terrain)
    tracks = plan_lines(terrain, heading_deg=30.0, swath_m=80.0, overlap=0.2, first_offset=0.1)
    ids = (7, 3, 12, 40)[: len(tracks)]
    lines = [FlightLine(i, a, b, 100.0, 1000.0 + 500 * k) for k, (i, (a, b)) in enumerate(zip(ids, tracks))]
    params = hand_params(lines, scan_angles=False, pulses_per_m2=3.0)
    first = simulate_scan(terrain, params, tmp_path / "a")
    second = simulate_scan(terrain, params, tmp_path / "b")
    assert np.array_equal(first.x, second.x) and np.array_equal(first.y, second.y)
    assert np.array_equal(first.causes, second.causes)
    las = [laspy.read(path) for path in first.tiles]
    assert {f.header.point_format.id for f in las} == {6} and {str(f.header.version) for f in las} == {"1.4"}
    assert {f.header.parse_crs().to_epsg() for f in las} == {32631}
    assert set(np.concatenate([np.asarray(f.point_source_id) for f in las])) == set(ids)
    assert all(np.all(np.asarray(f.scan_angle) == 0) for f in las)  # "without scan angles"
    for source_id in ids:  # GPS time grows along each line
        times = np.sort(np.concatenate([f.gps_time[np.asarray(f.point_source_id) == source_id] for f in las]))
        assert times[-1] - times[0] < 30.0
    truth_path = write_truth(first, 1.0, tmp_path / "truth.tif")
    from pipeline.io.raster import read_raster

    truth, transform, crs = read_raster(truth_path)
    assert transform.a == 1.0 and transform.c % 1.0 == 0.0
    assert "32631" in crs or "UTM zone 31N" in crs
    assert np.array_equal(truth.astype(np.uint8), first.truth(1.0)[0])


def test_point_format_1_writes_scan_angle_rank(tmp_path):
    import laspy

    terrain = flat_terrain(100.0)
    params = hand_params([north_line(40, 50.0, 100.0, terrain)], point_format=1, tile_m=50.0, pulses_per_m2=2.0)
    scan = simulate_scan(terrain, params, tmp_path)
    las = laspy.read(scan.tiles[0])
    assert las.header.point_format.id == 1
    assert np.abs(np.asarray(las.scan_angle_rank)).max() in range(25, 31)


def test_terrain_from_points_finds_water_voids_buildings_and_ground():
    rng = np.random.default_rng(3)
    x, y = rng.uniform(0, 40, 40_000), rng.uniform(0, 40, 40_000)
    z = np.zeros_like(x)
    cls = np.full(x.shape, 2)
    building = (x > 5) & (x < 15) & (y > 5) & (y < 15)
    z[building], cls[building] = 10.0, 6
    pond = (x > 25) & (x < 35) & (y > 25) & (y < 35)
    cls[pond], z[pond] = 9, -0.5
    void = pond & (x > 28)  # water with few returns: a void beside class-9 points
    keep = ~void
    terrain = terrain_from_points(x[keep], y[keep], z[keep], cls[keep], cell_m=1.0, bounds=(0, 0, 40, 40), crs=CRS)
    kind = terrain.kind
    assert np.all(kind[40 - 14 : 40 - 6, 6:14] == Surface.BUILDING)
    assert np.all(kind[40 - 34 : 40 - 26, 26:34] == Surface.WATER)  # points and the void next to them
    assert np.allclose(terrain.surface[40 - 34 : 40 - 26, 29:34], -0.5)
    assert np.allclose(terrain.ground[40 - 14 : 40 - 6, 6:14], 0.0)  # interpolated under the roof


@pytest.mark.realdata
def test_scan_over_real_urban_terrain(shared_data, tmp_path):
    terrain = load_terrain("amsterdam", shared_data)
    assert terrain.crs == "EPSG:28992" and terrain.width_m == 200.0
    assert np.any(terrain.kind == Surface.BUILDING) and np.any(terrain.kind == Surface.VEGETATION)
    params = random_scan_params(4, terrain)
    scan = simulate_scan(terrain, params, tmp_path)
    assert scan.n_points > 10_000
    truth, _ = scan.truth(1.0)
    assert set(np.unique(truth)) <= {0, 1, 2, 3, 4}
    assert {int(i) for i in np.unique(scan.point_source_id)} == {line.source_id for line in params.lines}


def test_dark_patches_keep_off_water():
    """A dark patch is land: none of its cells lies within the margin of water, whatever the seed."""
    from pipeline.simulate.params import DARK_PATCH_WATER_MARGIN_M, dark_mask, dark_patches

    terrain = with_block_and_pond(flat_terrain(200.0, 0.5))
    water = terrain.kind == Surface.WATER
    reach = int(np.ceil(DARK_PATCH_WATER_MARGIN_M / terrain.cell_m))
    near_water = ndi.binary_dilation(water, iterations=reach, structure=np.ones((3, 3), bool))
    placed = 0
    for seed in range(40):
        patches = dark_patches(terrain, np.random.default_rng(seed), count=3)
        placed += len(patches)
        assert not (dark_mask(terrain, patches) & near_water).any(), seed
    assert placed == 120  # the pond, 4 % of the scene, never leaves a patch without a place
