"""The survey's density on its data footprint: pulses counted in the blocks of an absolute lattice.

A header's box is an upper bound of where its points are, and can be far larger:
``ign_laspy_appendbug`` holds 3.85 first returns/m² on two patches 1 km apart
(8,150 m²) and 0.04 over its 0.76 km² box; ``wires_quebec``'s diagonal strip
fills 36 % of its box. A pixel size chosen from the header density is then 10 m
where 2 m is supported, and a sampling-gap width from it hides real voids. No
cheaper source knows the footprint: point order (flight lines, or spatial
sort) makes any subset of LAZ chunks a biased sample of where data is, and LAZ
chunk tables hold no positions. So every point's x, y and return number are read,
and first returns (all points where the headers cannot tell returns apart) are
counted in square blocks on an absolute lattice (:class:`BlockCounter`).

Who counts: stage 1, as it decodes the points for the DSM (``TileTask.counting``). The
run is planned with the headers' density meanwhile and settled from the counts after
stage 1 (:func:`pipeline.run.settle_density`): where the footprint gives the same pixel and
cell sizes (31 of the 37 real files, every tiled survey whose tiles are full), nothing is
decoded twice; where it does not, stage 1 runs again on the grid the footprint supports.
A pre-pass over the files (:func:`measure_footprint`: x, y and return numbers alone,
decoded in processes) counts the same blocks for the PDAL reader, whose points are the
user's pipeline's. Either way the counts, and so the plan, are the same.

The blocks are 1 m, coarsened by powers of two only where a survey's tile boxes
would need more than :data:`MAX_BLOCKS` (16 km² at 1 m: a block map of at most
a few tens of MB on the client). The counts are then read at the finest power
of two whose occupied blocks hold on average :data:`pipeline.survey.density.BLOCK_PULSES`
pulses (8: a block inside the footprint is empty by chance with probability
e^-8 = 0.03 % for a random pattern), and the footprint is the occupied blocks'
area. Blocks on the data's edge count whole, so the density errs low (towards
coarser pixels) by about half a block along the edge. The lattice is absolute and
counts from overlapping tiles add up, so the result depends neither on the cell
size nor on how the survey is cut into tiles (below the 16 km² of tile boxes
where the base block doubles).

The same counts give a local density around each hole (:func:`local_pulses_per_m2`),
from which the sampling-gap width follows (:mod:`pipeline.survey.density`).
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import os
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Any

import numba
import numpy as np
import shapely
from pyproj import CRS, Transformer

from ..errors import InputDataError
from ..grid import Grid
from ..io.las import iter_xy
from .blocks import (
    BlockCounts,
    BlockPart,
    Blocks,
    BlockWindow,
    DenseBlockCounts,
    FootprintDensity,
    block_histogram,
    merge_blocks,
)
from .density import BLOCK_PULSES, narrow_width, sampling_gap_width_m
from .scan import Survey, source_crs_for_task

logger = logging.getLogger(__name__)

#: Side of the finest block (metres).
BASE_BLOCK_M = 1.0
#: The base block doubles until the union of the tile boxes holds at most this many blocks.
MAX_BLOCKS = 1 << 24
#: A file's counts are kept in a dense array when its box holds at most this many blocks.
DENSE_FILE_BLOCKS = 1 << 22
#: The coarsest block is ``BASE_BLOCK_M * 2**MAX_LEVEL`` (256 m at the base).
MAX_LEVEL = 8
#: Points decoded at a time by the pre-pass.
CHUNK_POINTS = 1_000_000
#: A process of the pre-pass decodes at least this many points: x, y alone decode at about
#: 2 M points/s a core (1.8 M on the 2-core VM), so a process decodes for a second or more,
#: twice what it takes to start (fork, import laspy and pyproj).
POINTS_PER_PROCESS = 2_000_000
#: Threads of the pre-pass where it runs in this process.
MAX_THREADS = 8
#: Around a hole, the blocks within this many blocks of its bounding box give its local density.
LOCAL_MARGIN_BLOCKS = 4
#: ... at most this many blocks across (a larger window is centred on the hole).
LOCAL_WINDOW_BLOCKS = 128


def choose_level(base: Blocks, *, min_mean: float = BLOCK_PULSES, max_level: int = MAX_LEVEL) -> Blocks:
    """The finest coarsening (by powers of two) whose occupied blocks hold ``min_mean`` pulses on average.

    Each level is the one before coarsened by two (``ix // 2**(k + 1) == (ix // 2**k) // 2``).
    """
    blocks = base
    for level in range(max_level + 1):
        if level:
            blocks = blocks.coarsen(2)
        if blocks.occupied == 0 or blocks.total / blocks.occupied >= min_mean:
            return blocks
    return blocks


def base_block(survey: Survey) -> float:
    """The finest block (survey CRS units): 1 m, doubled while the tile boxes would hold more than MAX_BLOCKS."""
    area = shapely.union_all([shapely.box(*t.bounds) for t in survey.tiles]).area
    block = BASE_BLOCK_M / survey.horizontal_unit_m
    while area / block**2 > MAX_BLOCKS:
        block *= 2
    return block


@dataclass(frozen=True)
class PulseCounting:
    """How a reader counts a file's pulses in the blocks of the survey's lattice.

    ``bounds`` is the file's box (survey CRS): points beyond it count in its edge blocks,
    as the pre-pass counts them; ``first_only``: first returns only (the headers can tell
    returns apart).
    """

    bounds: tuple[float, float, float, float]
    block: float
    first_only: bool


def pulse_counting(survey: Survey) -> tuple[float, bool]:
    """The survey's block (:func:`base_block`) and whether first returns alone are counted."""
    return base_block(survey), survey.header_density.first_returns


def measure_footprint(survey: Survey, *, workers: int | None = None) -> Survey:
    """The survey with its density measured on the data footprint (decodes x, y of every point).

    The files are decoded side by side in up to ``workers`` (default: the machine's cores)
    processes, one per :data:`POINTS_PER_PROCESS` points at least; a small survey is
    decoded in this process, on threads. A run reading with laspy counts the same blocks
    in stage 1 instead (:func:`footprint_from_counts`); this pre-pass serves the PDAL reader,
    whose points are the user's pipeline's, not the file's.
    """
    started = time.perf_counter()
    block, first = pulse_counting(survey)
    target = survey.crs.to_wkt()
    tasks = [(str(t.path), source_crs_for_task(t, survey), target, t.bounds, block, first) for t in survey.tiles]
    cores = workers or os.cpu_count() or 1
    processes = max(1, min(len(tasks), cores, math.ceil(survey.point_count / POINTS_PER_PROCESS)))
    parts = _count_files(tasks, processes, threads=max(1, min(len(tasks), cores, MAX_THREADS)))
    measured = footprint_from_counts(survey, parts, started, how=f"the pre-pass, {processes} process(es)")
    return replace(survey, footprint=measured)


def footprint_from_counts(
    survey: Survey,
    parts: list[BlockPart],
    started: float,
    *,
    how: str,
) -> FootprintDensity:
    """The density on the data footprint from the files' block counts (the pre-pass's or stage 1's,
    in the survey's blocks: :func:`pulse_counting`).

    ``started``: when the counting began (``time.perf_counter()``), for the record and the log.
    """
    block, first = pulse_counting(survey)
    blocks = choose_level(merge_blocks(parts, block))
    pulses = blocks.total
    area_m2 = blocks.occupied * (blocks.block * survey.horizontal_unit_m) ** 2
    measured = FootprintDensity(blocks, survey.point_count, pulses, first, area_m2, time.perf_counter() - started)
    logger.info(
        "density on the data footprint: %d %s over %.6g m2 (%.4g m blocks), %.3g /m2; %.2f s (%s)",
        pulses,
        "first returns" if first else "points",
        area_m2,
        blocks.block * survey.horizontal_unit_m,
        pulses / area_m2 if area_m2 else math.inf,
        measured.seconds,
        how,
    )
    return measured


def _count_files(tasks: list[tuple], processes: int, *, threads: int) -> list[BlockPart]:
    """Each file's counts (:func:`_count_file_or_none` of each task): in ``processes`` processes
    where more than one, else on ``threads`` threads of this one.

    Decoding is the cost, and processes scale with cores where threads need lazrs to release
    the GIL (on a 16-core machine the threads' pre-pass took 10 s at every worker count). The
    processes fork from the local cluster's fork server where it runs (distributed and numpy
    already imported; SIGINT blocked, so a Ctrl-C reaches this process alone).
    """
    columns = list(zip(*tasks, strict=True)) if tasks else []
    if processes <= 1 or len(tasks) <= 1:
        with ThreadPoolExecutor(max_workers=threads) as threads_pool:
            return list(threads_pool.map(_count_file_or_none, *columns))
    method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
    pool = ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context(method))
    try:
        return list(pool.map(_count_file_or_none, *columns, chunksize=1))
    finally:  # on Ctrl-C the files not begun are dropped; those under way finish (a tile's seconds)
        pool.shutdown(wait=True, cancel_futures=True)


def _count_file_or_none(
    path: str,
    source_wkt: str | None,
    target_wkt: str,
    bounds: tuple[float, float, float, float],
    block: float,
    first_only: bool,
) -> BlockPart:
    """A file's counts; none for a file that cannot be decoded: stage 1 fails it or skips it
    (``survey.on_error``) with the same message, and the density comes from the others."""
    try:
        return _count_file(path, source_wkt, target_wkt, bounds, block, first_only)
    except InputDataError as e:
        logger.debug("density pre-pass: %s", e)
        empty = np.zeros(0, np.int64)
        return empty, empty, empty


def _count_file(
    path: str,
    source_wkt: str | None,
    target_wkt: str,
    bounds: tuple[float, float, float, float],
    block: float,
    first_only: bool,
) -> BlockPart:
    """One file's occupied base blocks and counts (pure of the survey: runs in a worker process)."""
    transformer = (
        Transformer.from_crs(CRS.from_wkt(source_wkt), CRS.from_wkt(target_wkt), always_xy=True) if source_wkt else None
    )
    counter = BlockCounter(bounds, block)
    for x, y in iter_xy(path, CHUNK_POINTS, first_only=first_only):
        if transformer is not None:
            x, y = transformer.transform(x, y)
        counter.add(x, y)
    return counter.counts()


class BlockCounter:
    """One file's points counted in the blocks of an absolute lattice, chunk by chunk.

    A dense array over the file's box where it holds at most :data:`DENSE_FILE_BLOCKS`
    blocks (points beyond the box count in its edge blocks), else sparse histograms.
    """

    def __init__(self, bounds: tuple[float, float, float, float], block: float) -> None:
        minx, miny, maxx, maxy = bounds
        self.block = block
        self.x0, self.y0 = math.floor(minx / block), math.floor(miny / block)
        self.cols = math.floor(maxx / block) - self.x0 + 1
        self.rows = math.floor(maxy / block) - self.y0 + 1
        dense = self.cols * self.rows <= DENSE_FILE_BLOCKS
        self.dense: np.ndarray | None = np.zeros(self.cols * self.rows, np.int64) if dense else None
        self.sparse: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def add(self, x: np.ndarray, y: np.ndarray) -> None:
        """Count points at scaled coordinates ``x``, ``y`` (survey CRS)."""
        if self.dense is None:
            self.sparse.append(block_histogram(x, y, self.block))
            return
        ix = np.clip(np.floor(x / self.block).astype(np.int64) - self.x0, 0, self.cols - 1)
        iy = np.clip(np.floor(y / self.block).astype(np.int64) - self.y0, 0, self.rows - 1)
        self.dense += np.bincount(ix * self.rows + iy, minlength=self.cols * self.rows)

    def add_records(
        self,
        x: np.ndarray,
        y: np.ndarray,
        scales: tuple[float, float, float],
        offsets: tuple[float, float, float],
        return_number: np.ndarray | None = None,
    ) -> None:
        """Count points at a LAS record's integer ``x``, ``y`` (``X * scale + offset``, as :meth:`add` is given
        them), the first returns alone where ``return_number`` is given: one compiled pass, no array per step."""
        if self.dense is None:
            if return_number is not None:
                first = return_number == 1
                x, y = x[first], y[first]
            self.add(x * scales[0] + offsets[0], y * scales[1] + offsets[1])
            return
        first_only = return_number is not None
        returns = return_number if return_number is not None else np.empty(0, np.uint8)
        _count_dense(
            self.dense, x, y, scales[0], offsets[0], scales[1], offsets[1], returns, first_only,
            self.block, self.x0, self.y0, self.cols, self.rows,
        )  # fmt: skip

    def counts(self) -> BlockPart:
        """The counts: the dense box as a :class:`BlockWindow`, else the occupied blocks ``(ix, iy, count)``."""
        if self.dense is None:
            merged = merge_blocks(self.sparse, self.block)
            return merged.ix, merged.iy, merged.count
        return BlockWindow.of(self.x0, self.y0, self.cols, self.rows, self.dense)


@numba.njit(cache=True, nogil=True)
def _count_dense(
    dense, xs, ys, scale_x, offset_x, scale_y, offset_y, return_number, first_only, block, x0, y0, cols, rows
):
    """:meth:`BlockCounter.add` on raw records: the same expressions, point by point."""
    for i in range(len(xs)):
        if first_only and return_number[i] != 1:
            continue
        ix = min(max(np.int64(math.floor((xs[i] * scale_x + offset_x) / block)) - x0, 0), cols - 1)
        iy = min(max(np.int64(math.floor((ys[i] * scale_y + offset_y) / block)) - y0, 0), rows - 1)
        dense[ix * rows + iy] += 1


def local_pulses_per_m2(blocks: Blocks, boxes: np.ndarray) -> np.ndarray:
    """Per box (``minx, miny, maxx, maxy`` rows, CRS units): the median pulses per occupied block around it, per CRS unit².

    The window is the box grown by :data:`LOCAL_MARGIN_BLOCKS` blocks, at most
    :data:`LOCAL_WINDOW_BLOCKS` blocks across (centred on the box). The median
    leaves out the partly filled blocks along a void's edge. NaN where the window
    holds no occupied block.
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    out = np.full(len(boxes), np.nan)
    if blocks.occupied == 0:
        return out
    if isinstance(blocks, DenseBlockCounts):
        per_box = _dense_window_counts(blocks, boxes)
    else:
        per_box = _listed_window_counts(blocks, boxes)
    for i, found in enumerate(per_box):
        if len(found):
            out[i] = float(np.median(found)) / blocks.block**2
    return out


def _dense_window_counts(blocks: DenseBlockCounts, boxes: np.ndarray) -> Iterator[np.ndarray]:
    """The occupied blocks' counts in each box's window (:func:`_window`), read from the dense box."""
    cols, rows = blocks.counts.shape
    for minx, miny, maxx, maxy in boxes:
        cx = _window(minx, maxx, blocks.block) - blocks.x0
        cy = _window(miny, maxy, blocks.block) - blocks.y0
        x0, x1 = max(int(cx[0]), 0), min(int(cx[-1]) + 1, cols)
        y0, y1 = max(int(cy[0]), 0), min(int(cy[-1]) + 1, rows)
        window = blocks.counts[x0:x1, y0:y1] if x0 < x1 and y0 < y1 else blocks.counts[:0, :0]
        yield window[window > 0]


def _listed_window_counts(blocks: BlockCounts, boxes: np.ndarray) -> Iterator[np.ndarray]:
    """The occupied blocks' counts in each box's window (:func:`_window`), looked up among the listed blocks."""
    x0, y0 = int(blocks.ix.min()), int(blocks.iy.min())
    rows = int(blocks.iy.max()) - y0 + 1
    keys = (blocks.ix - x0) * rows + (blocks.iy - y0)
    counts = blocks.count
    if len(keys) > 1 and not (keys[1:] >= keys[:-1]).all():  # merged blocks come in key order (0.3 s saved at 4 M)
        order = np.argsort(keys)
        keys, counts = keys[order], counts[order]
    for minx, miny, maxx, maxy in boxes:
        cx = _window(minx, maxx, blocks.block)
        cy = _window(miny, maxy, blocks.block)
        gx, gy = np.meshgrid(cx - x0, cy - y0, indexing="ij")
        inside = (gy >= 0) & (gy < rows)
        wanted = (gx * rows + gy)[inside]
        at = np.clip(np.searchsorted(keys, wanted), 0, len(keys) - 1)
        yield counts[at][keys[at] == wanted]


def _window(lo: float, hi: float, block: float) -> np.ndarray:
    first, last = math.floor(lo / block) - LOCAL_MARGIN_BLOCKS, math.floor(hi / block) + LOCAL_MARGIN_BLOCKS
    if last - first + 1 > LOCAL_WINDOW_BLOCKS:
        first = (first + last) // 2 - LOCAL_WINDOW_BLOCKS // 2
        last = first + LOCAL_WINDOW_BLOCKS - 1
    return np.arange(first, last + 1, dtype=np.int64)


def sampling_gap_px(survey: Survey, grid: Grid, stats: Any, survey_gap_px: float) -> np.ndarray:
    """Per hole, the width (pixels) under which it is a sampling gap: 4 local point spacings.

    ``stats``: the holes' merged statistics (``area_px``, ``edge_len_px`` and the
    bounding box in grid rows and columns). The local density is read around each
    hole that could be a gap at all (no wider than four spacings of a block holding
    one pulse); the survey-wide width ``survey_gap_px`` stands where the density was
    not measured or no block lies near. 0 (no sampling gaps) stays 0.
    """
    n = len(stats["area_px"])
    out = np.full(n, float(survey_gap_px))
    blocks = survey.footprint.blocks if survey.footprint is not None else None
    if survey_gap_px <= 0 or blocks is None or n == 0:
        return out
    pixel_m = grid.resolution * survey.horizontal_unit_m
    widest_px = sampling_gap_width_m(blocks.block * survey.horizontal_unit_m) / pixel_m
    candidates = np.flatnonzero(narrow_width(stats["area_px"], stats["edge_len_px"]) <= widest_px)  # void_width >= it
    if len(candidates) == 0:
        return out
    col_min, col_max, row_min, row_max = (
        np.asarray(stats[k])[candidates] for k in ("col_min", "col_max", "row_min", "row_max")
    )
    r = grid.resolution
    boxes = np.column_stack(
        [
            grid.x_left + col_min * r,
            grid.y_top - (row_max + 1) * r,
            grid.x_left + (col_max + 1) * r,
            grid.y_top - row_min * r,
        ]
    )
    per_m2 = local_pulses_per_m2(blocks, boxes) / survey.horizontal_unit_m**2
    known = np.isfinite(per_m2) & (per_m2 > 0)
    spacing_m = 1.0 / np.sqrt(per_m2[known])
    out[candidates[known]] = sampling_gap_width_m(spacing_m) / pixel_m  # type: ignore[arg-type]
    return out


__all__ = [
    "BlockCounter",
    "BlockCounts",
    "FootprintDensity",
    "block_histogram",
    "choose_level",
    "footprint_from_counts",
    "local_pulses_per_m2",
    "measure_footprint",
    "merge_blocks",
    "pulse_counting",
    "PulseCounting",
    "sampling_gap_px",
]
