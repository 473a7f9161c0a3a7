"""Tests of pipeline.io.intermediate: the cell statistics kept for later stages, read again."""

from __future__ import annotations

import os

import numpy as np
import pytest

from pipeline.grid import PixelWindow
from pipeline.io.intermediate import (
    load_shared_cell_statistics,
    load_task_fill,
    save_cell_statistics,
    save_task_fill,
)
from pipeline.rasterize import STATISTIC_DTYPES, STATISTIC_NAMES, PixelStatistics


def _statistics(value: float) -> PixelStatistics:
    window = PixelWindow(2, 3, 4, 5)
    arrays = {name: np.full(window.shape, value, STATISTIC_DTYPES[name]) for name in STATISTIC_NAMES}
    return PixelStatistics(window=window, **arrays)


def test_shared_statistics_are_read_once_read_only_and_again_when_rewritten(tmp_path):
    path = tmp_path / "cell.npz"
    save_cell_statistics(path, _statistics(1.0))
    names = ("zmax", "count")
    first = load_shared_cell_statistics(path, names)
    assert load_shared_cell_statistics(path, names) is first  # a neighbour's task reads it from memory
    assert first.window == PixelWindow(2, 3, 4, 5)
    assert first.zmax.shape == (4, 5) and first.zmin.shape == (0, 0)  # only the names asked for
    with pytest.raises(ValueError):
        first.zmax[0, 0] = 5.0  # shared between tasks: nobody writes into it
    save_cell_statistics(path, _statistics(2.0))
    os.utime(path, ns=(1, 1))  # a rewritten file: another modification time
    again = load_shared_cell_statistics(path, names)
    assert again is not first and float(again.zmax[0, 0]) == 2.0


def test_the_shared_cells_stay_within_their_byte_budget_least_recently_used_out(tmp_path, monkeypatch):
    from pipeline.io import intermediate

    names = ("zmax", "count")
    one_cell = 4 * 5 * (4 + 4)  # the bytes of one small cell's two statistics
    monkeypatch.setattr(intermediate, "_SHARED", intermediate._SharedCells(budget=3 * one_cell))
    paths = []
    for k in range(4):
        paths.append(tmp_path / f"cell_{k}.npz")
        save_cell_statistics(paths[-1], _statistics(float(k)))
    first = [load_shared_cell_statistics(p, names) for p in paths[:3]]
    assert load_shared_cell_statistics(paths[0], names) is first[0]  # used again: now the most recent
    load_shared_cell_statistics(paths[3], names)  # over the budget: the least recently used (cell 1) goes
    assert intermediate._SHARED.total == 3 * one_cell
    assert load_shared_cell_statistics(paths[0], names) is first[0]
    assert load_shared_cell_statistics(paths[2], names) is first[2]
    assert load_shared_cell_statistics(paths[1], names) is not first[1]  # read again


def _task_fill_arrays(shape, seed=0):
    rng = np.random.default_rng(seed)
    hole_ids = np.where(rng.random(shape) < 0.3, rng.integers(1, 5, shape), 0)
    heights = np.where(hole_ids > 0, rng.normal(10.0, 3.0, shape), np.nan)
    codes = np.where(hole_ids > 0, rng.integers(1, 6, shape), 0).astype(np.uint8)
    distance = rng.random(shape).astype(np.float32)
    return hole_ids, heights, codes, distance


@pytest.mark.parametrize("within", [PixelWindow(10, 20, 12, 9), PixelWindow(0, 0, 100, 100), PixelWindow(15, 22, 3, 4)])
def test_a_fill_result_read_for_a_cell_is_its_crop_there(tmp_path, within):
    window = PixelWindow(10, 20, 12, 9)
    hole_ids, heights, codes, distance = _task_fill_arrays(window.shape)
    cells = [("beside", PixelWindow(0, 0, 10, 20)), ("asked", within)]
    save_task_fill(tmp_path / "fill.npz", window, hole_ids, heights, codes, distance, cells=cells)
    piece = load_task_fill(tmp_path / "fill.npz", "asked", within)
    overlap = window.intersection(within)
    assert piece.window == overlap
    there = overlap.slices_within(window)
    filled = hole_ids[there] > 0
    np.testing.assert_array_equal(piece.hole_ids, hole_ids[there])
    np.testing.assert_array_equal(piece.codes[filled], codes[there][filled])
    np.testing.assert_array_equal(piece.heights[filled], heights[there][filled].astype(np.float32))
    np.testing.assert_array_equal(piece.distance[filled], distance[there][filled])
    assert np.isnan(piece.heights[~filled]).all()
    assert load_task_fill(tmp_path / "fill.npz", "beside", PixelWindow(0, 0, 10, 20)) is None  # nothing filled
    assert load_task_fill(tmp_path / "fill.npz", "elsewhere", within) is None


def test_each_cell_reads_only_its_own_part_of_a_fill(tmp_path):
    window = PixelWindow(0, 0, 8, 12)
    hole_ids, heights, codes, distance = _task_fill_arrays(window.shape, seed=3)
    cells = [(f"c{i}", PixelWindow(0, 4 * i, 8, 4)) for i in range(3)]
    save_task_fill(tmp_path / "fill.npz", window, hole_ids, heights, codes, distance, cells=cells)
    with np.load(tmp_path / "fill.npz") as data:
        assert [len(data[f"p{i}_rows"]) for i in range(3)] == [
            int((hole_ids[:, 4 * i : 4 * i + 4] > 0).sum()) for i in range(3)
        ]
    painted = np.zeros(window.shape, np.int64)
    for cell_id, core in cells:
        piece = load_task_fill(tmp_path / "fill.npz", cell_id, core)
        painted[piece.window.slices_within(window)] = piece.hole_ids
    np.testing.assert_array_equal(painted, hole_ids)


def test_a_coarse_fill_result_gives_each_pixel_its_coarse_pixels_values(tmp_path):
    window, factor = PixelWindow(5, 7, 10, 11), 3
    lattice = (4, 4)  # ceil(10 / 3), ceil(11 / 3)
    hole_ids, heights, codes, distance = _task_fill_arrays(lattice, seed=1)
    within = PixelWindow(8, 4, 20, 8)  # from the window's second coarse row, up to its sixth column
    cells = [("left", within), ("right", PixelWindow(8, 12, 20, 8))]  # coarse column 1 lies in both
    save_task_fill(tmp_path / "fill.npz", window, hole_ids, heights, codes, distance, cells=cells, factor=factor)
    for cell_id, core in cells:
        piece = load_task_fill(tmp_path / "fill.npz", cell_id, core)
        assert piece.window == window.intersection(core)
        for r in range(piece.window.height):
            for c in range(piece.window.width):
                coarse = ((piece.window.row_off + r - 5) // factor, (piece.window.col_off + c - 7) // factor)
                assert piece.hole_ids[r, c] == hole_ids[coarse]
                if hole_ids[coarse]:
                    assert piece.heights[r, c] == np.float32(heights[coarse])
                    assert piece.codes[r, c] == codes[coarse]


def test_a_fill_result_with_pixels_outside_its_window_is_refused(tmp_path):
    window = PixelWindow(0, 0, 4, 4)
    path = tmp_path / "fill.npz"
    hole_ids, heights, codes, distance = _task_fill_arrays(window.shape, seed=2)
    save_task_fill(path, window, hole_ids, heights, codes, distance, cells=[("c", window)])
    with np.load(path) as data:
        arrays = dict(data)
    arrays["p0_rows"] = arrays["p0_rows"] + 4
    np.savez(path, **arrays)
    with pytest.raises(ValueError, match="outside the fill's window"):
        load_task_fill(path, "c", window)
    arrays["p0_rows"] = arrays["p0_rows"][:-1]
    np.savez(path, **arrays)
    with pytest.raises(ValueError, match="unequal lengths"):
        load_task_fill(path, "c", window)
