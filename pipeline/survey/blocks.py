"""Points counted in square blocks of an absolute lattice, and what the density pre-pass measured (pure).

The records and array kernels of :mod:`pipeline.survey.footprint_density`, apart so that the
survey's own record (:class:`pipeline.survey.scan.Survey`) can hold a measurement without
importing the pre-pass that makes it.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np

from .density import Density


@dataclass(frozen=True)
class BlockCounts:
    """Pulses counted in square blocks of an absolute lattice (only the occupied blocks).

    Block ``(ix, iy)`` covers ``[ix * block, (ix + 1) * block)`` in x, likewise in y
    (survey CRS units).
    """

    block: float
    ix: np.ndarray  # int64
    iy: np.ndarray  # int64
    count: np.ndarray  # int64, > 0

    @property
    def occupied(self) -> int:
        return len(self.count)

    @property
    def total(self) -> int:
        """The pulses counted in all blocks."""
        return int(self.count.sum())

    def coarsen(self, factor: int) -> Blocks:
        """The same counts in blocks ``factor`` times as wide (floor division keeps the lattice absolute)."""
        if factor == 1:
            return self
        return merge_blocks([(self.ix // factor, self.iy // factor, self.count)], self.block * factor)


@dataclass(frozen=True)
class DenseBlockCounts:
    """The counts of :class:`BlockCounts` over a dense box of the lattice: block ``(x0 + i, y0 + j)``
    holds ``counts[i, j]`` pulses (0: none).

    What the survey's footprint is where its blocks fill their box (a tiled survey): 8 bytes a
    block, where the occupied blocks' three arrays took 24 and each meant a pass over all of
    them (0.3-0.5 s of the client's at the end of stage 1 on the 42 M-point survey's 4 M
    blocks). The occupied blocks, in key order, are made on first use (:attr:`ix`, :attr:`iy`,
    :attr:`count`).
    """

    block: float
    x0: int
    y0: int
    counts: np.ndarray  # int64, shape (cols, rows)

    @functools.cached_property
    def occupied(self) -> int:
        return int(np.count_nonzero(self.counts))

    @property
    def total(self) -> int:
        """The pulses counted in all blocks."""
        return int(self.counts.sum())

    @functools.cached_property
    def _listed(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return _occupied(self.counts.ravel(), self.x0, self.y0, self.counts.shape[1])

    @property
    def ix(self) -> np.ndarray:
        return self._listed[0]

    @property
    def iy(self) -> np.ndarray:
        return self._listed[1]

    @property
    def count(self) -> np.ndarray:
        return self._listed[2]

    def coarsen(self, factor: int) -> DenseBlockCounts:
        """The same counts in blocks ``factor`` times as wide (block ``ix // factor``, as :meth:`BlockCounts.coarsen`)."""
        if factor == 1:
            return self
        x0, y0 = self.x0 // factor, self.y0 // factor  # floor: the coarse block holding the box's first
        cols, rows = self.counts.shape
        lead_x, lead_y = self.x0 - x0 * factor, self.y0 - y0 * factor
        coarse_cols, coarse_rows = -(-(lead_x + cols) // factor), -(-(lead_y + rows) // factor)
        padded = np.zeros((coarse_cols * factor, coarse_rows * factor), self.counts.dtype)
        padded[lead_x : lead_x + cols, lead_y : lead_y + rows] = self.counts
        coarse = padded.reshape(coarse_cols, factor, coarse_rows, factor).sum(axis=(1, 3))
        return DenseBlockCounts(self.block * factor, x0, y0, coarse)


#: Block counts in either form (the same blocks and counts).
Blocks = BlockCounts | DenseBlockCounts


@dataclass(frozen=True)
class FootprintDensity:
    """What the pre-pass measured: the blocks at the level chosen, and the totals."""

    blocks: Blocks
    points: int  # the headers' point count
    pulses: int  # the points counted (first returns when ``first_returns``)
    first_returns: bool
    area_m2: float  # the occupied blocks' area
    seconds: float  # wall time of the pre-pass

    def density(self) -> Density:
        return Density(self.points, self.pulses, self.area_m2, self.first_returns, area_source="data footprint")


@dataclass(frozen=True)
class BlockWindow:
    """Counts over a dense box of lattice blocks: a file's footprint counts as stage 1 sends them.

    Block ``(x0 + i, y0 + j)`` holds ``counts[i * rows + j]`` (zero: no point), in the smallest
    unsigned type that holds the largest count. A 250 m tile's one-metre blocks are 62,500
    numbers of one or two bytes, where their occupied ``(ix, iy, count)`` took 24 bytes each
    (1.5 MB a tile, 96 MB from the 42 M-point survey's 64 tiles to the client).
    """

    x0: int
    y0: int
    cols: int
    rows: int
    counts: np.ndarray

    @classmethod
    def of(cls, x0: int, y0: int, cols: int, rows: int, counts: np.ndarray) -> BlockWindow:
        """The window of ``counts`` (any integer type), kept in the smallest unsigned type that holds them."""
        largest = int(counts.max(initial=0))
        return cls(x0, y0, cols, rows, counts.astype(np.min_scalar_type(largest)))

    def occupied(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The occupied blocks ``(ix, iy, count)``, int64, in key order."""
        ix, iy, count = _occupied(self.counts, self.x0, self.y0, self.rows)
        return ix, iy, count.astype(np.int64)


#: One file's block counts, as a reader sends them: the occupied blocks, or a dense window of them.
BlockPart = tuple[np.ndarray, np.ndarray, np.ndarray] | BlockWindow


def block_histogram(x: np.ndarray, y: np.ndarray, block: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Occupied blocks of side ``block`` and their point counts (pure).

    >>> block_histogram(np.array([0.5, 0.7, 2.1]), np.array([0.1, 0.2, -0.5]), 1.0)
    (array([0, 2]), array([ 0, -1]), array([2, 1]))
    """
    ix = np.floor(np.asarray(x, np.float64) / block).astype(np.int64)
    iy = np.floor(np.asarray(y, np.float64) / block).astype(np.int64)
    merged = merge_blocks([(ix, iy, np.ones(len(ix), np.int64))], block)
    return merged.ix, merged.iy, merged.count


def merge_blocks(parts: Sequence[BlockPart], block: float) -> Blocks:
    """Counts of the same lattice added up block by block (tiles that overlap, chunks of a file).

    Dense (:class:`DenseBlockCounts`) where the blocks' box is not much larger than their
    number, else the occupied blocks (:class:`BlockCounts`): the same blocks and counts.
    """
    windows = [p for p in parts if isinstance(p, BlockWindow) and p.cols * p.rows]
    listed = [p for p in parts if not isinstance(p, BlockWindow) and len(p[0])]
    if not windows and not listed:
        empty = np.zeros(0, np.int64)
        return BlockCounts(block, empty, empty, empty)
    boxes = [(w.x0, w.x0 + w.cols - 1, w.y0, w.y0 + w.rows - 1) for w in windows]
    boxes += [(int(ix.min()), int(ix.max()), int(iy.min()), int(iy.max())) for ix, iy, _ in listed]
    x0, x1 = min(b[0] for b in boxes), max(b[1] for b in boxes)
    y0, y1 = min(b[2] for b in boxes), max(b[3] for b in boxes)
    cols, rows = x1 - x0 + 1, y1 - y0 + 1
    blocks = sum(w.cols * w.rows for w in windows) + sum(len(p[0]) for p in listed)
    # a dense tally beats sorting where the blocks' box is not much larger than their number (0.29 -> 0.07 s
    # on the 42 M survey's 4 M blocks; compiled and part by part, 0.55 -> 0.07 s for its 64 files' counts)
    if cols * rows <= min(DENSE_SPAN_MAX, 4 * blocks + (1 << 20)):
        tally = np.zeros(cols * rows, np.int64)
        grid = tally.reshape(cols, rows)
        for w in windows:  # added in place: no concatenated copy
            grid[w.x0 - x0 : w.x0 - x0 + w.cols, w.y0 - y0 : w.y0 - y0 + w.rows] += w.counts.reshape(w.cols, w.rows)
        for ix, iy, count in listed:
            _tally(tally, ix, iy, count, x0, y0, rows)
        return DenseBlockCounts(block, x0, y0, grid)
    # blocks spread far apart: sort the keys
    listed += [w.occupied() for w in windows]
    ix, iy, count = (np.concatenate([np.asarray(p[k], np.int64) for p in listed]) for k in range(3))
    keys = (ix - x0) * rows + (iy - y0)
    unique, inverse = np.unique(keys, return_inverse=True)
    sums = np.bincount(inverse, weights=count, minlength=len(unique)).astype(np.int64)
    return BlockCounts(block, unique // rows + x0, unique % rows + y0, sums)


@numba.njit(cache=True, nogil=True)
def _tally(tally, ix, iy, count, x0, y0, rows):
    """Add each block's count into a dense array over the box from ``(x0, y0)``, ``rows`` blocks tall."""
    for i in range(len(ix)):
        tally[(ix[i] - x0) * rows + (iy[i] - y0)] += count[i]


def _occupied(tally: np.ndarray, x0: int, y0: int, rows: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The blocks of a dense tally that hold points: ``(ix, iy, count)``, in key order.

    Plain numpy: on the client, where the files' windows are added up once a run, loading a
    compiled kernel from numba's cache (0.1 s each) cost more than the work (4 M blocks: 30 ms).
    """
    keys = np.flatnonzero(tally)
    return keys // rows + x0, keys % rows + y0, tally[keys]


#: :func:`merge_blocks` tallies in a dense array where the blocks' box holds at most this many (128 MB of int64).
DENSE_SPAN_MAX = 1 << 24
