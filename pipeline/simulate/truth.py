"""The truth of a simulated scan: why each empty pixel is empty (pure).

Per terrain cell, the simulation knows whether some flown line's swath reaches it, whether
a line sees it (line of sight to its first surface free, or free but through vegetation),
and what it is (water, a dark patch). :func:`cell_causes` turns that into a cause code per
cell, :func:`truth_causes` into a raster of ``HoleCause`` codes on any pixel lattice, from
the points actually written:

* a pixel holding a point is 0;
* an empty pixel takes the most common code of its cells (sampled on a sub-grid of at
  least one sample per terrain cell; a tie goes to the cause, not to 0): 3 missed coverage
  (outside every swath), 2 water, 1 occlusion (inside a swath, no line sees it clearly),
  4 no return (seen, unobstructed, a dark patch), 0 a sampling gap (seen clearly: the
  pulses merely fell elsewhere).
"""

from __future__ import annotations

import math

import numpy as np

from ..synth.spec import HoleCause
from ._kernels import IN_SWATH, SEEN_CLEAR
from .terrain import Surface


def cell_causes(kind: np.ndarray, dark: np.ndarray, flags: np.ndarray) -> np.ndarray:
    """The ``HoleCause`` a terrain cell would have if no point landed on it.

    Parameters
    ----------
    kind : ndarray of shape (M, N), uint8
        :class:`.terrain.Surface` codes.
    dark : ndarray of bool, shape (M, N)
        Cells that return nothing (dark patches).
    flags : ndarray of shape (M, N), uint8
        Visibility bits ORed over the flown lines (``_kernels.line_visibility``).

    Returns
    -------
    ndarray of shape (M, N), uint8
    """
    in_swath = (flags & IN_SWATH) > 0
    seen = (flags & SEEN_CLEAR) > 0
    causes = np.full(kind.shape, HoleCause.NONE, np.uint8)
    causes[~in_swath] = HoleCause.MISSED_COVERAGE
    water = in_swath & (kind == Surface.WATER)
    causes[water] = HoleCause.WATER
    causes[in_swath & ~water & ~seen] = HoleCause.OCCLUSION
    causes[in_swath & ~water & seen & dark] = HoleCause.NO_RETURN
    return causes


def pixel_lattice(
    bounds: tuple[float, float, float, float], resolution: float
) -> tuple[int, int, int, int, tuple[float, ...]]:
    """The pixels of the lattice ``floor(x / resolution)`` covering ``bounds``.

    Returns ``(col_min, row_top, width, height, transform)``: columns ``col_min ..``,
    lattice rows ``row_top`` down, and the affine transform's coefficients
    ``(a, b, c, d, e, f) = (resolution, 0, x_left, 0, -resolution, y_top)``.
    """
    x0, y0, x1, y1 = bounds
    col_min = math.floor(x0 / resolution)
    col_max = math.ceil(x1 / resolution) - 1
    row_bottom = math.floor(y0 / resolution)
    row_top = math.ceil(y1 / resolution) - 1
    width, height = col_max - col_min + 1, row_top - row_bottom + 1
    transform = (resolution, 0.0, col_min * resolution, 0.0, -resolution, (row_top + 1) * resolution)
    return col_min, row_top, width, height, transform


def truth_causes(
    causes: np.ndarray,
    *,
    cell_m: float,
    x_min: float,
    y_min: float,
    x: np.ndarray,
    y: np.ndarray,
    resolution: float,
) -> tuple[np.ndarray, tuple[float, ...]]:
    """``HoleCause`` codes on the pixel lattice of ``resolution`` over the terrain.

    Parameters
    ----------
    causes : ndarray of shape (M, N), uint8
        :func:`cell_causes` of the terrain cells (row 0 north).
    cell_m, x_min, y_min : float
        The terrain lattice: cell size and lower-left corner.
    x, y : ndarray of shape (P,)
        The points written, as a reader decodes them (pixel ``floor(x / resolution)``, the
        pipeline's binning).
    resolution : float
        Pixel size of the run to score.

    Returns
    -------
    truth : ndarray of shape (H, W), uint8
        0 where a point landed or the pixel lies outside the terrain, else the cause.
    transform : tuple of float
        Coefficients ``(a, b, c, d, e, f)`` of ``truth``'s affine transform.
    """
    rows, cols = causes.shape
    bounds = (x_min, y_min, x_min + cols * cell_m, y_min + rows * cell_m)
    col_min, row_top, width, height, transform = pixel_lattice(bounds, resolution)
    pixel_col = np.floor(np.asarray(x) / resolution).astype(np.int64) - col_min
    pixel_row = row_top - np.floor(np.asarray(y) / resolution).astype(np.int64)
    inside = (pixel_col >= 0) & (pixel_col < width) & (pixel_row >= 0) & (pixel_row < height)
    occupied = np.zeros((height, width), bool)
    occupied[pixel_row[inside], pixel_col[inside]] = True
    votes = _sampled_votes(causes, cell_m, x_min, y_min, transform, (height, width))
    # most common code; a tie goes to the cause with the highest code, not to 0
    truth = (votes.shape[-1] - 1 - np.argmax(votes[..., ::-1], axis=-1)).astype(np.uint8)
    truth[occupied] = HoleCause.NONE
    return truth, transform


def _sampled_votes(
    causes: np.ndarray,
    cell_m: float,
    x_min: float,
    y_min: float,
    transform: tuple[float, ...],
    shape: tuple[int, int],
) -> np.ndarray:
    """Per pixel, how many of its sub-samples fall on cells of each cause (0 outside the terrain)."""
    resolution, x_left, y_top = transform[0], transform[2], transform[5]
    rows, cols = causes.shape
    n = max(1, math.ceil(resolution / cell_m))
    offsets = (np.arange(n) + 0.5) / n * resolution
    codes = int(causes.max(initial=0)) + 1
    votes = np.zeros((*shape, max(codes, len(HoleCause))), np.int32)
    centre_x = x_left + np.arange(shape[1]) * resolution
    centre_y = y_top - np.arange(shape[0]) * resolution
    for dy in offsets:
        sample_y = centre_y - dy
        cell_row = rows - 1 - np.floor((sample_y - y_min) / cell_m).astype(np.int64)
        row_ok = (cell_row >= 0) & (cell_row < rows)
        for dx in offsets:
            sample_x = centre_x + dx
            cell_col = np.floor((sample_x - x_min) / cell_m).astype(np.int64)
            col_ok = (cell_col >= 0) & (cell_col < cols)
            ok = row_ok[:, None] & col_ok[None, :]
            code = causes[np.clip(cell_row, 0, rows - 1)[:, None], np.clip(cell_col, 0, cols - 1)[None, :]]
            code = np.where(ok, code, HoleCause.NONE)
            _add_votes(votes, code)
    return votes


def _add_votes(votes: np.ndarray, code: np.ndarray) -> None:
    """``votes[r, c, code[r, c]] += 1`` for every pixel."""
    for value in np.unique(code):
        votes[..., int(value)] += code == value
