"""Tests of pipeline.io.intermediate: the cell statistics kept for later stages, read again."""

from __future__ import annotations

import os

import numpy as np
import pytest

from pipeline.grid import PixelWindow
from pipeline.io.intermediate import load_shared_cell_statistics, save_cell_statistics
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
