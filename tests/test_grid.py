from __future__ import annotations

import numpy as np
import pytest

from pipeline.grid import Grid, PixelWindow


def make_grid(resolution=0.5, cell_px=100, bounds=((770500.0, 6277500.0, 770649.99, 6277599.99),)):
    return Grid.covering(list(bounds), resolution=resolution, cell_px=cell_px, halo_px=4, crs_wkt="")


def test_grid_snaps_to_the_absolute_lattice():
    grid = make_grid()
    assert grid.bounds == (770500.0, 6277500.0, 770650.0, 6277600.0)
    assert (grid.width, grid.height) == (300, 200)
    assert grid.transform.a == 0.5 and grid.transform.e == -0.5


def test_cells_tile_the_grid_exactly_and_are_world_aligned():
    grid = make_grid(cell_px=64)
    cover = np.zeros((grid.height, grid.width), int)
    for cell in grid.cells():
        cover[cell.window.slices_within(grid.window)] += 1
        x0, y0, _, _ = grid.window_bounds(cell.window)
        # interior cells start on multiples of the cell size (32 m)
        if cell.window.width == 64 and cell.window.height == 64:
            assert x0 % 32 == 0 and y0 % 32 == 0
        assert not cell.halo_window.intersection(grid.window).is_empty
    assert np.all(cover == 1)


@pytest.mark.parametrize("cell_px", [16, 64, 100, 1000])
def test_pixel_of_a_point_does_not_depend_on_cell_size(cell_px, rng):
    x = rng.uniform(770500, 770650, 1000)
    y = rng.uniform(6277500, 6277600, 1000)
    reference = make_grid(cell_px=16).pixel_rows_cols(x, y)
    rows, cols = make_grid(cell_px=cell_px).pixel_rows_cols(x, y)
    assert np.array_equal(rows, reference[0]) and np.array_equal(cols, reference[1])


def test_window_of_bounds_and_intersections():
    grid = make_grid()
    w = grid.window_of_bounds(770500, 6277550, 770550, 6277599.99)
    assert w == PixelWindow(0, 0, 100, 101)
    assert w.intersection(PixelWindow(50, 50, 500, 500)) == PixelWindow(50, 50, 50, 51)
    assert PixelWindow(0, 0, 5, 5).intersection(PixelWindow(10, 10, 5, 5)).is_empty
    assert grid.window_of_bounds(0, 0, 1, 1).is_empty


def test_cell_ids_are_lower_left_corners():
    grid = make_grid(resolution=1.0, cell_px=50)
    ids = {cell.id for cell in grid.cells()}
    assert "770500_6277500" in ids and "770600_6277550" in ids


def test_center_alignment_puts_pixel_centres_on_the_lattice(rng):
    grid = Grid.covering(
        [(770500.0, 6277500.0, 770649.99, 6277599.99)], resolution=0.5, cell_px=100, halo_px=4, crs_wkt="", offset=0.5
    )
    # IGN's 50 cm products: pixel edges at 770499.75, ...; the first pixel is centred on 770500
    assert grid.bounds == (770499.75, 6277499.75, 770650.25, 6277600.25)
    assert (grid.width, grid.height) == (301, 201)
    centre_x, centre_y = grid.transform @ (0.5, grid.height - 0.5)
    assert (centre_x, centre_y) == (770500.0, 6277500.0)
    # a point within a quarter pixel of a lattice node lands in the pixel centred on it
    rows, cols = grid.pixel_rows_cols(np.array([770500.2, 770500.3]), np.array([6277599.8, 6277599.7]))
    assert cols.tolist() == [0, 1] and rows.tolist() == [0, 1]
    # the compiled kernel places points by the same formula
    from pipeline.rasterize import HeightMapAccumulator

    x = rng.uniform(770500, 770650, 5000)
    y = rng.uniform(6277500, 6277600, 5000)
    acc = HeightMapAccumulator(
        grid.window,
        resolution=grid.resolution,
        col_min=grid.col_min,
        row_top=grid.row_top,
        grid_width=grid.width,
        voxel_height=0.5,
        offset=grid.offset,
    )
    acc.add(x, y, np.zeros_like(x), np.ones(len(x), bool))
    rows, cols = grid.pixel_rows_cols(x, y)
    expected = np.zeros(grid.window.shape, np.uint32)
    np.add.at(expected, (rows, cols), 1)
    assert np.array_equal(acc.statistics.count, expected)
    # cells are still aligned to multiples of the cell size, shifted by half a pixel
    assert {c.id for c in grid.cells()} >= {"770499p75_6277499p75"}


def test_z_order_visits_each_block_of_cells_before_the_next():
    """Cells in Z order: every aligned 2^k x 2^k block is visited in one run, at any offset of the indices."""
    from pipeline.grid import z_order

    rng = np.random.default_rng(3)
    cols, rows = np.meshgrid(np.arange(-8, 8), np.arange(5, 21))  # 16 x 16 cells, negative indices too
    cols, rows = cols.ravel(), rows.ravel()
    shuffled = rng.permutation(len(cols))
    order = shuffled[z_order(cols[shuffled], rows[shuffled])]
    assert sorted(order.tolist()) == list(range(len(cols)))
    for size in (2, 4, 8):
        blocks = ((cols[order] + 8) // size) * 100 + (rows[order] - 5) // size
        runs = [blocks[0]] + [b for a, b in zip(blocks, blocks[1:]) if a != b]
        assert len(runs) == len(set(runs)) == (16 // size) ** 2
    assert z_order(np.array([], np.int64), np.array([], np.int64)).size == 0
