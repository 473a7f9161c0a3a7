"""The survey plan: the tile-to-cell index by grid arithmetic agrees with comparing every pair."""

from __future__ import annotations

import numpy as np
import pytest
from pyproj import CRS

from pipeline.config import load_config
from pipeline.grid import Grid
from pipeline.io.las import TileHeader
from pipeline.plan import _shared_windows, _tiles_by_cell, plan_survey
from pipeline.survey.scan import Survey, Tile


def header(bounds, points, by_return=()):
    """A tile header as the scan reads it (no file behind it)."""
    return TileHeader("t.laz", "LAZ", "1.4", 6, points, bounds, (0.0, 10.0), None, None, 1, tuple(by_return))


def survey_of(bounds, points=10_000, by_return=()):
    crs = CRS.from_epsg(2154).to_wkt()
    tiles = [Tile(i, header(b, points, by_return), crs, b) for i, b in enumerate(bounds)]
    return Survey(tiles=tiles, crs_wkt=crs, reproject=False, horizontal_unit_m=1.0, vertical_unit_m=1.0)


def random_tiles(rng, n):
    """Overlapping tiles of random sizes, some off the lattice."""
    x0 = rng.uniform(1000, 1400, n)
    y0 = rng.uniform(5000, 5300, n)
    w = rng.uniform(5, 120, n)
    h = rng.uniform(5, 120, n)
    return [(float(a), float(b), float(a + c), float(b + d)) for a, b, c, d in zip(x0, y0, w, h)]


@pytest.mark.parametrize("cell_px, halo_px", [(16, 0), (32, 8), (100, 8), (1000, 12)])
def test_lattice_index_matches_brute_force(rng, cell_px, halo_px):
    bounds = random_tiles(rng, 40)
    grid = Grid.covering(bounds, resolution=1.0, cell_px=cell_px, halo_px=halo_px, crs_wkt="")
    windows = [grid.window_of_bounds(*b) for b in bounds]
    core = _tiles_by_cell(grid, windows, expand_px=0)
    halo = _tiles_by_cell(grid, windows, expand_px=halo_px)
    for cell in grid.cells():
        key = (cell.index_x, cell.index_y)
        assert core.get(key, []) == [i for i, w in enumerate(windows) if not w.intersection(cell.window).is_empty]
        assert halo.get(key, []) == [i for i, w in enumerate(windows) if not w.intersection(cell.halo_window).is_empty]
    shared = _shared_windows(windows, core)
    for i, window in enumerate(windows):
        expected = tuple(
            overlap
            for j, other in enumerate(windows)
            if j != i and not (overlap := window.intersection(other)).is_empty
        )
        assert shared[i] == expected


def test_plan_keeps_only_cells_holding_tiles_in_plan_order():
    # two far-apart blocks of tiles: the cells between them are not planned
    bounds = [(0.0, 0.0, 100.0, 100.0), (100.0, 0.0, 200.0, 100.0), (5000.0, 3000.0, 5100.0, 3100.0)]
    survey = survey_of(bounds)
    config = load_config(overrides=["grid.cell_size_m=50", "grid.resolution_m=1"])
    plan = plan_survey(survey, config)
    # 200 x 100 m and 100 x 100 m: max edges on the lattice add a row and a column of cells
    assert len(plan.cells) == 5 * 3 + 3 * 3
    keys = [(-c.index_y, c.index_x) for c in plan.cells]
    assert keys == sorted(keys)
    assert all(plan.tiles_of_cell[c.id] for c in plan.cells)
    assert np.isclose(plan.pixel_area_m2, 1.0)


def test_auto_pixel_size_follows_the_first_return_density(caplog):
    bounds = [(0.0, 0.0, 1000.0, 1000.0)]
    # 1 km2, 50,000 first returns of 80,000 points: 0.05 first returns/m2 -> 10 m pixels (5 per pixel)
    sparse = plan_survey(survey_of(bounds, 80_000, (50_000, 30_000)), load_config())
    assert sparse.sizing.density.first_returns and sparse.sizing.density.pulses_per_m2 == pytest.approx(0.05)
    assert sparse.sizing.resolution_m == 10.0 and sparse.sizing.resolution_source == "auto"
    assert sparse.grid.resolution == 10.0
    # "auto" cells are 500 pixels, whatever the pixel size
    assert sparse.sizing.cell_size_m == 5000.0 and sparse.grid.cell_px == 500
    assert sparse.sizing.cell_size_requested_m == "auto"
    # min_area_m2 "auto" scales with the spacing: (4 x 1/sqrt(0.05) m)^2 = 320 m2
    assert sparse.hole_params.min_area_m2 == pytest.approx(320.0)
    assert sparse.hole_params.sampling_gap_px == pytest.approx(4 / np.sqrt(0.05) / 10)
    # a number set for min_area_m2 is the only rule: no sampling gaps
    set_area = plan_survey(survey_of(bounds, 80_000, (50_000, 30_000)), load_config(overrides=["holes.min_area_m2=4"]))
    assert set_area.hole_params.min_area_m2 == 4.0 and set_area.hole_params.sampling_gap_px == 0.0
    # per-return counts that do not add up: all points are used
    dense = plan_survey(survey_of(bounds, 20_000_000, (1, 2)), load_config())
    assert not dense.sizing.density.first_returns and dense.sizing.resolution_m == 0.5
    assert dense.sizing.cell_size_m == 250.0 and dense.grid.cell_px == 500
    assert dense.hole_params.min_area_m2 == 4.0  # the floor
    with caplog.at_level("INFO", logger="pipeline.plan"):
        fine = plan_survey(
            survey_of(bounds, 80_000, (50_000, 30_000)),
            load_config(overrides=["grid.resolution_m=4", "grid.cell_size_m=250"]),
        )
    assert fine.sizing.resolution_source == "set" and fine.grid.resolution == 4.0
    # a cell size set is rounded to whole pixels (250 m is 62.5 pixels of 4 m), never refused
    assert fine.sizing.cell_size_m == 248.0 and fine.grid.cell_px == 62
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "0.05 first returns/m2" in warnings[0] and "10 m or coarser" in warnings[0]
    assert any("cells are 248 m (62 pixels)" in r.getMessage() for r in caplog.records)
