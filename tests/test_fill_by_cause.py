"""How a hole is filled by its cause (pipeline.fill.by_cause), on 5 x 5 arrays.

The rule of docs/filling.md, "Fill by cause": water flat at its rim's lowest returns,
an occlusion (and a small void) from the low side of its rim only, everything else
from the whole rim with the configured method; ``fill.by_cause = false`` fills every
hole from its whole rim.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.fill import METHOD_CODES, NOT_FILLED, FillSettings
from pipeline.fill.by_cause import (
    FILLED,
    LOW_SIDE,
    NO_RETURN,
    NO_SUPPORT,
    OCCLUSION,
    RIM,
    SMALL_VOID,
    WATER,
    FillParams,
    fill_hole,
    fill_kind,
    hole_ids_of_labels,
    hole_record,
)


def params(**kwargs) -> FillParams:
    values = dict(method="idw", by_cause=True, pixel_size=1.0, max_distance=50.0,
                  jump_threshold=2.0, settings=FillSettings(estimate_error=False))  # fmt: skip
    return FillParams(**(values | kwargs))


def centre_hole() -> np.ndarray:
    """Labels of a 5 x 5 window: one 3 x 3 hole in the middle."""
    labels = np.zeros((5, 5), np.int32)
    labels[1:4, 1:4] = 1
    return labels


def beside_a_building() -> tuple[np.ndarray, np.ndarray]:
    """A roof 10 m high on the two western columns, ground at 0 m east of it; the hole at the wall's foot."""
    heights = np.zeros((5, 5))
    heights[:, :2] = 10.0
    labels = np.zeros((5, 5), np.int32)
    labels[1:4, 2] = 1
    return heights, labels


@pytest.mark.parametrize(
    ("cause", "kind"),
    [
        ("water", WATER),
        (OCCLUSION, LOW_SIDE),
        (SMALL_VOID, LOW_SIDE),
        ("missed_coverage", RIM),
        ("no_return", RIM),
        ("covered", RIM),
        ("unknown", RIM),
    ],
)
def test_each_cause_has_its_kind_of_fill(cause, kind):
    assert fill_kind(cause, params()) == kind
    assert fill_kind(cause, params(by_cause=False)) == RIM
    # a bare-earth model (a DTM) holds no object whose top could stand on a rim: terrain all round
    assert fill_kind(cause, params(bare_earth=True)) == (WATER if cause == "water" else RIM)


@pytest.mark.parametrize(
    ("keep", "bare"),
    [
        ((), False),
        ((2,), True),
        ((2, 9), True),
        ((2, 8, 9, 10, 11), True),
        ((2, 6), False),
        ((2, 18), True),
        ((5,), False),
    ],
)
def test_a_bare_earth_model_keeps_only_bare_earth_classes(keep, bare):
    """``filter.keep_classes`` of ground, key-points, water, rail, road only (noise dropped anyway)."""
    from pipeline.rasterize import PointFilter

    assert PointFilter(drop_classes=(7, 18), keep_classes=keep).bare_earth is bare


def test_a_water_hole_is_flat_at_its_rims_lowest_returns():
    labels = centre_hole()
    measured = labels == 0
    rim = measured & (np.abs(np.indices((5, 5)) - 2).min(axis=0) < 2)  # 4-adjacent to the hole: no corner
    zmax = np.where(measured, 10.0, np.nan)  # reeds on the bank: the highest returns
    zmin = np.where(measured, 2.0 + 0.1 * np.arange(25).reshape(5, 5), np.nan)  # the water's edge: the lowest
    out = fill_hole(zmax, zmin, measured, labels, fill_kind("water", params()), params())
    hole = labels > 0
    assert np.ptp(out.heights[hole]) == 0.0  # one level
    # no level agreed on by 3 rim pixels within 0.15: the rim's 10th percentile (its lower envelope)
    assert out.heights[2, 2] == pytest.approx(np.percentile(zmin[rim], 10))
    assert out.heights[2, 2] < 3.0
    assert (out.method_code[hole] == METHOD_CODES["flat"]).all()
    assert (out.method_code[measured] == 0).all()  # measured pixels untouched


def test_without_by_cause_a_water_hole_is_filled_from_its_whole_rim():
    labels = centre_hole()
    measured = labels == 0
    zmax, zmin = np.where(measured, 10.0, np.nan), np.where(measured, 2.0, np.nan)
    out = fill_hole(zmax, zmin, measured, labels, fill_kind("water", params(by_cause=False)), params(by_cause=False))
    assert np.allclose(out.heights[labels > 0], 10.0)
    assert (out.method_code[labels > 0] == METHOD_CODES["idw"]).all()


@pytest.mark.parametrize("cause", [OCCLUSION, SMALL_VOID])
def test_an_occlusion_is_filled_from_the_ground_not_ramped_to_the_roof(cause):
    heights, labels = beside_a_building()
    measured = labels == 0
    low = fill_hole(heights, heights, measured, labels, fill_kind(cause, params()), params())
    assert np.allclose(low.heights[labels > 0], 0.0)
    whole = fill_hole(heights, heights, measured, labels, RIM, params())
    assert whole.heights[labels > 0].max() > 1.0  # from the whole rim the roof pulls the fill up


def test_a_fill_is_clamped_to_its_rims_heights():
    """A dome's top under the hole: MLS reconstructs it above the rim; fill.clamp_to_rim keeps it within."""
    labels = centre_hole()
    measured = labels == 0
    r, c = np.indices((5, 5))
    dome = np.where(measured, 10.0 - (r - 2.0) ** 2 - (c - 2.0) ** 2, np.nan)  # rim 2 to 6 m
    free = fill_hole(dome, dome, measured, labels, RIM, params(method="mls", clamp_to_rim=False))
    assert free.heights[2, 2] == pytest.approx(10.0)
    clamped = fill_hole(dome, dome, measured, labels, RIM, params(method="mls"))
    assert np.nanmax(clamped.heights[labels > 0]) == pytest.approx(6.0)
    assert (clamped.method_code[labels > 0] == METHOD_CODES["mls"]).all()


def test_a_hole_without_a_measured_rim_is_not_filled():
    labels = np.ones((5, 5), np.int32)
    measured = np.zeros((5, 5), bool)
    nothing = np.full((5, 5), np.nan)
    out = fill_hole(nothing, nothing, measured, labels, RIM, params())
    assert np.isnan(out.heights).all() and (out.method_code == NOT_FILLED).all()
    record = hole_record(4, 1, labels, out, np.zeros((5, 5)), "fill.npz")
    assert record.status == NO_SUPPORT and record.pixels == 0 and record.result_path is None


def test_the_holes_record_of_a_fill():
    labels = centre_hole()
    measured = labels == 0
    zmax, zmin = np.where(measured, 10.0, np.nan), np.where(measured, 2.0, np.nan)
    out = fill_hole(zmax, zmin, measured, labels, WATER, params())
    distance = np.arange(25, dtype=float).reshape(5, 5)
    record = hole_record(7, 1, labels, out, distance, "fill.npz")
    assert record.hole_id == 7 and record.status == FILLED and record.result_path == "fill.npz"
    assert record.method == "flat" and record.pixels == 9
    assert record.max_distance == 18.0  # the farthest hole pixel, (3, 3)
    assert not record.degraded and record.error_estimate == 0.0  # water: the spread of its edge, a level ring


def test_hole_ids_of_labels():
    labels = np.array(
        [
            [0, 1, 1, 0, 0],
            [0, 1, 0, 2, 2],
            [-1, -1, 0, 2, 0],
            [0, 0, 0, 0, 3],
            [0, 0, 0, 0, 0],
        ]
    )
    hole_of_label = np.array([0, 7, 9, -1])  # part label -> hole id; the last entry serves label -1
    ids = hole_ids_of_labels(labels, hole_of_label)
    expected = np.where(labels == 1, 7, np.where(labels == 2, 9, np.where(labels == -1, -1, 0)))
    assert (ids == expected).all()  # label 3 lies beyond the lookup: no hole


def test_settled_voids_the_sensor_saw_unobstructed(tmp_path):
    """A cell's settled small voids (label -1) count as seen where a line of sight reached some of
    their pixels and none was blocked; they are kept beside the labels for the writer, which fills
    them from their whole rim (a no-return void) instead of the low side of a step."""
    from pipeline.grid import PixelWindow
    from pipeline.io.intermediate import load_labels, load_seen_voids, save_labels
    from pipeline.sensor.sight import BLOCKED, SEEN
    from pipeline.stages.detect_holes import seen_small_voids

    labels = np.zeros((8, 12), np.int32)
    labels[1:3, 1:3] = -1  # seen everywhere
    labels[5:7, 1:3] = -1  # seen, but one line of sight blocked: may hide ground behind a step
    labels[1:3, 6:9] = -1  # not judged (no class)
    labels[5:7, 6:9] = 4  # a listed hole's part: not a settled void
    sight = np.zeros(labels.shape, np.int8)
    sight[1:3, 1:3] = SEEN
    sight[5:7, 1:3] = SEEN
    sight[6, 2] = BLOCKED
    sight[5:7, 6:9] = SEEN
    seen = seen_small_voids(labels, sight)
    expected = np.zeros(labels.shape, bool)
    expected[1:3, 1:3] = True
    assert np.array_equal(seen, expected)
    path = tmp_path / "labels.npz"
    save_labels(path, labels, PixelWindow(0, 0, 8, 12), seen_voids=seen)
    assert np.array_equal(load_labels(path)[0], labels)
    assert np.array_equal(load_seen_voids(path), expected)
    save_labels(path, labels, PixelWindow(0, 0, 8, 12))  # not judged: none kept
    assert load_seen_voids(path) is None


def test_a_small_void_seen_unobstructed_is_filled_from_its_whole_rim():
    """At a step in a canopy a settled void is filled from the low side as an occlusion; seen
    unobstructed (a no-return void) from its whole rim: the crowns around it, not the gap below."""
    heights, labels = beside_a_building()
    measured = labels == 0
    hidden = fill_hole(heights, heights, measured, labels, fill_kind(SMALL_VOID, params()), params())
    seen = fill_hole(heights, heights, measured, labels, fill_kind(NO_RETURN, params()), params())
    assert np.allclose(hidden.heights[labels > 0], 0.0)
    assert seen.heights[labels > 0].min() > 1.0
