"""Hydro-flattening: lakes one level, rivers flat across and stepping down along their course."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.fill import METHOD_CODES, FillSettings, WaterEdge, river_surfaces
from pipeline.fill.by_cause import WATER, FillParams, fill_hole

PIXEL = 0.5  # metres
EDGE = WaterEdge(tolerance=0.15, min_share=0.1, max_slope=0.05 * PIXEL)  # 5 %: none of the scenes is capped


def params(**kwargs) -> FillParams:
    values = dict(method="auto", by_cause=True, pixel_size=PIXEL, max_distance=50.0,
                  jump_threshold=2.0, settings=FillSettings(), river_min_drop=0.25, river_min_elongation=4.0,
                  water_edge=EDGE)  # fmt: skip
    return FillParams(**(values | kwargs))


def river_scene(fall_per_100m: float, *, seed: int = 1, rows: int = 140, cols: int = 640):
    """A meandering west-east river, 10 m wide, water falling eastwards; banks rising from the water's edge.

    The water surface falls with the arc length ``s`` along the centre line, so it is
    flat on every section perpendicular to the course. Returns the DSM of the land (NaN
    on water), the water mask, the true water surface, ``s`` and the distance from the
    centre line at every pixel.
    """
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    r, c = np.indices((rows, cols))
    u, v = (c + 0.5) * PIXEL, (rows - r - 0.5) * PIXEL
    line_u = np.arange(-20.0, cols * PIXEL + 20.0, 0.05)
    line_v = 35.0 + 8.0 * np.sin(2 * np.pi * line_u / 160.0)
    line_s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(line_u), np.diff(line_v)))])
    offset, nearest = cKDTree(np.column_stack([line_u, line_v])).query(np.column_stack([u.ravel(), v.ravel()]))
    offset, chainage = offset.reshape(u.shape), line_s[nearest].reshape(u.shape)
    level = 50.0 - fall_per_100m / 100.0 * chainage
    water = offset < 5.0
    land = level + 0.4 * (offset - 5.0) + rng.normal(0, 0.02, level.shape)
    trees = rng.random(level.shape) < 0.05
    land = np.where(trees, land + 4.0, land)  # vegetation on the banks: high outliers
    return np.where(water, np.nan, land), water, level, chainage, offset


def fill(dsm, water, **kwargs):
    measured = np.isfinite(dsm)
    return fill_hole(dsm, dsm, measured, water.astype(np.int32), WATER, params(**kwargs))


@pytest.mark.parametrize("fall", [0.5, 1.0, 2.0, -1.0])
def test_a_river_steps_down_along_its_course(fall):
    dsm, water, level, chainage, offset = river_scene(fall)
    out = fill(dsm, water)
    heights = out.heights
    assert np.isfinite(heights[water]).all()
    assert (out.method_code[water] == METHOD_CODES["river"]).all()
    assert out.components[0].method == "river" and "river: falls" in out.components[0].detail
    # never rises downstream: along the centre line (one pixel per column), the way the water flows
    centre = water & (offset < 0.25)
    downstream = np.argsort(chainage[centre] if fall > 0 else -chainage[centre])
    assert centre.sum() == water.shape[1]
    assert (np.diff(heights[centre][downstream]) <= 0).all()
    # flat across: every section perpendicular to the course (0.25 m thick) within 2 cm
    section = np.floor(chainage[water] / 0.25)
    spread = [np.ptp(heights[water][section == k]) for k in np.unique(section)]
    assert max(spread) <= 0.02, max(spread)
    # within 0.05 m of the true water surface, 2 cm RMSE (the banks' lower envelope sits ~2 cm above it)
    assert np.abs(heights[water] - level[water]).max() <= 0.05
    assert np.sqrt(np.mean((heights[water] - level[water]) ** 2)) <= 0.02


def test_one_flat_level_would_miss_the_river():
    dsm, water, level, _, _ = river_scene(1.0)
    flat = fill(dsm, water, river_min_drop=np.inf).heights
    assert np.ptp(flat[water]) == 0 and np.abs(flat[water] - level[water]).max() > 1.0


def test_a_flat_river_is_one_level_at_its_edge():
    dsm, water, level, _, _ = river_scene(0.0)
    out = fill(dsm, water)
    assert np.ptp(out.heights[water]) == 0.0
    assert (out.method_code[water] == METHOD_CODES["flat"]).all()
    assert abs(out.heights[water][0] - level[water][0]) <= 0.03  # the bank's lower envelope, 2 cm of noise


def test_a_lake_on_a_slope_stays_one_level():
    """A round lake: its rim may differ around it (a slope), it is still one level."""
    rng = np.random.default_rng(3)
    r, c = np.indices((120, 120))
    lake = (r - 60) ** 2 + (c - 60) ** 2 < 40**2
    dsm = np.where(lake, np.nan, 20.0 + 0.02 * c + rng.normal(0, 0.02, lake.shape))
    out = fill(dsm, lake)
    assert np.ptp(out.heights[lake]) <= 0.02
    assert (out.method_code[lake] == METHOD_CODES["flat"]).all()
    _, fits = river_surfaces(dsm, lake.astype(np.int32), edge=EDGE, min_drop=0.25)
    assert not fits[0].is_river and fits[0].elongation < 2.0


def test_rivers_and_lakes_in_one_call_are_independent():
    dsm, water, level, _, _ = river_scene(1.0)
    labels = water.astype(np.int32)
    r, c = np.indices(water.shape)
    pond = ((r - 10) ** 2 + (c - 300) ** 2 < 6**2) & ~water
    labels[pond] = 2
    dsm = np.where(pond, np.nan, dsm)
    both = fill_hole(dsm, dsm, np.isfinite(dsm), labels, WATER, params())
    alone = fill(np.where(pond, dsm[10, 290], dsm), water)
    assert np.ptp(both.heights[pond]) == 0
    assert (both.method_code[pond] == METHOD_CODES["flat"]).all()
    assert np.allclose(both.heights[water], alone.heights[water])


def test_elongation_and_drop_rules():
    dsm, water, _, _, _ = river_scene(1.0)
    _, fits = river_surfaces(dsm, water.astype(np.int32), edge=EDGE, min_drop=0.25)
    assert fits[0].is_river and 3.0 < fits[0].drop < 3.5 and fits[0].elongation > 20  # 330 m at 1 %
    _, fits = river_surfaces(dsm, water.astype(np.int32), edge=EDGE, min_drop=10.0)
    assert not fits[0].is_river
    _, fits = river_surfaces(dsm, water.astype(np.int32), edge=EDGE, min_drop=0.25, min_elongation=1000.0)
    assert not fits[0].is_river


def test_the_holes_layer_names_a_river():
    """The hole's record (its ``fill_method`` and ``fill_note`` in the holes layer) says river."""
    from pipeline.fill.by_cause import FILLED, hole_record

    dsm, water, _, _, _ = river_scene(1.0)
    labels = water.astype(np.int32)
    out = fill(dsm, water)
    record = hole_record(7, 1, labels, out, np.ones(water.shape), "fill.npz")
    assert record.status == FILLED and record.method == "river" and record.detail.startswith("river: falls 3.")
    # its error: the spread of the bank heights its stations agreed on (2 cm noise, banks rising 0.4 m/m)
    assert 0.01 <= record.error_estimate <= 0.1, record.error_estimate


def test_a_step_between_stations_is_told_from_their_noise():
    """A weir stands out of the stations' falls; one noisy station (a fall too much, the next too little) does not."""
    from pipeline.fill.hydro import _measured_steps

    rng = np.random.default_rng(4)
    centres = np.arange(30) * 18.0
    errors = np.full(30, 0.007)  # 3 cm noise over ~18 water returns a station
    for trial in range(20):
        levels = 50.0 - 0.01 * centres + rng.normal(0, 0.007, 30)
        assert not _measured_steps(centres, levels, errors).any(), trial
        weir = levels - np.where(centres > 250, 0.3, 0.0)
        steps = _measured_steps(centres, weir, errors)
        assert steps.tolist() == [c == 234.0 for c in centres[:-1]], trial  # the gap from 234 to 252 only


def test_a_weir_keeps_its_step_and_the_reaches_stay_smooth():
    dsm, water, level, chainage, offset = river_scene(0.5)
    weir = np.where(chainage > 160.0, 0.3, 0.0)  # the water and its banks drop 0.3 m past 160 m
    dsm, level = dsm - weir, level - weir
    heights = fill(dsm, water).heights
    far = water & (np.abs(chainage - 160.0) > 20.0)
    assert np.abs(heights[far] - level[far]).max() <= 0.06
    above, below = water & (np.abs(chainage - 150.0) < 1.0), water & (np.abs(chainage - 170.0) < 1.0)
    assert np.median(heights[above]) - np.median(heights[below]) >= 0.25
