"""Flight-line directions from per-pixel line ids: mergeable moments, principal axis."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.holes.flight_lines import axial_mean, line_azimuths, line_moments, merge_line_moments


def strip_raster(shape, azimuth_deg, width_px, line_id):
    """A straight strip through the raster centre at an azimuth (clockwise from north)."""
    rows, cols = np.indices(shape)
    east, north = cols - shape[1] / 2, -(rows - shape[0] / 2)
    a = np.radians(azimuth_deg)
    across = east * np.cos(a) - north * np.sin(a)
    return np.where(np.abs(across) < width_px / 2, line_id, -1)


@pytest.mark.parametrize("azimuth", [0.0, 30.0, 90.0, 135.0])
def test_strip_direction_is_found_whatever_the_cells(azimuth):
    ids = strip_raster((300, 400), azimuth, 20, 7)
    whole = line_azimuths(line_moments(ids, row_off=100, col_off=50))
    pieces = [
        line_moments(ids[r : r + 64, c : c + 64], row_off=100 + r, col_off=50 + c)
        for r in range(0, 300, 64)
        for c in range(0, 400, 64)
    ]
    merged = line_azimuths(merge_line_moments(pieces))
    assert merged[7] == pytest.approx(whole[7], abs=1e-6)
    assert min(abs(merged[7] - azimuth), 180 - abs(merged[7] - azimuth)) < 1.0


def test_round_blobs_have_no_direction_and_axial_mean_wraps():
    rows, cols = np.indices((100, 100))
    blob = np.where((rows - 50) ** 2 + (cols - 50) ** 2 < 400, 3, -1)
    assert line_azimuths(line_moments(blob, row_off=0, col_off=0)) == {}
    assert axial_mean([179.0, 1.0], [1.0, 1.0]) == pytest.approx(0.0, abs=1e-9) or axial_mean(
        [179.0, 1.0], [1.0, 1.0]
    ) == pytest.approx(180.0, abs=1e-9)
    assert axial_mean([10.0, 30.0], [1.0, 3.0]) == pytest.approx(25.0, abs=0.5)


@pytest.mark.parametrize("largest", [11, 65_534, 5_000_000])
def test_moments_are_the_same_whether_the_lines_are_counted_or_sorted(rng, largest):
    """Point source ids are counted into their lines (no sort); ids too large to count are sorted."""
    ids = rng.choice(np.array([0, 3, largest]), size=(40, 30))
    ids[rng.random(ids.shape) < 0.2] = -1
    got = line_moments(ids, row_off=7, col_off=-3)
    rows, cols = np.nonzero(ids >= 0)
    assert list(got["line"]) == sorted(set(ids[rows, cols].tolist()))
    for m in got:
        mine = ids == m["line"]
        r, c = np.nonzero(mine)
        r, c = r + 7.0, c - 3.0
        assert m["n"] == mine.sum()
        assert np.allclose(
            [m["r"], m["c"], m["rr"], m["cc"], m["rc"]], [r.sum(), c.sum(), (r * r).sum(), (c * c).sum(), (r * c).sum()]
        )
