"""Tests of pipeline.survey.footprint: the data footprint that decides the default AOI."""

from __future__ import annotations

import numpy as np

from pipeline.survey.footprint import data_footprint


def test_data_footprint_diagonal_strip():
    n = 120
    r, c = np.mgrid[:n, :n]
    strip = np.abs(r - c) < 25  # a diagonal flight strip: most of the tile is empty
    occupied = strip.copy()
    occupied[50:60, 50:60] = False  # a void enclosed by data
    occupied[:, 80:84] &= False  # a missed line across the strip (opens to the outside)
    fp = data_footprint(occupied, closing_px=3)
    assert fp[55, 55] and fp[82, 82]  # enclosed void and bridged gap are inside
    assert not fp[5, 110] and not fp[110, 5]  # the empty corners are outside
    assert fp.sum() < 0.5 * n * n
    # without closing, the gap opening to the outside stays exterior
    assert not data_footprint(occupied, closing_px=0)[82, 82]
    assert data_footprint(occupied, closing_px=0)[55, 55]
