"""The survey's global raster grid, its cells, halos and pixel windows.

Every pixel of every output lives on one absolute lattice: pixel column
``floor(x / resolution + offset)`` and row ``floor(y / resolution + offset)`` in
the survey CRS, so a point always lands in the same pixel whatever the tiling of
the inputs or the cell size. ``offset`` is 0 when pixel edges lie on multiples of
the resolution (``grid.align = "edge"``) and 0.5 when pixel centres do
(``"center"``, the convention of national DSM products such as IGN's). The survey grid is the part of that lattice covering the union of
the tile extents; cells are the squares of ``cell_px`` pixels aligned to
multiples of the cell size in world coordinates (so cell names are stable), and
clipped to the grid. Rows count downwards from the top (north-up rasters).

Pure geometry: no I/O, no Dask.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from affine import Affine
from numpy.typing import ArrayLike


@dataclass(frozen=True, order=True)
class PixelWindow:
    """A rectangle of grid pixels: rows ``[row_off, row_off+height)``, columns likewise."""

    row_off: int
    col_off: int
    height: int
    width: int

    @property
    def row_end(self) -> int:
        return self.row_off + self.height

    @property
    def col_end(self) -> int:
        return self.col_off + self.width

    @property
    def is_empty(self) -> bool:
        return self.height <= 0 or self.width <= 0

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    def intersection(self, other: PixelWindow) -> PixelWindow:
        """The overlap of two windows (possibly empty, with zero height/width)."""
        r0, c0 = max(self.row_off, other.row_off), max(self.col_off, other.col_off)
        r1, c1 = min(self.row_end, other.row_end), min(self.col_end, other.col_end)
        return PixelWindow(r0, c0, max(0, r1 - r0), max(0, c1 - c0))

    def expand(self, pixels: int) -> PixelWindow:
        """The window grown by ``pixels`` on every side (not clipped)."""
        return PixelWindow(
            self.row_off - pixels, self.col_off - pixels, self.height + 2 * pixels, self.width + 2 * pixels
        )

    def slices_within(self, outer: PixelWindow) -> tuple[slice, slice]:
        """Array slices selecting this window inside an array covering ``outer``."""
        return (
            slice(self.row_off - outer.row_off, self.row_end - outer.row_off),
            slice(self.col_off - outer.col_off, self.col_end - outer.col_off),
        )


@dataclass(frozen=True)
class Cell:
    """One processing cell: its core window and the halo window read around it."""

    id: str
    index_x: int
    index_y: int
    window: PixelWindow
    halo_window: PixelWindow


@dataclass(frozen=True)
class Grid:
    """The survey grid on the absolute lattice.

    Attributes
    ----------
    resolution : float
        Pixel size in CRS units.
    col_min : int
        Absolute lattice column of the grid's first column (``x_left = col_min * resolution``).
    row_top : int
        Absolute lattice row (counting up from y = 0) of the grid's top row.
    width, height : int
        Grid size in pixels.
    cell_px : int
        Cell side in pixels; cells are aligned to absolute multiples of it.
    halo_px : int
        Pixels read around each cell.
    crs_wkt : str
        The survey CRS.
    offset : float
        0.0: pixel edges on multiples of the resolution; 0.5: pixel centres (see the module).
    """

    resolution: float
    col_min: int
    row_top: int
    width: int
    height: int
    cell_px: int
    halo_px: int
    crs_wkt: str
    offset: float = 0.0

    @classmethod
    def covering(
        cls,
        bounds: list[tuple[float, float, float, float]] | np.ndarray,
        *,
        resolution: float,
        cell_px: int,
        halo_px: int,
        crs_wkt: str,
        offset: float = 0.0,
    ) -> Grid:
        """The smallest grid on the lattice that covers every (minx, miny, maxx, maxy) box."""
        b = np.asarray(bounds, dtype=np.float64).reshape(-1, 4)
        col_min = _lattice_index(b[:, 0].min(), resolution, offset)
        col_max = _lattice_index(b[:, 2].max(), resolution, offset)
        row_bottom = _lattice_index(b[:, 1].min(), resolution, offset)
        row_top = _lattice_index(b[:, 3].max(), resolution, offset)
        return cls(
            resolution=float(resolution),
            col_min=col_min,
            row_top=row_top,
            width=col_max - col_min + 1,
            height=row_top - row_bottom + 1,
            cell_px=int(cell_px),
            halo_px=int(halo_px),
            crs_wkt=crs_wkt,
            offset=float(offset),
        )

    # -- geometry -----------------------------------------------------------------
    @property
    def window(self) -> PixelWindow:
        return PixelWindow(0, 0, self.height, self.width)

    @property
    def x_left(self) -> float:
        return (self.col_min - self.offset) * self.resolution

    @property
    def y_top(self) -> float:
        return (self.row_top + 1 - self.offset) * self.resolution

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        return (
            self.x_left,
            self.y_top - self.height * self.resolution,
            self.x_left + self.width * self.resolution,
            self.y_top,
        )

    @property
    def transform(self) -> Affine:
        return Affine(self.resolution, 0.0, self.x_left, 0.0, -self.resolution, self.y_top)

    def window_transform(self, window: PixelWindow) -> Affine:
        """The affine transform of a window's top-left pixel."""
        return self.transform @ Affine.translation(window.col_off, window.row_off)

    def window_bounds(self, window: PixelWindow) -> tuple[float, float, float, float]:
        r = self.resolution
        return (
            self.x_left + window.col_off * r,
            self.y_top - window.row_end * r,
            self.x_left + window.col_end * r,
            self.y_top - window.row_off * r,
        )

    def pixel_rows_cols(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Grid row and column of world points (may fall outside the grid).

        This is the one formula that places points; the compiled kernel in
        ``rasterize`` uses the same expression (``floor(x / resolution + offset)``).
        """
        r, o = self.resolution, self.offset
        cols = np.floor(np.asarray(x) / r + o).astype(np.int64) - self.col_min
        rows = self.row_top - np.floor(np.asarray(y) / r + o).astype(np.int64)
        return rows, cols

    def window_of_bounds(self, minx: float, miny: float, maxx: float, maxy: float) -> PixelWindow:
        """The pixels touched by a world box (inclusive of its max edge), clipped to the grid."""
        r, o = self.resolution, self.offset
        c0 = _lattice_index(minx, r, o) - self.col_min
        c1 = _lattice_index(maxx, r, o) - self.col_min
        r0 = self.row_top - _lattice_index(maxy, r, o)
        r1 = self.row_top - _lattice_index(miny, r, o)
        return PixelWindow(r0, c0, r1 - r0 + 1, c1 - c0 + 1).intersection(self.window)

    def window_of_centres(self, minx: float, miny: float, maxx: float, maxy: float) -> PixelWindow:
        """The pixels whose centres lie in a world box (edges included), clipped to the grid.

        Unlike :meth:`window_of_bounds`, a pixel the box only grazes (a point exactly on the
        box's max edge lands in the pixel beyond it) is left out.
        """
        r, o = self.resolution, self.offset
        c0 = math.ceil(minx / r + o - 0.5) - self.col_min
        c1 = math.floor(maxx / r + o - 0.5) - self.col_min
        r0 = self.row_top - math.floor(maxy / r + o - 0.5)
        r1 = self.row_top - math.ceil(miny / r + o - 0.5)
        return PixelWindow(r0, c0, max(r1 - r0 + 1, 0), max(c1 - c0 + 1, 0)).intersection(self.window)

    # -- cells --------------------------------------------------------------------
    def cells(self) -> list[Cell]:
        """All cells overlapping the grid, west to east within north to south."""
        return [self.cell(ix, iy) for iy, ix in self._cell_index_ranges(self.window)]

    def cell(self, index_x: int, index_y: int) -> Cell:
        """The cell of absolute indices ``(index_x, index_y)`` (``index_y`` counts upwards)."""
        n = self.cell_px
        # absolute rows index_y*n .. index_y*n+n-1 (upwards) -> grid rows
        row_off = self.row_top - (index_y * n + n - 1)
        col_off = index_x * n - self.col_min
        core = PixelWindow(row_off, col_off, n, n).intersection(self.window)
        halo = core.expand(self.halo_px).intersection(self.window)
        x0 = (index_x * n - self.offset) * self.resolution
        y0 = (index_y * n - self.offset) * self.resolution
        return Cell(
            id=f"{_coordinate_name(x0)}_{_coordinate_name(y0)}",
            index_x=index_x,
            index_y=index_y,
            window=core,
            halo_window=halo,
        )

    def cell_indices_under(self, window: PixelWindow) -> list[tuple[int, int]]:
        """``(index_x, index_y)`` of the cells whose core meets ``window``, by grid arithmetic.

        In the order of :meth:`cells` (north to south, west to east within a row).
        """
        window = window.intersection(self.window)
        if window.is_empty:
            return []
        return [(ix, iy) for iy, ix in self._cell_index_ranges(window)]

    def _cell_index_ranges(self, window: PixelWindow) -> Iterator[tuple[int, int]]:
        n = self.cell_px
        # absolute lattice rows count upwards: the window's top row is the highest
        top_index = math.floor((self.row_top - window.row_off) / n)
        bottom_index = math.floor((self.row_top - window.row_end + 1) / n)
        left_index = math.floor((self.col_min + window.col_off) / n)
        right_index = math.floor((self.col_min + window.col_end - 1) / n)
        for index_y in range(top_index, bottom_index - 1, -1):
            for index_x in range(left_index, right_index + 1):
                yield index_y, index_x


def _lattice_index(value: float, resolution: float, offset: float) -> int:
    """``floor(value / resolution + offset)``: the formula of :meth:`Grid.pixel_rows_cols`, on a scalar."""
    return math.floor(float(value) / resolution + offset)


def _coordinate_name(value: float) -> str:
    rounded = round(value)
    if abs(value - rounded) < 1e-6:
        return str(rounded)
    return f"{value:.2f}".replace(".", "p")


def window_boxes(windows: list[PixelWindow] | tuple[PixelWindow, ...]) -> np.ndarray:
    """``(row_off, col_off, row_end, col_end)`` of each window, int64 of shape (n, 4): for :func:`meeting`."""
    return np.array([(w.row_off, w.col_off, w.row_end, w.col_end) for w in windows], np.int64).reshape(-1, 4)


def meeting(boxes: np.ndarray, window: PixelWindow) -> np.ndarray:
    """Indices of the :func:`window_boxes` rows that overlap ``window`` (a non-empty intersection), in order.

    One array comparison where a loop of :meth:`PixelWindow.intersection` over thousands of
    tiles, for every cell or strip, cost seconds on the client of a 1,536-tile survey.
    """
    rows = np.maximum(boxes[:, 0], window.row_off) < np.minimum(boxes[:, 2], window.row_end)
    cols = np.maximum(boxes[:, 1], window.col_off) < np.minimum(boxes[:, 3], window.col_end)
    return np.flatnonzero(rows & cols)


def window_union_mask(window: PixelWindow, windows: list[PixelWindow] | tuple[PixelWindow, ...]) -> np.ndarray:
    """Pixels of ``window`` covered by any of ``windows`` (tile extents, grid squares)."""
    mask = np.zeros(window.shape, bool)
    for other in windows:
        overlap = other.intersection(window)
        if not overlap.is_empty:
            mask[overlap.slices_within(window)] = True
    return mask


def z_order(columns: ArrayLike, rows: ArrayLike) -> np.ndarray:
    """Indices that put lattice positions along a Z-order (Morton) curve: positions close together
    come close together in the order, at every scale.

    ``columns``, ``rows``: integers (any offset: they are taken from their minima), under 2**31
    apart. Used to visit cells neighbour after neighbour, so that what a task reads of the cells
    around it is still in a cache the previous tasks filled.
    """
    columns = np.asarray(columns, np.int64)
    rows = np.asarray(rows, np.int64)
    if columns.size == 0:
        return np.empty(0, np.int64)
    x = (columns - columns.min()).astype(np.uint64)
    y = (rows - rows.min()).astype(np.uint64)
    key = np.zeros(len(x), np.uint64)
    for bit in range(31):
        one = np.uint64(1)
        key |= ((x >> np.uint64(bit)) & one) << np.uint64(2 * bit)
        key |= ((y >> np.uint64(bit)) & one) << np.uint64(2 * bit + 1)
    return np.argsort(key, kind="stable")
