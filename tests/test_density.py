"""Density rules: pure functions of header counts."""

from __future__ import annotations

import math

import pytest

from pipeline.survey.density import (
    Density,
    auto_min_area_m2,
    auto_resolution_m,
    nominal_spacing_m,
    pulse_count,
    round_cell_size,
    supported_resolution_m,
)


@pytest.mark.parametrize(
    "pulses_per_m2, expected",
    [
        (64.0, 0.25),  # 4 per 0.25 m pixel exactly
        (63.9, 0.5),
        (20.0, 0.5),  # IGN LiDAR HD first returns: IGN's own 0.5 m DSM
        (10.0, 1.0),  # AHN, bcts
        (3.4, 2.0),  # yellowscan
        (0.28, 4.0),  # decimated IGN tiles
        (0.16, 5.0),
        (0.05, 10.0),
        (0.001, 10.0),  # sparser than anything listed: the coarsest
    ],
)
def test_auto_resolution_is_the_finest_size_with_four_first_returns(pulses_per_m2, expected):
    assert auto_resolution_m(pulses_per_m2) == expected
    assert auto_resolution_m(pulses_per_m2) ** 2 * pulses_per_m2 >= 4 or expected == 10.0


def test_other_rules():
    assert auto_resolution_m(1.0, per_pixel=1.0) == 1.0
    assert supported_resolution_m(4.0) == 1.0 and supported_resolution_m(0.0) == math.inf
    assert nominal_spacing_m(4.0) == 0.5 and nominal_spacing_m(0) == math.inf
    assert auto_min_area_m2(0.1) == 4.0 and auto_min_area_m2(1.0) == 16.0 and auto_min_area_m2(math.inf) == 4.0


@pytest.mark.parametrize(
    "cell, resolution, expected",
    [(250.0, 1.0, (250.0, 250)), (250.0, 4.0, (248.0, 62)), (250.0, 10.0, (250.0, 25)), (100.0, 10.0, (160.0, 16))],
)
def test_cell_size_is_rounded_to_whole_pixels(cell, resolution, expected):
    assert round_cell_size(cell, resolution) == expected


def test_first_returns_only_when_the_header_counts_add_up():
    assert pulse_count(100, (60, 30, 10, 0, 0)) == (60, True)
    assert pulse_count(100, (0, 0, 0, 0, 0)) == (100, False)  # not filled in by the writer
    assert pulse_count(100, (200, 30)) == (100, False)  # counts of another file
    assert pulse_count(100, (0, 0, 0, 100)) == (100, False)  # no return numbered 1 (Geiger mode)
    assert pulse_count(100, ()) == (100, False)
    d = Density(points=1000, pulses=500, area_m2=250.0, first_returns=True)
    assert d.points_per_m2 == 4.0 and d.pulses_per_m2 == 2.0 and d.spacing_m == pytest.approx(1 / math.sqrt(2))
    assert d.as_record()["first_returns_per_m2"] == 2.0
