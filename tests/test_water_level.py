"""The level of water from its edge (pipeline.fill.water_level) and water holes filled at it."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.fill import METHOD_CODES, FillSettings, WaterEdge
from pipeline.fill.by_cause import WATER, FillParams, fill_hole
from pipeline.fill.water_level import edge_level, lowest_consistent_level, water_edge_heights

TOL, SHARE = 0.15, 0.1


def params(pixel: float = 1.0, max_slope: float = 0.02, **kwargs) -> FillParams:
    values = dict(method="auto", by_cause=True, pixel_size=pixel, max_distance=50.0, jump_threshold=2.0,
                  settings=FillSettings(), river_min_drop=0.25, river_min_elongation=4.0,
                  water_edge=WaterEdge(TOL, SHARE, max_slope * pixel), water_reach_px=3.0)  # fmt: skip
    return FillParams(**(values | kwargs))


def test_the_lowest_consistent_level_leaves_out_walls_trees_and_stray_lows():
    rng = np.random.default_rng(0)
    edge = 1.0 + rng.normal(0, 0.02, 40)  # the water's edge: 40 % of the ring
    quay = 2.5 + rng.normal(0, 0.05, 45)  # quay walls and bank tops
    trees = rng.uniform(6, 15, 12)  # crowns over the water
    strays = np.array([0.1, 0.3, -0.4])  # multipath below the water
    found = lowest_consistent_level(np.concatenate([quay, edge, trees, strays]), tolerance=TOL, min_share=SHARE)
    assert abs(found.level - 1.0) <= 0.02
    assert found.spread < 0.04 and 30 <= found.count <= 43
    # its 10th percentile (the old rule) is pulled down by the strays
    assert np.percentile(np.concatenate([quay, edge, trees, strays]), 10) < 0.99


def test_without_agreement_the_level_is_the_quantile_of_everything():
    heights = np.array([1.0, 2.0, 3.0, 4.0])
    found = lowest_consistent_level(heights, tolerance=TOL, min_share=SHARE, quantile=0.5)
    assert found.level == pytest.approx(2.5) and found.count == 4
    assert np.isnan(lowest_consistent_level(np.array([np.nan]), tolerance=TOL, min_share=SHARE).level)


def test_water_returns_decide_the_level_when_there_are_enough():
    ring = np.full(30, 0.6)  # a canal between quays: its ring is the quay top
    water = np.array([-0.47, -0.46, -0.45, -0.46, 0.9])  # class 9, one misclassified on the quay
    found = edge_level(ring, water, tolerance=TOL, min_share=SHARE)
    assert found.source == "water returns" and found.level == pytest.approx(-0.46) and found.count == 4
    few = edge_level(ring, water[:2], tolerance=TOL, min_share=SHARE)  # two: stray points, the ring decides
    assert few.source == "ring" and few.level == pytest.approx(0.6)


def test_water_returns_belong_to_the_hole_they_are_near():
    labels = np.zeros((7, 12), np.int32)
    labels[2:5, 1:4] = 1
    labels[2:5, 8:11] = 2
    zmin = np.where(labels > 0, np.nan, 0.0)
    water = np.zeros(labels.shape, np.uint16)
    water[0, 2] = 1  # two pixels above hole 1
    water[3, 6] = 1  # between the holes: three pixels from hole 1, two from hole 2
    ring, near = water_edge_heights(zmin, water, labels, reach_px=2.0)
    assert near[0, 2] == 1 and near[3, 6] == 2 and (near > 0).sum() == 2
    assert ring[1, 2] == 1 and ring[3, 7] == 2 and ring[0, 2] == 0 and (ring[labels > 0] == 0).all()


def canal(rows=40, cols=200, quay=0.8, water_level=-0.46, returns=True):
    """A canal 10 px wide between quay walls, class-9 returns on some pixels along its edge."""
    rng = np.random.default_rng(4)
    hole = np.zeros((rows, cols), bool)
    hole[15:25, :] = True
    zmax = np.where(hole, np.nan, quay + rng.normal(0, 0.02, hole.shape))
    zmax[5:35, 90:100] = 3.5  # a bridge across the canal (its deck measured, the water under it a hole)
    hole[5:35, 90:100] &= False
    hole[15:25, 90:100] = False
    zmin = zmax.copy()
    water = np.zeros(hole.shape, np.uint16)
    if returns:
        edge = np.zeros(hole.shape, bool)
        edge[[14, 25], :] = True
        edge &= rng.random(hole.shape) < 0.3
        edge[:, 85:105] = False
        zmin[edge] = water_level + rng.normal(0, 0.02, int(edge.sum()))
        water[edge] = 1
    return zmax, zmin, hole, water


def test_a_canal_between_quays_is_filled_at_its_water_returns():
    zmax, zmin, hole, water = canal()
    labels = np.zeros(hole.shape, np.int32)
    labels[:, :90][hole[:, :90]] = 1
    labels[:, 100:][hole[:, 100:]] = 2
    out = fill_hole(zmax, zmin, np.isfinite(zmax), labels, WATER, params(), water)
    assert np.abs(out.heights[hole] - (-0.46)).max() <= 0.02
    assert all(c.method == "flat" and c.error_estimate < 0.05 for c in out.components)
    assert "water returns" in out.components[0].detail
    # without water returns the ring is the only evidence: the quay top
    zmax, zmin, hole, _ = canal(returns=False)
    out = fill_hole(zmax, zmin, np.isfinite(zmax), labels, WATER, params())
    assert np.abs(out.heights[hole] - 0.8).max() <= 0.05


@pytest.mark.parametrize("across_m", [20, 100, 500])
def test_a_lake_of_any_size_is_filled_at_its_edge(across_m):
    """A lake in a hollow, banks rising 5 % from its edge, reeds on 10 % of the shore; water returns on some."""
    rng = np.random.default_rng(across_m)
    pixel = 2.0 if across_m == 500 else 1.0
    n = int(across_m / pixel) + 40
    r, c = np.indices((n, n))
    radius = np.hypot(r - n / 2, c - n / 2) * pixel
    lake = radius < across_m / 2
    ground = 12.0 + 0.05 * (radius - across_m / 2) + rng.normal(0, 0.02, lake.shape)
    ground = np.where(rng.random(lake.shape) < 0.1, ground + 2.0, ground)
    zmin = np.where(lake, np.nan, ground)
    out = fill_hole(zmin, zmin, ~lake, lake.astype(np.int32), WATER, params(pixel))
    assert np.ptp(out.heights[lake]) == 0.0 and (out.method_code[lake] == METHOD_CODES["flat"]).all()
    assert abs(out.heights[lake][0] - 12.0) <= 0.02


@pytest.mark.parametrize("fall_percent", [1.0, 8.0])
def test_a_river_falls_no_faster_than_water_can(fall_percent):
    """A straight river whose banks fall ``fall_percent``: at 8 % (a weir, walls) the surface is capped at 2 %."""
    rows, cols = 30, 300
    r, c = np.indices((rows, cols))
    hole = (r >= 10) & (r < 20)
    true = 20.0 - fall_percent / 100.0 * c
    zmin = np.where(hole, np.nan, true + 0.05 * (np.abs(r - 14.5) - 5))  # banks rising 5 % from the edge
    out = fill_hole(zmin, zmin, ~hole, hole.astype(np.int32), WATER, params())
    surface = out.heights[12]  # one row of the river, along its course
    steepest = np.max(np.abs(np.diff(surface)))
    assert steepest <= 0.02 + 1e-6
    assert (np.diff(surface) <= 1e-9).all()  # never rising downstream
    if fall_percent <= 2:
        assert out.components[0].method == "river"
        assert np.abs(out.heights[hole] - true[hole]).max() <= 0.03


def test_every_void_is_filled_but_missed_coverage_and_water_whatever_the_limits():
    from pipeline.fill.by_cause import MISSED, TOO_LARGE, unfilled_reason

    default = params(max_distance=float("inf"))  # as fill_params makes it from the default config
    assert unfilled_reason("unknown", area_m2=1e6, farthest=1e3, params=default) is None  # no limit by default
    assert unfilled_reason("missed_coverage", area_m2=10.0, farthest=1.0, params=default)[0] == MISSED
    asked = params(fill_missed_coverage=True)
    assert unfilled_reason("missed_coverage", area_m2=10.0, farthest=1.0, params=asked) is None
    limited = params(max_area_m2=1e4, max_distance=25.0)
    assert unfilled_reason("occlusion", area_m2=2e4, farthest=1.0, params=limited)[0] == TOO_LARGE
    assert unfilled_reason("no_return", area_m2=10.0, farthest=30.0, params=limited)[0] == TOO_LARGE
    assert unfilled_reason("water", area_m2=2e5, farthest=250.0, params=limited) is None


def test_a_pixel_of_water_returns_only_gives_its_mid_range():
    """Several noisy returns per pixel: the lowest lies below the water by about the noise, the mid-range does not."""
    rng = np.random.default_rng(2)
    hole = np.zeros((30, 30), bool)
    hole[8:22, 8:22] = True
    returns = -0.46 + rng.normal(0, 0.03, (6, *hole.shape))  # six returns per pixel, 3 cm noise
    zmin, zmax = returns.min(axis=0), returns.max(axis=0)
    edge = ~hole & (np.abs(np.indices(hole.shape) - 14.5).max(axis=0) < 10)  # a band of water returns round it
    zmin, zmax = np.where(hole, np.nan, np.where(edge, zmin, 1.0)), np.where(hole, np.nan, np.where(edge, zmax, 1.0))
    counts = np.where(hole, 0, 6).astype(np.uint32)
    water = np.where(edge, 6, 0).astype(np.uint16)
    labels = hole.astype(np.int32)
    mid = fill_hole(zmax, zmin, ~hole, labels, WATER, params(), water, counts).heights[hole][0]
    low = fill_hole(zmax, zmin, ~hole, labels, WATER, params(), water).heights[hole][0]
    assert abs(mid - (-0.46)) <= 0.01 and low < -0.46 - 0.02


def test_pixels_with_bank_returns_too_are_left_out_where_pure_ones_are_enough():
    """A pixel of water and bank returns gives only its lowest (the lowest of its water returns): below the water."""
    rng = np.random.default_rng(3)
    hole = np.zeros((40, 40), bool)
    hole[10:30, 10:30] = True
    near = ~hole & (np.abs(np.indices(hole.shape) - 19.5).max(axis=0) < 13)  # 3 px of water returns round it
    inner = ~hole & (np.abs(np.indices(hole.shape) - 19.5).max(axis=0) < 11)  # the 1 px band next to the hole
    water_returns = -0.46 + rng.normal(0, 0.03, (3, *hole.shape))  # three water returns per pixel, 3 cm noise
    # the outer two pixels of the band hold bank returns too (a metre up): only their lowest tells of the water
    mixed = near & ~inner
    zmin = np.where(near, water_returns.min(axis=0), 1.0)
    zmax = np.where(inner, water_returns.max(axis=0), 1.0)
    zmin, zmax = np.where(hole, np.nan, zmin), np.where(hole, np.nan, zmax)
    water = np.where(near, 3, 0).astype(np.uint16)
    counts = np.where(hole, 0, np.where(mixed, 5, 3)).astype(np.uint32)
    labels = hole.astype(np.int32)
    level = fill_hole(zmax, zmin, ~hole, labels, WATER, params(), water, counts).heights[hole][0]
    assert abs(level - (-0.46)) <= 0.01  # from the pure pixels' mid-ranges alone
    # without pure pixels enough (a hole with no band of water returns only), the mixed ones still count
    water_only_mixed = np.where(inner, 0, water).astype(np.uint16)
    counts_only_mixed = np.where(inner, 3, counts).astype(np.uint32)
    zmin_only_mixed = np.where(inner, 1.0, zmin)
    zmin_only_mixed[hole] = np.nan
    level = fill_hole(zmax, zmin_only_mixed, ~hole, labels, WATER, params(), water_only_mixed, counts_only_mixed)
    assert -0.46 - 0.06 < level.heights[hole][0] < -0.46 - 0.01  # the lowest of three: about 0.85 x 3 cm low
