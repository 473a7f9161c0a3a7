"""Tests of pipeline.holes.walls: wall segments from jump pixels and the S-curve fit ([WALL])."""

from __future__ import annotations

import math

import numpy as np
import pytest
from affine import Affine
from scipy import sparse
from scipy.sparse import csgraph

from pipeline.holes import height_jumps
from pipeline.holes.walls import WallParams, _group_jump_pixels, find_walls, fit_wall, wall_segments

LOW, HIGH = 10.0, 22.0


def antialiased_step(n: int, angle_deg: float, offset: float, supersample: int = 16) -> np.ndarray:
    """Each pixel holds the mean height over its square of a sharp step at a known line."""
    a = math.radians(angle_deg)
    sub = (np.arange(n * supersample) + 0.5) / supersample
    x, y = np.meshgrid(sub, sub)
    high = (x * math.cos(a) + y * math.sin(a) - offset) > 0
    return LOW + (HIGH - LOW) * high.reshape(n, supersample, n, supersample).mean(axis=(1, 3))


def binned_points(n: int, angle_deg: float, offset: float, density: float, seed: int):
    """zmax, zmin and count rasters of random points on a sharp step (the stage-2 rasters)."""
    rng = np.random.default_rng(seed)
    k = int(n * n * density)
    x, y = rng.uniform(0, n, k), rng.uniform(0, n, k)
    a = math.radians(angle_deg)
    z = np.where(x * math.cos(a) + y * math.sin(a) - offset > 0, HIGH, LOW) + rng.normal(0, 0.02, k)
    r, c = y.astype(int), x.astype(int)
    zmax = np.full((n, n), -np.inf)
    zmin = np.full((n, n), np.inf)
    count = np.zeros((n, n), np.int64)
    np.maximum.at(zmax, (r, c), z)
    np.minimum.at(zmin, (r, c), z)
    np.add.at(count, (r, c), 1)
    zmax[count == 0] = np.nan
    zmin[count == 0] = np.nan
    return zmax, zmin, count


def distance_to_truth(wall, angle_deg, offset):
    """Largest distance (pixels) of the fitted segment's ends and middle from the true line."""
    a = math.radians(angle_deg)
    c0, r0, c1, r1 = wall.line_px
    pts = [(c0, r0), (c1, r1), ((c0 + c1) / 2, (r0 + r1) / 2)]
    return max(abs(c * math.cos(a) + r * math.sin(a) - offset) for c, r in pts)


def centred_offset(angle_deg, n=40, shift=0.0):
    a = math.radians(angle_deg)
    return n / 2 * (math.cos(a) + math.sin(a)) + shift


@pytest.mark.parametrize("angle", [0.0, 20.0, 33.0, 45.0, 110.0, 200.0])
@pytest.mark.parametrize("shift", [0.0, 0.37])
def test_fit_recovers_a_subpixel_step_on_a_mean_raster(angle, shift):
    offset = centred_offset(angle, shift=shift)
    z = antialiased_step(40, angle, offset)
    walls = find_walls(z, None, jump_threshold=2.0, params=WallParams(pixel_values="centre"))
    assert len(walls) == 1
    wall = walls[0]
    assert distance_to_truth(wall, angle, offset) < 0.2
    assert wall.bottom == pytest.approx(LOW, abs=0.1) and wall.top == pytest.approx(HIGH, abs=0.1)
    assert wall.rms < 0.1
    # the normal points to the high side
    a = math.radians(angle)
    assert wall.normal_px[0] * math.cos(a) + wall.normal_px[1] * math.sin(a) > 0.99


@pytest.mark.parametrize("angle,seed", [(20.0, 0), (33.0, 1), (-25.0, 2)])
def test_fit_recovers_a_slanted_wall_from_binned_points(angle, seed):
    offset = centred_offset(angle, shift=0.13 * seed)
    zmax, zmin, count = binned_points(40, angle, offset, density=20, seed=seed)
    walls = find_walls(zmax, zmin, jump_threshold=2.0, count=count)
    assert walls
    assert distance_to_truth(walls[0], angle, offset) < 0.2
    assert walls[0].height == pytest.approx(HIGH - LOW, abs=0.2)


def test_shadow_next_to_the_wall_keeps_the_wall_at_the_roof_edge():
    angle, offset = 10.0, centred_offset(10.0, shift=0.3)
    z = antialiased_step(40, angle, offset)
    zmax = z.copy()
    a = math.radians(angle)
    r, c = np.mgrid[:40, :40]
    d = (c + 0.5) * math.cos(a) + (r + 0.5) * math.sin(a) - offset
    zmax[(d < -0.5) & (d > -5.5)] = np.nan  # the ground beside the wall was not seen
    walls = find_walls(zmax, None, jump_threshold=2.0, params=WallParams(support_px=4.0, pixel_values="centre"))
    assert walls and distance_to_truth(walls[0], angle, offset) < 0.3


def test_l_shaped_building_gives_two_perpendicular_walls_in_world_coordinates():
    n = 60
    z = np.full((n, n), LOW)
    z[10:40, 10:45] = HIGH
    transform = Affine(0.5, 0, 1000.0, 0, -0.5, 2000.0)  # 0.5 m pixels
    walls = find_walls(z, z, jump_threshold=2.0, transform=transform, params=WallParams(min_length_px=8))
    assert len(walls) == 4
    directions = sorted(round(math.degrees(math.atan2(w.y1 - w.y0, w.x1 - w.x0))) % 180 for w in walls)
    assert directions == [0, 0, 90, 90]
    north = max(walls, key=lambda w: (w.y0 + w.y1) / 2)
    # the north wall is the edge between rows 9 and 10: y = 2000 - 10 * 0.5, within half a pixel
    assert north.y0 == pytest.approx(1995.0, abs=0.25) and north.y1 == pytest.approx(1995.0, abs=0.25)
    assert north.length == pytest.approx(35 * 0.5, abs=1.0)
    assert all(w.top == pytest.approx(HIGH, abs=0.1) and w.bottom == pytest.approx(LOW, abs=0.1) for w in walls)


def test_segments_split_at_corners_and_ignore_noise():
    n = 50
    z = np.full((n, n), LOW)
    z[10:30, 10:35] = HIGH
    rng = np.random.default_rng(0)
    r, c = np.mgrid[:n, :n]
    crown = (r - 42) ** 2 + (c - 8) ** 2 < 25
    z[crown] += rng.uniform(3, 15, crown.sum())  # a tree: jumps in every direction
    jumps = height_jumps(z, z, jump_threshold=2.0)
    segs = wall_segments(jumps, z, min_pixels=8)
    assert len(segs) == 4
    normals = sorted((round(s.normal[0]), round(s.normal[1])) for s in segs)
    assert normals == [(-1, 0), (0, -1), (0, 1), (1, 0)]  # all point into the building


def test_fit_rejects_flat_ground():
    z = np.full((30, 30), 5.0)
    assert find_walls(z, z, jump_threshold=1.0) == []
    jumps = np.zeros((30, 30), bool)
    jumps[10, 5:20] = True
    seg = wall_segments(jumps, z + np.arange(30)[:, None] * 0.0, min_pixels=3)
    for s in seg:
        assert fit_wall(z, z, s, min_height=1.0) is None


def _scipy_step_fit(observations, x0, lower, upper, step0):
    """The fit as scipy's least_squares makes it (trf, then the soft-L1 polish): the reference of the compiled one."""
    from scipy.optimize import least_squares

    from pipeline.holes.wall_step import soft_l1_cost, step_jacobian, step_residuals

    bounds = (np.asarray(lower, dtype=float), np.asarray(upper, dtype=float))
    residuals = lambda p: step_residuals(np.asarray(p, dtype=float), *observations)  # noqa: E731
    jacobian = lambda p: step_jacobian(np.asarray(p, dtype=float), *bounds, *observations)  # noqa: E731
    scale = [0.05, 0.1, 0.1 * step0, 0.1 * step0, 0.5]
    options = {"ftol": 1e-6, "xtol": 1e-6, "gtol": 1e-6, "jac": jacobian, "x_scale": scale}
    fit = least_squares(residuals, x0, bounds=(lower, upper), max_nfev=200, **options)
    f_scale = max(0.05 * step0, 1e-6)
    if np.max(np.abs(fit.fun)) > 3.0 * f_scale:
        start = np.clip(fit.x, np.nextafter(lower, upper), np.nextafter(upper, lower))
        robust = least_squares(
            residuals, start, bounds=(lower, upper), max_nfev=100, loss="soft_l1", f_scale=f_scale, **options
        )
        if robust.status >= 0 and robust.cost <= soft_l1_cost(fit.fun, f_scale):
            return robust
    return fit


@pytest.mark.parametrize("seed", range(12))
def test_compiled_fit_finds_scipys_wall(seed, monkeypatch):
    """The compiled bounded Levenberg-Marquardt search fits at least as well as scipy's trf (cost
    within 1 %), and lands where it does (the same line within 0.02 px at the segment's middle,
    the same heights within 1 cm) unless its fit is clearly better (scipy can stop early on a
    flat valley: a short piece of wall beside a shadow), outliers and shadows included."""
    from pipeline.holes import walls as W

    rng = np.random.default_rng(seed)
    angle = float(rng.uniform(0, 360))
    offset = centred_offset(angle, shift=float(rng.uniform(-0.5, 0.5)))
    zmax, zmin, count = binned_points(40, angle, offset, density=float(rng.uniform(3, 30)), seed=seed)
    if seed % 3 == 1:  # outliers on both sides
        rows, cols = rng.integers(0, 40, 12), rng.integers(0, 40, 12)
        zmax[rows, cols] += rng.choice([-6.0, 6.0], 12)
    if seed % 3 == 2:  # a shadow on the low side along part of the wall
        a = math.radians(angle)
        r, c = np.mgrid[:40, :40]
        d = (c + 0.5) * math.cos(a) + (r + 0.5) * math.sin(a) - offset
        along = -(c + 0.5) * math.sin(a) + (r + 0.5) * math.cos(a)
        shadow = (d < -0.5) & (d > -2.5) & (along > np.median(along))
        zmax[shadow], zmin[shadow], count[shadow] = np.nan, np.nan, 0
    problems = []
    compiled = W._fit_step

    def both(observations, x0, lower, upper, step0):
        found = compiled(observations, x0, lower, upper, step0)
        problems.append((observations, found, _scipy_step_fit(observations, x0, lower, upper, step0)))
        return found

    monkeypatch.setattr(W, "_fit_step", both)
    find_walls(zmax, zmin, jump_threshold=2.0, count=count)
    assert problems

    def offset_at_middle(observations, x):
        """The fitted line's signed offset at the middle of the support (pixels)."""
        xs = np.concatenate([observations[0], observations[8]])
        ys = np.concatenate([observations[1], observations[9]])
        return xs.mean() * math.cos(x[0]) + ys.mean() * math.sin(x[0]) - x[1]

    for observations, found, reference in problems:
        assert found is not None
        assert found.cost <= reference.cost * 1.01 + 1e-9
        if found.cost < reference.cost * 0.99:
            continue
        assert abs(offset_at_middle(observations, found.x) - offset_at_middle(observations, reference.x)) < 0.02
        assert found.x[2] == pytest.approx(reference.x[2], abs=0.01)
        assert found.x[3] == pytest.approx(reference.x[3], abs=0.01)


@pytest.mark.parametrize("seed", range(8))
def test_analytic_jacobian_matches_forward_differences(seed):
    """The step's Jacobian (analytic in rho, the heights and the width; a difference in phi) agrees
    with forward differences in every parameter, at random lines, widths and point counts,
    axis-aligned walls (a degenerate trapezoid) included."""
    from pipeline.holes.wall_step import LOGISTIC_NODES, step_jacobian

    rng = np.random.default_rng(seed)
    phi = 0.0 if seed == 0 else float(rng.uniform(-math.pi, math.pi))
    params = np.array([phi, rng.uniform(-2, 2), 10.0, 10.0 + rng.uniform(2, 15), math.log(rng.uniform(0.01, 2.0))])
    lower, upper = params - 1.0, params + 1.0

    def pixels(n):
        return rng.uniform(-4, 4, n), rng.uniform(-4, 4, n)

    (xh, yh), (xl, yl), (xe, ye) = pixels(60), pixels(50), pixels(10)
    kh, kl = np.maximum(rng.poisson(6, 60), 1).astype(float), np.maximum(rng.poisson(6, 50), 1).astype(float)
    zh, zl = rng.uniform(10, 25, 60), rng.uniform(10, 25, 50)
    observations = (xh, yh, kh, zh, xl, yl, kl, zl, xe, ye, LOGISTIC_NODES)
    analytic = step_jacobian(params, lower, upper, *observations)
    reference = _forward_differences(params, upper, observations)
    scale = np.abs(reference).max(axis=0) + 1e-9
    # forward differences are accurate to about sqrt(eps) relative, worse at the trapezoid's kinks
    assert np.abs(analytic - reference).max(axis=0) / scale == pytest.approx(np.zeros(5), abs=1e-5)
    np.testing.assert_array_equal(analytic[:, 0], reference[:, 0])


def _segments_one_by_one(jumps, zmax, *, min_pixels=6, min_length_px=4.0, angle_tolerance_deg=20.0, thickness=2.0):
    """The segments as the groups were judged one at a time (eigh of each group's covariance): the reference."""
    from pipeline.holes import walls as W

    gx, gy = W._uphill(np.asarray(zmax, dtype=np.float64))
    rows, cols = np.nonzero(jumps)
    gxs, gys = gx[rows, cols], gy[rows, cols]
    tol = math.radians(angle_tolerance_deg)
    n_groups, group = W._group_jump_pixels(jumps, rows, cols, gxs, gys, tol)
    found = {}
    for g in range(n_groups):
        members = np.flatnonzero(group == g)
        if len(members) < min_pixels:
            continue
        pts = np.stack([cols[members] + 0.5, rows[members] + 0.5], axis=1)
        centred = pts - pts.mean(axis=0)
        evals, evecs = np.linalg.eigh(centred.T @ centred / len(pts))
        along = evecs[:, 1]
        if math.sqrt(max(evals[0], 0.0)) > thickness + 1e-9 or math.sqrt(12 * evals[1]) < min_length_px - 1e-9:
            continue
        normal = np.array([-along[1], along[0]])
        unit = np.stack([gxs[members], gys[members]], axis=1)
        uphill = (unit / np.linalg.norm(unit, axis=1, keepdims=True)).mean(axis=0)
        if np.linalg.norm(uphill) < math.cos(tol) or abs(normal @ uphill) < math.cos(tol) * np.linalg.norm(uphill):
            continue
        found[tuple(sorted(zip(rows[members].tolist(), cols[members].tolist())))] = (
            normal if normal @ uphill > 0 else -normal
        )
    return found


@pytest.mark.parametrize("seed", range(6))
def test_segments_judged_together_as_one_by_one(seed):
    """All groups judged at once (closed-form 2 x 2 eigenvalues, bincount sums) give the segments
    and normals of judging each group alone, on a roofscape of random boxes and noise."""
    rng = np.random.default_rng(seed)
    z = rng.normal(0.0, 0.3, (120, 120))
    for _ in range(25):
        r, c = rng.integers(0, 110, 2)
        h, w = rng.integers(4, 30, 2)
        z[r : r + h, c : c + w] += rng.uniform(3, 15)
    z = ndi_rotate(z, float(rng.uniform(0, 90)))
    jumps = height_jumps(z, z, jump_threshold=2.0)
    reference = _segments_one_by_one(jumps, z)
    got = {tuple(sorted(zip(s.rows.tolist(), s.cols.tolist()))): np.array(s.normal) for s in wall_segments(jumps, z)}
    assert len(reference) > 5
    assert got.keys() == reference.keys()

    for key, normal in reference.items():
        np.testing.assert_allclose(got[key], normal, atol=1e-9)


def ndi_rotate(z: np.ndarray, angle: float) -> np.ndarray:
    from scipy import ndimage

    return ndimage.rotate(z, angle, reshape=False, order=0, mode="nearest")


def test_a_group_exactly_as_long_as_the_limit_is_a_segment():
    """Nine jump pixels of a diagonal wall in williams_az_urban_norm are exactly 4 px long
    (sqrt(12 x 4/3)); eigh made it 3.9999999999999996 and dropped the wall. Ties meet the limit."""
    tie = np.zeros((110, 160), bool)  # where it lay in its cell: the rounding depends on it
    for r, c in ((97, 143), (97, 144), (98, 143), (98, 144), (98, 145), (99, 144), (99, 145), (100, 144), (100, 145)):
        tie[r, c] = True
    rows, cols = np.mgrid[:110, :160]
    ramp = 10.0 * (cols - 0.5 * rows)  # uphill across the group (east-north-east), the same at every pixel
    segments = wall_segments(tie, ramp, min_pixels=6, min_length_px=4.0)
    assert len(segments) == 1 and segments[0].n_pixels == 9


def _forward_differences(params, upper, observations):
    """The step's Jacobian by forward differences in every parameter (scipy's "2-point" rule)."""
    from pipeline.holes.wall_step import step_residuals

    base = step_residuals(params, *observations)
    columns = []
    for j in range(len(params)):
        h = 1.4901161193847656e-08 * max(1.0, abs(params[j]))
        if params[j] + h > upper[j]:
            h = -h
        shifted = params.copy()
        shifted[j] += h
        columns.append((step_residuals(shifted, *observations) - base) / (shifted[j] - params[j]))
    return np.column_stack(columns)


def test_a_segment_s_middle_pixel_is_numpy_s_median_truncated():
    """find_walls fits a segment in the cell holding its median pixel: the same pixel as int(np.median)."""
    from pipeline.holes.walls import _median_index

    rng = np.random.default_rng(11)
    for _ in range(2000):
        indices = rng.integers(0, int(rng.integers(1, 3000)), int(rng.integers(1, 60)))
        assert _median_index(indices) == int(np.median(indices))


def test_jump_pixel_groups_are_scipys_connected_components_in_the_same_numbering():
    # the union-find numbers groups by their lowest pixel, as csgraph does: segments sort by size
    # with ties kept in group order, so the numbering reaches the walls layer
    rng = np.random.default_rng(3)
    for _ in range(20):
        shape = tuple(int(v) for v in rng.integers(5, 80, 2))
        jumps = rng.random(shape) < rng.uniform(0.05, 0.7)
        rows, cols = np.nonzero(jumps)
        gxs, gys = rng.normal(size=len(rows)), rng.normal(size=len(rows))
        gxs[rng.random(len(rows)) < 0.1] = 0.0
        gys[gxs == 0.0] = 0.0  # flat pixels join no group
        tol = math.radians(20.0)
        index = np.full(shape, -1, np.int64)
        index[rows, cols] = np.arange(len(rows))
        angle = np.mod(np.arctan2(gys, gxs), np.pi)
        strong = np.hypot(gxs, gys) > 0
        a_all, b_all = [], []
        for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
            r2, c2 = rows + dr, cols + dc
            ok = (r2 >= 0) & (r2 < shape[0]) & (c2 >= 0) & (c2 < shape[1])
            other = np.full(len(rows), -1, np.int64)
            other[ok] = index[r2[ok], c2[ok]]
            a, b = np.flatnonzero(other >= 0), other[other >= 0]
            diff = np.abs(angle[a] - angle[b])
            keep = (np.minimum(diff, np.pi - diff) < tol) & strong[a] & strong[b]
            a_all.append(a[keep])
            b_all.append(b[keep])
        a, b = np.concatenate(a_all), np.concatenate(b_all)
        graph = sparse.coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(len(rows), len(rows)))
        expected_n, expected = csgraph.connected_components(graph, directed=False)
        n, groups = _group_jump_pixels(jumps, rows, cols, gxs, gys, tol)
        assert n == expected_n and np.array_equal(groups, expected)


def _observations_by_arrays(zmax, zmin, count, segment, support_px, k_fixed, empty_is_low):
    """The fit's observations and starting levels as whole-array numpy code computes them (the
    reference of the compiled pass: pixels within ``support_px`` of the initial line, row by row)."""
    from pipeline.quantiles import linear_quantiles

    n0 = np.asarray(segment.normal, dtype=np.float64)
    pts = np.stack([segment.cols + 0.5, segment.rows + 0.5], axis=1)
    rho0 = float((pts @ n0).mean())
    along0 = np.array([n0[1], -n0[0]])
    t = pts @ along0
    t_lo, t_hi = float(t.min()) + 1.0, float(t.max()) - 1.0
    pad = int(math.ceil(support_px)) + 2
    h, w = zmax.shape
    r0, r1 = max(int(segment.rows.min()) - pad, 0), min(int(segment.rows.max()) + pad + 1, h)
    c0, c1 = max(int(segment.cols.min()) - pad, 0), min(int(segment.cols.max()) + pad + 1, w)
    xc, yc = (np.arange(c0, c1) + 0.5)[None, :], (np.arange(r0, r1) + 0.5)[:, None]
    d0 = xc * n0[0] + yc * n0[1] - rho0
    tt = xc * along0[0] + yc * along0[1]
    rows, cols = np.nonzero((np.abs(d0) <= support_px) & (tt >= t_lo) & (tt <= t_hi))
    x, y, d = xc[0, cols], yc[rows, 0], d0[rows, cols]
    zx = zmax[r0:r1, c0:c1][rows, cols]
    zn = zmin[r0:r1, c0:c1][rows, cols] if zmin is not None else np.full(len(zx), np.nan)
    k = count[r0:r1, c0:c1][rows, cols].astype(np.float64) if count is not None else np.full(len(zx), k_fixed)
    measured = np.isfinite(zx)
    if measured.sum() < 6 or (d[measured] < 0).sum() < 3 or (d[measured] > 0).sum() < 3:
        return None
    lows = np.concatenate([zn[measured & (d < -0.5)], zx[measured & (d < -0.5)]])
    lows = lows[np.isfinite(lows)]
    highs = zx[measured & (d > 0.5)]
    low0 = linear_quantiles(lows, (0.2,))[0] if len(lows) else float(np.nanmin(zx))
    high0 = linear_quantiles(highs, (0.8,))[0] if len(highs) else float(np.nanmax(zx))
    has_min = measured & np.isfinite(zn)
    empty = ~measured if empty_is_low else np.zeros(len(zx), bool)
    arrays = (
        x[measured], y[measured], np.maximum(k[measured], 1.0), zx[measured],
        x[has_min], y[has_min], np.maximum(k[has_min], 1.0), zn[has_min],
        x[empty], y[empty],
    )  # fmt: skip
    return arrays, low0, high0, int(measured.sum() + has_min.sum()), len(zx)


@pytest.mark.parametrize("seed", range(8))
def test_compiled_observations_are_the_array_versions(seed):
    """The compiled support pass gives, bit for bit, the pixels, values and levels of whole-array
    numpy code, with and without lowest points and counts, empty pixels low or not; walls along
    the rows and columns put pixel centres exactly at the support's edge."""
    from pipeline.holes import walls as W

    rng = np.random.default_rng(seed)
    angle = float(rng.uniform(0, 360)) if seed % 2 else 90.0 * (seed // 2)
    zmax, zmin, count = binned_points(40, angle, centred_offset(angle), density=float(rng.uniform(1, 12)), seed=seed)
    segments = wall_segments(height_jumps(zmax, zmin, jump_threshold=2.0), zmax)
    assert segments
    checked = 0
    for segment in segments:
        n0 = np.asarray(segment.normal, dtype=np.float64)
        rho0 = W._initial_line(segment)[2]
        cases = [(zmin, count, True, 3.0), (None, None, False, 2.5), (zmin, None, False, 2.0), (zmin, count, True, 2.5)]
        for low_points, counts, empty_is_low, support_px in cases:
            want = _observations_by_arrays(zmax, low_points, counts, segment, support_px, 8.0, empty_is_low)
            got = W._observe(
                zmax, low_points, counts, segment, n0, rho0, support_px=support_px, pixel_values="extremes",
                points_per_pixel=8.0, empty_is_low=empty_is_low,
            )  # fmt: skip
            if want is None or not want[2] > want[1]:
                assert got is None
                continue
            arrays, low0, high0, n_measured, n_support = got
            assert (low0, high0, n_measured, n_support) == want[1:]
            assert len(arrays) == 11 and arrays[10] is W.LOGISTIC_NODES
            for a, b in zip(arrays[:10], want[0], strict=True):
                assert a.dtype == np.float64 and np.array_equal(a, b)
            checked += 1
    assert checked


def test_compiled_quantile_is_numpys():
    from pipeline.holes.walls import _linear_quantile

    rng = np.random.default_rng(3)
    for n in (1, 2, 5, 17, 100):
        values = rng.normal(0, 10, n).round(rng.integers(0, 3))  # ties too
        for q in (0.0, 0.2, 0.5, 0.8, 1.0):
            assert _linear_quantile(values, q) == np.quantile(values, q)
