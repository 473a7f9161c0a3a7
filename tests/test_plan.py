"""The survey plan: the tile-to-cell index by grid arithmetic agrees with comparing every pair."""

from __future__ import annotations

import numpy as np
import pytest
from pyproj import CRS

from pipeline.config import load_config
from pipeline.grid import Grid
from pipeline.plan import _shared_windows, _tiles_by_cell, plan_survey
from pipeline.survey import Survey, Tile


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
    crs = CRS.from_epsg(2154).to_wkt()
    # two far-apart blocks of tiles: the cells between them are not planned
    bounds = [(0.0, 0.0, 100.0, 100.0), (100.0, 0.0, 200.0, 100.0), (5000.0, 3000.0, 5100.0, 3100.0)]
    tiles = [Tile(i, None, crs, b) for i, b in enumerate(bounds)]  # type: ignore[arg-type]
    survey = Survey(tiles=tiles, crs_wkt=crs, reproject=False, horizontal_unit_m=1.0, vertical_unit_m=1.0)
    config = load_config(overrides=["grid.cell_size_m=50", "grid.resolution_m=1"])
    plan = plan_survey(survey, config)
    # 200 x 100 m and 100 x 100 m: max edges on the lattice add a row and a column of cells
    assert len(plan.cells) == 5 * 3 + 3 * 3
    keys = [(-c.index_y, c.index_x) for c in plan.cells]
    assert keys == sorted(keys)
    assert all(plan.tiles_of_cell[c.id] for c in plan.cells)
    assert np.isclose(plan.pixel_area_m2, 1.0)
