"""The stage-1 kernel and the stage-2 merge against a plain numpy reference."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.grid import Grid, PixelWindow
from pipeline.rasterize import (
    LEVEL_BITS,
    LEVEL_OFFSET,
    GroundSums,
    HeightMapAccumulator,
    merge_ground_sums,
    merge_statistics,
    point_filter_mask,
    shared_pixel_mask,
)


def reference_statistics(grid: Grid, x, y, z, voxel_height):
    """Plain numpy: max/min/count per pixel and distinct voxel levels per pixel."""
    rows, cols = grid.pixel_rows_cols(x, y)
    inside = (rows >= 0) & (rows < grid.height) & (cols >= 0) & (cols < grid.width)
    pixel = rows[inside] * grid.width + cols[inside]
    zi = z[inside].astype(np.float32)
    n = grid.width * grid.height
    count = np.bincount(pixel, minlength=n)
    zmax = np.full(n, -np.inf, np.float32)
    zmin = np.full(n, np.inf, np.float32)
    np.maximum.at(zmax, pixel, zi)
    np.minimum.at(zmin, pixel, zi)
    levels = np.floor(z[inside] / voxel_height).astype(np.int64) + LEVEL_OFFSET
    voxels = np.bincount(np.unique((pixel << LEVEL_BITS) | levels) >> LEVEL_BITS, minlength=n)
    empty = count == 0
    zmax[empty] = np.nan
    zmin[empty] = np.nan
    shape = (grid.height, grid.width)
    return zmax.reshape(shape), zmin.reshape(shape), count.reshape(shape), voxels.reshape(shape)


def make_points(rng, n):
    x = rng.uniform(100.0, 160.0, n)
    y = rng.uniform(200.0, 250.0, n)
    # most heights within a few metres, some far outside a pixel's 64-level span
    z = np.where(rng.random(n) < 0.05, rng.uniform(-80, 300, n), rng.normal(20, 3, n))
    return x, y, z


def accumulate(grid, window, x, y, z, keep, chunk, voxel_height=0.5):
    acc = HeightMapAccumulator(
        window,
        resolution=grid.resolution,
        col_min=grid.col_min,
        row_top=grid.row_top,
        grid_width=grid.width,
        voxel_height=voxel_height,
    )
    used = outside = 0
    for start in range(0, len(x), chunk):
        s = slice(start, start + chunk)
        u, o = acc.add(x[s], y[s], z[s], keep[s])
        used += u
        outside += o
    return acc, used, outside


@pytest.mark.parametrize("resolution", [0.5, 1.0, 0.3048])
@pytest.mark.parametrize("chunk", [997, 100_000])
def test_kernel_matches_numpy_reference(rng, resolution, chunk):
    x, y, z = make_points(rng, 40_000)
    grid = Grid.covering([(100, 200, 160, 250)], resolution=resolution, cell_px=32, halo_px=2, crs_wkt="")
    acc, used, outside = accumulate(grid, grid.window, x, y, z, np.ones(len(x), bool), chunk)
    zmax, zmin, count, voxels = reference_statistics(grid, x, y, z, 0.5)
    stats = acc.statistics
    assert used == len(x) and outside == 0
    np.testing.assert_array_equal(stats.count, count)
    np.testing.assert_array_equal(stats.zmax, zmax)
    np.testing.assert_array_equal(stats.zmin, zmin)
    np.testing.assert_array_equal(stats.voxels, voxels)
    # the keys of any window are exactly the distinct voxels there
    window = PixelWindow(5, 7, 20, 30)
    keys = acc.voxel_keys((window,))
    rows, cols = np.divmod(keys >> LEVEL_BITS, grid.width)
    assert np.all((rows >= 5) & (rows < 25) & (cols >= 7) & (cols < 37))
    assert len(keys) == voxels[5:25, 7:37].sum()


def test_the_overflow_set_grows_as_it_fills_and_binning_resumes_where_it_stopped(rng):
    """Voxels beyond a pixel's 64-level mask go to a set that starts small and grows when half full: the
    kernel stops before the point that would pass the limit and the next call goes on from it, so every
    statistic is the reference's, with the set sized by its keys, not by the points of a chunk."""
    n = 30_000
    x, y = rng.uniform(100.0, 104.0, n), rng.uniform(200.0, 204.0, n)  # 16 pixels
    # one point in ten far above or below its pixel's first: about 2,500 keys, grown from 512 in steps
    z = np.where(rng.random(n) < 0.1, rng.uniform(-50.0, 950.0, n), rng.normal(20.0, 2.0, n))
    keep = rng.random(n) < 0.9
    grid = Grid.covering([(100, 200, 104, 204)], resolution=1.0, cell_px=32, halo_px=0, crs_wkt="")
    acc, used, outside = accumulate(grid, grid.window, x, y, z, keep, n)
    zmax, zmin, count, voxels = reference_statistics(grid, x[keep], y[keep], z[keep], 0.5)
    assert (used, outside) == (keep.sum(), 0)
    np.testing.assert_array_equal(acc.statistics.count, count)
    np.testing.assert_array_equal(acc.statistics.zmax, zmax)
    np.testing.assert_array_equal(acc.statistics.voxels, voxels)
    in_masks = int(np.unpackbits(acc.voxel_bits.view(np.uint8)).sum())
    assert acc.overflow.size == voxels.sum() - in_masks > 1024
    assert acc.overflow.size < len(acc.overflow.table) <= 4 * acc.overflow.size  # doubled as it filled


@pytest.mark.parametrize("chunk", [1_009, 40_000])
def test_ground_sums_take_every_ground_point_in_the_window_whatever_the_filter_keeps(rng, chunk):
    """The take-off's ground: each pixel's ground points' heights summed and counted, points the class filter
    dropped included, points outside the window not, none twice where the overflow set made the kernel stop."""
    n = 40_000
    x, y = rng.uniform(100.0, 130.0, n), rng.uniform(200.0, 225.0, n)
    z = np.round(np.where(rng.random(n) < 0.1, rng.uniform(-50.0, 950.0, n), rng.normal(20.0, 2.0, n)), 2)
    ground, keep = rng.random(n) < 0.4, rng.random(n) < 0.8
    grid = Grid.covering([(100, 200, 130, 225)], resolution=1.0, cell_px=32, halo_px=0, crs_wkt="")
    window = PixelWindow(3, 4, 15, 20)  # part of the grid: the others' points are outside
    acc = HeightMapAccumulator(
        window, resolution=1.0, col_min=grid.col_min, row_top=grid.row_top, grid_width=grid.width,
        voxel_height=0.5, ground=True,
    )  # fmt: skip
    used = outside = 0
    for start in range(0, n, chunk):
        s = slice(start, start + chunk)
        u, o = acc.add(x[s], y[s], z[s], keep[s], ground=ground[s])
        used, outside = used + u, outside + o
    rows, cols = grid.pixel_rows_cols(x, y)
    rows, cols = rows - window.row_off, cols - window.col_off
    inside = (rows >= 0) & (rows < window.height) & (cols >= 0) & (cols < window.width)
    assert (used, outside) == ((keep & inside).sum(), (keep & ~inside).sum())  # the counts of kept points alone
    pixel = (rows * window.width + cols)[inside & ground]
    counts = np.bincount(pixel, minlength=window.height * window.width).reshape(window.shape)
    sums = np.bincount(pixel, weights=z[inside & ground], minlength=counts.size).reshape(window.shape)
    assert acc.ground is not None and acc.overflow.size > 0
    np.testing.assert_array_equal(acc.ground.count, counts)
    np.testing.assert_allclose(acc.ground.height_sum, sums, rtol=1e-12, atol=1e-9)
    assert (ground & ~keep & inside).sum() > 1000  # the filter dropped ground points, and they count
    with np.errstate(invalid="ignore"):
        np.testing.assert_allclose(acc.ground.mean_height(), np.where(counts > 0, sums / counts, np.nan), rtol=1e-12)
    # the statistics are those of the kept points alone
    zmax, _, count, _ = reference_statistics(grid, x[keep], y[keep], z[keep], 0.5)
    np.testing.assert_array_equal(acc.statistics.count, count[window.slices_within(grid.window)])
    np.testing.assert_array_equal(acc.statistics.zmax, zmax[window.slices_within(grid.window)])
    # tiles overlapping a cell: sums and counts add
    halves = [acc.ground.crop(PixelWindow(3, 4, 15, 12)), acc.ground.crop(PixelWindow(3, 10, 15, 14))]
    merged = merge_ground_sums(window, [GroundSums(h.window, h.height_sum.copy(), h.count.copy()) for h in halves])
    overlap = PixelWindow(3, 10, 15, 6).slices_within(window)
    expected = acc.ground.count.copy()
    expected[overlap] *= 2
    np.testing.assert_array_equal(merged.count, expected)


def test_no_ground_sums_unless_asked(rng):
    x, y, z = make_points(rng, 2_000)
    grid = Grid.covering([(100, 200, 160, 250)], resolution=1.0, cell_px=32, halo_px=2, crs_wkt="")
    acc, _, _ = accumulate(grid, grid.window, x, y, z, np.ones(len(x), bool), 1000)
    assert acc.ground is None


def test_points_outside_the_window_are_counted_not_binned(rng):
    x, y, z = make_points(rng, 5_000)
    grid = Grid.covering([(100, 200, 160, 250)], resolution=1.0, cell_px=32, halo_px=2, crs_wkt="")
    window = PixelWindow(0, 0, 20, 20)
    acc, used, outside = accumulate(grid, window, x, y, z, np.ones(len(x), bool), 1000)
    assert used + outside == len(x)
    assert acc.statistics.count.sum() == used


def test_filter_drops_noise_withheld_and_keeps_only_requested():
    classification = np.array([1, 2, 7, 18, 6, 2], np.uint8)
    withheld = np.array([0, 0, 0, 0, 0, 1], bool)
    keep = point_filter_mask(classification, withheld, drop_classes=(7, 18), keep_classes=(), drop_withheld=True)
    assert keep.tolist() == [True, True, False, False, True, False]
    ground = point_filter_mask(classification, withheld, drop_classes=(7, 18), keep_classes=(2,), drop_withheld=False)
    assert ground.tolist() == [False, True, False, False, False, True]


def test_merge_of_overlapping_tiles_equals_one_tile(rng):
    """Two overlapping tiles (like flight strips) merge to exactly the statistics of all points."""
    x, y, z = make_points(rng, 30_000)
    grid = Grid.covering([(100, 200, 160, 250)], resolution=1.0, cell_px=32, halo_px=2, crs_wkt="")
    # tile A: x < 135, tile B: x >= 120 (15 m of overlap, points in the overlap go to both at random)
    in_a = (x < 135) & ((x < 120) | (rng.random(len(x)) < 0.5))
    in_b = ~in_a
    windows = [grid.window_of_bounds(100, 200, 135, 250), grid.window_of_bounds(120, 200, 160, 250)]
    parts = []
    for select, window in zip((in_a, in_b), windows, strict=True):
        other = windows[1] if window is windows[0] else windows[0]
        acc, _, outside = accumulate(grid, window, x[select], y[select], z[select], np.ones(select.sum(), bool), 4096)
        assert outside == 0
        parts.append((acc.statistics, acc.voxel_keys((window.intersection(other),))))
    target = PixelWindow(3, 10, 40, 45)
    merged = merge_statistics(target, parts, shared=shared_pixel_mask(target, windows), grid_width=grid.width)
    zmax, zmin, count, voxels = reference_statistics(grid, x, y, z, 0.5)
    rows, cols = target.slices_within(grid.window)
    np.testing.assert_array_equal(merged.count, count[rows, cols])
    np.testing.assert_array_equal(merged.zmax, zmax[rows, cols])
    np.testing.assert_array_equal(merged.zmin, zmin[rows, cols])
    np.testing.assert_array_equal(merged.voxels, voxels[rows, cols])


def test_integer_records_bin_exactly_like_scaled_floats(rng):
    """The kernel applies X * scale + offset itself; it must match laspy's float coordinates."""
    n = 20_000
    X = rng.integers(0, 6_000_000, n).astype(np.int32)
    Y = rng.integers(0, 5_000_000, n).astype(np.int32)
    Z = rng.integers(-5000, 40_000, n).astype(np.int32)
    scales, offsets = (0.001, 0.001, 0.01), (770_000.0, 6_270_000.0, -12.0)
    x, y, z = (raw * s + o for raw, s, o in zip((X, Y, Z), scales, offsets))
    grid = Grid.covering([(770_000, 6_270_000, 776_000, 6_275_000)], resolution=7.0, cell_px=32, halo_px=2, crs_wkt="")
    keep = rng.random(n) < 0.9
    from_floats, *_ = accumulate(grid, grid.window, x, y, z, keep, 5000)
    from_records = HeightMapAccumulator(
        grid.window, resolution=7.0, col_min=grid.col_min, row_top=grid.row_top, grid_width=grid.width, voxel_height=0.5
    )
    from_records.add(X, Y, Z, keep, scales=scales, offsets=offsets)
    for name in ("zmax", "zmin", "count", "voxels"):
        np.testing.assert_array_equal(getattr(from_records.statistics, name), getattr(from_floats.statistics, name))
