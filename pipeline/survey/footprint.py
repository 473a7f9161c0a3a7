"""The survey area (AOI) at pixel level: where an empty pixel is a hole.

Outside the AOI everything is exterior, never a hole. The AOI is the survey area
(the union of the tile windows, or a polygon given with ``--aoi``) intersected
with the data footprint, so that the empty corners of a tile around a diagonal
flight strip are not holes, while voids enclosed by data and gaps between
flight lines are.

The footprint needs a global view (whether a void is enclosed is not a local
question), which must not mean a survey-sized fine raster: each cell reports
which blocks of ``block_px`` x ``block_px`` pixels hold data; the client closes
and fills that coarse map (:func:`data_footprint`). Blocks lie on
the absolute lattice, so the result does not depend on the cell size. At pixel
level, blocks on the footprint's border keep only what a small closing of the
occupied pixels covers (a local operation inside the cell's halo); interior
blocks are wholly inside.

Pure: arrays in, arrays out.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.ndimage as ndi

from ..grid import Grid, PixelWindow

#: Radius (pixels) of the closing of occupied pixels in border blocks.
EDGE_CLOSING_PX = 2


def data_footprint(occupied: np.ndarray, *, closing_px: int) -> np.ndarray:
    """The area covered by the survey: the default AOI when no polygon is given.

    The occupied pixels are closed with a Euclidean disc of radius ``closing_px``
    (gaps narrower than about ``2 * closing_px`` between data are bridged, so
    missed flight lines and scan gaps stay inside), then every void enclosed by
    data is filled. What remains outside is the empty area that opens to the
    raster's border, e.g. the corners of a rectangular tile around a diagonal
    flight strip: those are not holes.

    Parameters
    ----------
    occupied : ndarray of bool, shape (M, N)
        True where there is at least one point. Give a coarse raster for a whole
        survey (e.g. occupancy in 4-16 m blocks): the closing is not local to a cell.
    closing_px : int
        Radius of the closing disc, in pixels of ``occupied``; 0 only fills
        enclosed voids.

    Returns
    -------
    ndarray of bool, shape (M, N)
        True inside the footprint.
    """
    occ = np.asarray(occupied, dtype=bool)
    if occ.ndim != 2:
        raise ValueError(f"occupied must be a 2-dimensional array, got shape {occ.shape}")
    closing_px = int(closing_px)
    if closing_px < 0:
        raise ValueError(f"closing_px must be >= 0, got {closing_px}")
    pad = closing_px + 1
    work = np.pad(occ, pad)  # outside the raster counts as empty
    if closing_px > 0 and work.any():
        dilated = ndi.distance_transform_edt(~work) <= closing_px
        work = ndi.distance_transform_edt(dilated) > closing_px
    work = ndi.binary_fill_holes(work)
    return work[pad:-pad, pad:-pad]


@dataclass(frozen=True)
class BlockMap:
    """A boolean map of absolute blocks: row 0 is block row ``top`` (counting up), column 0 is ``left``."""

    block_px: int
    left: int
    top: int
    inside: np.ndarray  # bool (rows, cols): in the footprint
    border: np.ndarray  # bool: in the footprint with a 4-neighbour outside it
    everywhere: bool = False  # a given AOI is authoritative: every block counts as inside, none as border
    # bool: border blocks whose only outside neighbours lie beyond the survey area (the area's cut bounds them,
    # not the data: their empty pixels that a swath swept are inside); None: not known (all-False)
    cut: np.ndarray | None = None

    def slice_for(self, grid: Grid, window: PixelWindow) -> BlockMap:
        """The blocks under a window (with one block of margin), small enough to ship to a task."""
        c0, r0 = block_of(grid, window.row_off + window.height - 1, window.col_off, self.block_px)
        c1, r1 = block_of(grid, window.row_off, window.col_off + window.width - 1, self.block_px)
        rows = slice(max(0, self.top - (r1 + 1)), max(0, self.top - (r0 - 1) + 1))
        cols = slice(max(0, c0 - 1 - self.left), max(0, c1 + 1 - self.left + 1))
        if self.everywhere:
            return self
        return BlockMap(
            self.block_px,
            self.left + cols.start,
            self.top - rows.start,
            self.inside[rows, cols].copy(),
            self.border[rows, cols].copy(),
            cut=None if self.cut is None else self.cut[rows, cols].copy(),
        )


def block_size_px(grid: Grid, block_m: float, unit_m: float) -> int:
    """Pixels per block side for a block size in metres (at least 1)."""
    return max(1, round(block_m / unit_m / grid.resolution))


def occupied_blocks(count: np.ndarray, window: PixelWindow, grid: Grid, block_px: int) -> np.ndarray:
    """Packed keys ``(block_col, block_row)`` of the absolute blocks holding data in ``window``."""
    rows, cols = np.nonzero(count > 0)
    if len(rows) == 0:
        return np.empty(0, np.int64)
    block_cols = np.floor_divide(grid.col_min + window.col_off + cols, block_px)
    block_rows = np.floor_divide(grid.row_top - (window.row_off + rows), block_px)
    return np.unique(_pack(block_cols, block_rows))


def footprint_map(
    keys: list[np.ndarray],
    grid: Grid,
    block_px: int,
    *,
    closing_blocks: int,
    everything: bool = False,
    area_blocks: Callable[[int, int, tuple[int, int]], np.ndarray] | None = None,
) -> BlockMap:
    """Close and fill the survey's block occupancy into its footprint (``everything``: the whole grid).

    The map covers only the bounding box of the occupied blocks (nothing outside
    it can be inside a closing of them, nor a void cut open between them), so its
    size follows the data, never the survey's bounding box; with ``everything`` no
    map is built at all. ``area_blocks(left, top, shape)`` says which blocks of a
    map (first column ``left``, first row ``top``, counting up) lie in the survey
    area; with it, the voids the area's edge cuts open between data
    (:func:`edge_voids`) are inside.
    """
    packed = np.concatenate(keys) if keys else np.empty(0, np.int64)
    if everything or len(packed) == 0:
        empty = np.zeros((0, 0), bool)
        return BlockMap(block_px, 0, 0, empty, empty, everywhere=everything)
    block_cols, block_rows = _unpack(packed)
    left, right = int(block_cols.min()), int(block_cols.max())
    bottom, top = int(block_rows.min()), int(block_rows.max())
    occupied = np.zeros((top - bottom + 1, right - left + 1), bool)
    occupied[top - block_rows, block_cols - left] = True
    inside = data_footprint(occupied, closing_px=closing_blocks)
    # blocks with an outside neighbour: their pixels are inside only where the data's own closing reaches
    border = inside & ~ndi.binary_erosion(inside, border_value=0)
    cut = None
    if area_blocks is not None:
        # one block of margin all round: whether the area goes on beyond the data's blocks
        in_area = area_blocks(left - 1, top + 1, (inside.shape[0] + 2, inside.shape[1] + 2))
        cut_open = edge_voids(np.pad(inside, 1), in_area)[1:-1, 1:-1]
        inside = inside | cut_open
        border |= cut_open
        # where the footprint meets the area's end (or a void the cut opens), the cut bounds it,
        # not the data: there the pixels a swath swept are inside too (aoi_mask)
        beside_empty = ndi.binary_dilation(in_area & ~np.pad(inside, 1))[1:-1, 1:-1]  # a 4-neighbour
        cut = border & ~beside_empty
    return BlockMap(block_px, left, top, inside, border, cut=cut)


def edge_voids(footprint: np.ndarray, in_area: np.ndarray) -> np.ndarray:
    """Voids that one straight edge of the survey area cuts open, with data on both sides of the cut.

    A survey delivered as tiles (or cut to an extract) ends at straight lines that
    run through whatever lies there: a canal or a lake crossing the cut is a void
    open to the outside, and the footprint's closing (which counts the outside as
    empty land) leaves it exterior. The evidence that the survey went on across it
    is the data on both sides *along the cut*: a void whose contact with the area's
    edge is one stretch of one straight side (one row or one column of blocks,
    beyond which the area ends), with footprint blocks at both ends of the stretch
    on the same line, lies between data the survey holds on both sides, as a void
    enclosed by data does. The empty corner of a tile beside a diagonal strip meets
    two sides (it turns the tile's corner) and the margin beside the survey's last
    line has data at one end only: both stay exterior.

    Parameters
    ----------
    footprint : ndarray of bool, shape (M, N)
        The data footprint (:func:`data_footprint`) on a block lattice.
    in_area : ndarray of bool, shape (M, N)
        Blocks inside the survey area. A void reaching the array's outer ring inside
        the area is not judged (the area goes on beyond what the arrays show).

    Returns
    -------
    ndarray of bool, shape (M, N)
        The blocks of the voids cut open by the area's edge.
    """
    footprint = np.asarray(footprint, dtype=bool)
    in_area = np.asarray(in_area, dtype=bool)
    if footprint.shape != in_area.shape or footprint.ndim != 2:
        raise ValueError(f"footprint {footprint.shape} and in_area {in_area.shape} must be one 2-d shape")
    exterior = in_area & ~footprint
    labels, count = ndi.label(exterior)
    out = np.zeros(footprint.shape, bool)
    if count == 0:
        return out
    beyond = np.pad(~in_area, 1, constant_values=False)
    # contact with the area's edge, per side: the neighbour up / down / left / right lies beyond the area
    sides = (beyond[:-2, 1:-1], beyond[2:, 1:-1], beyond[1:-1, :-2], beyond[1:-1, 2:])
    rim = np.zeros(footprint.shape, bool)
    rim[[0, -1], :] = True
    rim[:, [0, -1]] = True
    unjudged = np.unique(labels[rim & exterior])
    touches = np.stack([np.bincount(labels[exterior & side], minlength=count + 1) > 0 for side in sides])
    for label in np.flatnonzero(touches.sum(axis=0) == 1):
        if label == 0 or label in unjudged:
            continue
        side = int(np.flatnonzero(touches[:, label])[0])
        rows, cols = np.nonzero((labels == label) & sides[side])
        along, across = (cols, rows) if side < 2 else (rows, cols)
        if len(np.unique(across)) != 1:
            continue  # the area's edge steps along the void: no straight cut
        line = int(across[0])
        ends = (int(along.min()) - 1, int(along.max()) + 1)
        cells = [(line, e) if side < 2 else (e, line) for e in ends]
        if all(0 <= r < footprint.shape[0] and 0 <= c < footprint.shape[1] and footprint[r, c] for r, c in cells):
            out |= labels == label
    return out


def aoi_mask(
    window: PixelWindow,
    grid: Grid,
    blocks: BlockMap,
    *,
    count: np.ndarray,
    survey_area: np.ndarray,
    swept: np.ndarray | None = None,
) -> np.ndarray:
    """Which pixels of ``window`` are inside the AOI.

    Parameters
    ----------
    window : PixelWindow
        Usually a cell's halo window.
    blocks : BlockMap
        The footprint (or a slice of it covering the window).
    count : ndarray, shape of ``window``
        Points per pixel.
    survey_area : ndarray of bool, shape of ``window``
        The tile windows or the ``--aoi`` polygon.
    swept : ndarray of bool, shape of ``window``, optional
        Pixels some flight line's swath covers. In blocks the area's cut bounds
        (``blocks.cut``), an empty pixel beyond the data's own closing is inside where
        a swath swept it: the survey went on across it (a canal crossing an extract's
        edge); outside every swath it is the scanner's edge wobbling short of the cut.
    """
    if blocks.everywhere:
        return survey_area.copy()
    if blocks.inside.size == 0:
        return np.zeros(window.shape, bool)
    rows = np.arange(window.row_off, window.row_end)
    cols = np.arange(window.col_off, window.col_end)
    block_rows = blocks.top - np.floor_divide(grid.row_top - rows, blocks.block_px)
    block_cols = np.floor_divide(grid.col_min + cols, blocks.block_px) - blocks.left
    valid_r = (block_rows >= 0) & (block_rows < blocks.inside.shape[0])
    valid_c = (block_cols >= 0) & (block_cols < blocks.inside.shape[1])
    br = np.clip(block_rows, 0, blocks.inside.shape[0] - 1)
    bc = np.clip(block_cols, 0, blocks.inside.shape[1] - 1)
    valid = valid_r[:, None] & valid_c[None, :]
    inside = blocks.inside[np.ix_(br, bc)] & valid
    border = blocks.border[np.ix_(br, bc)] & valid
    if swept is not None and blocks.cut is not None:
        border &= ~(blocks.cut[np.ix_(br, bc)] & swept)
    occupied = count > 0
    disc = _disc(EDGE_CLOSING_PX)
    padded = np.pad(occupied, EDGE_CLOSING_PX * 2, mode="edge")
    closed = ndi.binary_closing(padded, structure=disc)[
        EDGE_CLOSING_PX * 2 : -EDGE_CLOSING_PX * 2, EDGE_CLOSING_PX * 2 : -EDGE_CLOSING_PX * 2
    ]
    return survey_area & inside & (~border | closed | occupied)


def block_of(grid: Grid, row: int, col: int, block_px: int) -> tuple[int, int]:
    """The absolute block (column, row counting up) of a grid pixel."""
    return (grid.col_min + col) // block_px, (grid.row_top - row) // block_px


def _disc(radius: int) -> np.ndarray:
    yy, xx = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    return xx**2 + yy**2 <= radius**2


_OFFSET = np.int64(1) << 30  # block indices up to +-2^30 fit both halves of an int64


def _pack(block_cols: np.ndarray, block_rows: np.ndarray) -> np.ndarray:
    return ((block_cols.astype(np.int64) + _OFFSET) << 32) | (block_rows.astype(np.int64) + _OFFSET)


def _unpack(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return (keys >> 32) - _OFFSET, (keys & np.int64(0xFFFFFFFF)) - _OFFSET
