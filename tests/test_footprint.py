"""Tests of pipeline.survey.footprint: the data footprint that decides the default AOI."""

from __future__ import annotations

import numpy as np

from pipeline.survey.footprint import data_footprint, edge_voids


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


def _area_with_margin(shape: tuple[int, int], margin: int = 1) -> np.ndarray:
    """A rectangular survey area filling the map but for ``margin`` blocks beyond its cut all round."""
    in_area = np.zeros(shape, bool)
    in_area[margin:-margin, margin:-margin] = True
    return in_area


def test_a_canal_crossing_the_cut_lies_between_data_and_is_inside():
    in_area = _area_with_margin((40, 40))
    occupied = in_area.copy()
    occupied[1:12, 18:23] = False  # a canal from the top cut into the survey, data on both banks
    footprint = data_footprint(occupied, closing_px=0) & in_area
    assert not footprint[5, 20]  # the footprint alone leaves it outside: it opens to the outside
    cut_open = edge_voids(footprint, in_area)
    assert cut_open[1:12, 18:23].all() and cut_open.sum() == 11 * 5


def test_a_tile_s_empty_corner_and_the_margin_of_the_last_line_stay_outside():
    in_area = _area_with_margin((60, 60))
    r, c = np.mgrid[:60, :60]
    strip = (np.abs(r - c) < 12) & in_area  # a diagonal strip: two empty corners that turn the tile's corners
    footprint = data_footprint(strip, closing_px=0)
    assert not edge_voids(footprint, in_area).any()
    # the survey's last line stops halfway: the empty margin beside it meets the right cut and the
    # bottom cut, so it turns the tile's corner (data on one side of it only)
    partial = in_area.copy()
    partial[30:59, 50:59] = False
    footprint = data_footprint(partial, closing_px=0)
    assert not edge_voids(footprint, in_area).any()


def test_a_void_whose_contact_steps_or_reaches_the_unknown_is_not_judged():
    in_area = _area_with_margin((30, 30))
    occupied = in_area.copy()
    occupied[1:8, 10:15] = False  # cut open by the top edge ...
    in_area_stepped = in_area.copy()
    in_area_stepped[1, 12:15] = False  # ... where the area's edge steps: no straight cut
    footprint = data_footprint(occupied, closing_px=0) & in_area_stepped
    assert not edge_voids(footprint, in_area_stepped).any()
    # the area goes on beyond the map (no margin beyond the cut): the void is not judged
    in_area_open = np.ones((30, 30), bool)
    footprint = data_footprint(occupied, closing_px=0)
    assert not edge_voids(footprint, in_area_open).any()
