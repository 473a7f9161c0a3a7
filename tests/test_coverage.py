"""Coverage gaps between flight-line bands (pipeline.holes.coverage)."""

from __future__ import annotations

import numpy as np

from pipeline.grid import PixelWindow
from pipeline.holes.coverage import IN_GAP, IN_SWATH, UNKNOWN, coverage_gaps, keep_void_gaps
from pipeline.holes.flight_lines import line_moments, merge_line_moments


def _lines(width: int = 300, height: int = 200) -> np.ndarray:
    """Three north-south bands of 80 columns; the middle one is missing (id -1)."""
    ids = np.full((height, width), -1, np.int64)
    ids[:, 0:80] = 0
    ids[:, 160:240] = 2
    return ids


def test_a_missed_line_leaves_a_gap_between_its_neighbours():
    ids = _lines()
    gaps = coverage_gaps(line_moments(ids, row_off=0, col_off=0))
    assert len(gaps.bands) == 2 and len(gaps.gaps) == 1
    classes = gaps.classes(PixelWindow(0, 0, 200, 300), margin_px=0.0)
    assert (classes[:, 80:160] == IN_GAP).all()
    assert (classes[:, 0:80] == IN_SWATH).all() and (classes[:, 160:240] == IN_SWATH).all()
    assert (classes[:, 240:] == UNKNOWN).all()


def test_gaps_do_not_depend_on_how_the_moments_are_cut():
    ids = _lines()
    whole = coverage_gaps(line_moments(ids, row_off=0, col_off=0))
    pieces = [
        line_moments(ids[r : r + 50, c : c + 64], row_off=r, col_off=c)
        for r in range(0, 200, 50)
        for c in range(0, 300, 64)
    ]
    cut = coverage_gaps(merge_line_moments(pieces))
    window = PixelWindow(0, 0, 200, 300)
    assert np.array_equal(whole.classes(window), cut.classes(window))


def test_touching_lines_leave_no_gap():
    ids = np.zeros((200, 240), np.int64)
    ids[:, 80:160] = 1
    ids[:, 160:] = 2
    gaps = coverage_gaps(line_moments(ids, row_off=0, col_off=0))
    assert len(gaps.bands) == 3 and not gaps.gaps


def _checked(ids: np.ndarray, empty: np.ndarray, cuts: int = 1):
    """The gaps of ``ids`` checked against the empty pixels, counted over ``cuts`` x ``cuts`` windows."""
    gaps = coverage_gaps(line_moments(ids, row_off=0, col_off=0))
    h, w = ids.shape
    rows, cols = np.linspace(0, h, cuts + 1).astype(int), np.linspace(0, w, cuts + 1).astype(int)
    counts = sum(
        gaps.void_counts(PixelWindow(r0, c0, r1 - r0, c1 - c0), empty[r0:r1, c0:c1])
        for r0, r1 in zip(rows[:-1], rows[1:])
        for c0, c1 in zip(cols[:-1], cols[1:])
    )
    return gaps, keep_void_gaps(gaps, counts)


def test_a_missed_strip_is_kept_whatever_the_windows():
    ids = _lines()
    gaps, kept = _checked(ids, ids < 0)
    assert kept.gaps == gaps.gaps and len(kept.gaps) == 1
    assert _checked(ids, ids < 0, cuts=3)[1].gaps == kept.gaps


def test_a_lake_on_the_seam_of_two_lines_opens_no_gap():
    # two touching bands; a lake across their seam takes pixels from both and narrows them
    ids = np.zeros((200, 160), np.int64)
    ids[:, 80:] = 1
    lake = (np.arange(200)[:, None] - 100) ** 2 / 40**2 + (np.arange(160)[None, :] - 80) ** 2 / 12**2 < 1
    ids[lake] = -1
    gaps, kept = _checked(ids, lake)
    assert gaps.gaps and not kept.gaps  # a sliver of "gap" opened, and it is mostly measured ground


def test_only_the_windows_a_gap_reaches_are_checked():
    gaps = coverage_gaps(line_moments(_lines(), row_off=0, col_off=0))  # the gap: columns 80-160
    assert gaps.checked_near(PixelWindow(0, 64, 64, 64))
    assert gaps.checked_near(PixelWindow(100, 158, 20, 20))  # its flank only
    assert not gaps.checked_near(PixelWindow(0, 0, 64, 64))
    assert not gaps.checked_near(PixelWindow(0, 170, 64, 64))


def test_an_extent_strip_is_near_the_windows_it_meets(rng):
    """checked_near's strips: every window that meets a strip or its flank, and no other (random boxes)."""
    import dataclasses

    def box() -> PixelWindow:
        r, c = rng.integers(-50, 200, 2)
        return PixelWindow(int(r), int(c), int(rng.integers(0, 40)), int(rng.integers(0, 40)))

    gaps = dataclasses.replace(
        coverage_gaps(line_moments(np.zeros((1, 1), np.int64) - 1, row_off=0, col_off=0)),
        extent_strips=tuple((box(), box()) for _ in range(12)),
    )
    assert not gaps.gaps
    for _ in range(500):
        window = box()
        meets = any(not region.intersection(window).is_empty for pair in gaps.extent_strips for region in pair)
        assert gaps.checked_near(window) == meets


def test_a_task_s_slice_of_the_gaps_classes_and_counts_its_window_as_the_whole(rng):
    """CoverageGaps.near: the gaps, bands, missing tiles, extents and strips a window needs give its
    classes and (scattered back by the strips' indices) its void counts as the survey's do."""
    import dataclasses

    def box(size: int = 60) -> PixelWindow:
        r, c = rng.integers(-20, 240, 2)
        return PixelWindow(int(r), int(c), int(rng.integers(1, size)), int(rng.integers(1, size)))

    ids = _lines()
    whole = dataclasses.replace(
        coverage_gaps(line_moments(ids, row_off=0, col_off=0)),
        missing_tiles=tuple(box(30) for _ in range(5)),
        tile_extents=tuple(box() for _ in range(30)),
        extent_strips=tuple((box(20), box(20)) for _ in range(25)),
    )
    assert whole.gaps
    for _ in range(60):
        window = box(90)
        if window.is_empty:
            continue
        part, strips = whole.near(window)
        assert len(part.extent_strips) == len(strips) < len(whole.extent_strips)
        assert np.array_equal(part.classes(window), whole.classes(window))
        inner = PixelWindow(window.row_off + 1, window.col_off + 1, max(window.height - 2, 0), max(window.width - 2, 0))
        if not inner.is_empty:
            assert np.array_equal(part.classes(inner), whole.classes(inner))
        empty = rng.random(window.shape) < 0.5
        full = whole.void_counts(window, empty)
        sliced = part.void_counts(window, empty)
        n = len(whole.gaps)
        assert np.array_equal(sliced[:n], full[:n])
        assert np.array_equal(sliced[n:], full[n + strips])
        others = np.setdiff1d(np.arange(len(whole.extent_strips)), strips)
        assert not full[n + others].any()  # the strips left out count nothing in the window
