"""Stage 2, one task per cell: merge the statistics of the tiles touching the cell and its halo.

The gather step turns the cells' occupied blocks into the survey's data
footprint (:func:`footprint_blocks`), which hole detection needs.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import logging
import math
from dataclasses import dataclass

import numpy as np
import shapely
from affine import Affine

from ..config import Config
from ..grid import Cell, Grid, PixelWindow
from ..holes.coverage import CoverageGaps, coverage_gaps, keep_void_gaps
from ..holes.flight_lines import line_moments, merge_line_moments
from ..io.intermediate import (
    load_cell_statistics,
    load_tile_ground,
    load_tile_shared_keys,
    load_tile_statistics,
    save_cell_statistics,
)
from ..io.raster import geometry_mask
from ..plan import SurveyPlan
from ..rasterize import GroundSums, merge_ground_sums, merge_statistics, shared_pixel_mask
from ..staging import Staging
from ..survey.footprint import BlockMap, block_of, footprint_map, occupied_blocks
from .bin_tiles import BIN_TILES, READ_TASKS, TileFailure, TileResult, TileTask, result_folder
from .stage import RunState, Stage, in_plan_order

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class CellTask:
    """Merge the statistics of the tiles touching one cell.

    The stage-1 results of those tiles are passed to :func:`merge_cell` as
    arguments, so the cell runs as soon as they exist.
    """

    cell: Cell
    grid: Grid
    planned_windows: tuple[PixelWindow, ...]  # windows of every planned tile touching the cell
    statistics_path: str
    block_px: int
    reads: tuple[str, ...] = ()  # result folders of the read tasks touching the cell (their results are its arguments)
    ground: bool = False  # keep the core's ground sums (stage 1 summed them: TileTask.ground)


@dataclass(frozen=True)
class CellResult:
    cell_id: str
    statistics_path: str
    points: int
    pixels: int
    empty_pixels: int
    occupied_blocks: np.ndarray  # packed keys of the footprint blocks holding data
    line_moments: np.ndarray  # LINE_MOMENT_DTYPE: pixel moments of each flight line in the core
    failed_tiles: tuple[int, ...] = ()  # tiles touching the cell that stage 1 skipped (their area is exterior)


def merge_tasks(plan: SurveyPlan, tiles: list[TileTask], staging: Staging) -> list[tuple[CellTask, list[int]]]:
    """One task per planned cell, with the indices of the read tasks it needs.

    A cell that no read task touches is still merged (empty), so that its pixels are
    holes: a missing tile of the tile grid, or a cell inside a split COPC file's
    bounds where no octree node lies (as it would be were the file read whole).
    """
    windows = {t.read_index: t.window for t in tiles}
    ground = any(t.ground for t in tiles)
    recipes = []
    for cell in plan.cells:
        touching = [i for i in plan.reads_of_cell[cell.id] if i in windows]
        task = CellTask(
            cell=cell,
            grid=plan.grid,
            planned_windows=tuple(windows[i] for i in touching),
            statistics_path=str(staging.cell_statistics(cell.id)),
            block_px=plan.block_px,
            ground=ground,
        )
        recipes.append((task, touching))
    return recipes


def merge_key(task: CellTask) -> str:
    """The key of a cell's merge: what its result is made of (the cell, the lattice, its tiles' keys).

    An incremental run reuses the previous run's merge of a cell whose key is unchanged.
    """
    made_of = (
        task.cell,
        task.grid,
        task.planned_windows,
        task.block_px,
        sorted(task.reads),
    ) + (("ground",) if task.ground else ())
    return f"merge-{hashlib.sha1(repr(made_of).encode()).hexdigest()[:12]}-{task.cell.id}"


def adopt_result(task: CellTask, kept: CellResult) -> CellResult:
    """A previous run's merge of the same cell (same key), pointed at this run's files."""
    return dataclasses.replace(kept, statistics_path=task.statistics_path)


def merge_cell(task: CellTask, *tiles: TileResult | TileFailure) -> CellResult:
    """Merge tile statistics over a cell and its halo and keep them for the later stages.

    ``tiles`` are the stage-1 results of the tiles touching the cell; failed
    (skipped) tiles contribute nothing.
    """
    cell, grid = task.cell, task.grid
    window = cell.halo_window
    parts = []
    ground_parts: list[GroundSums | None] = []
    failed = tuple(tile.tile_index for tile in tiles if isinstance(tile, TileFailure))
    for tile in tiles:
        if not isinstance(tile, TileResult):
            continue
        overlap = tile.window.intersection(window)
        if overlap.is_empty:
            continue
        statistics = load_tile_statistics(tile.output_dir, tile.window, overlap)
        parts.append((statistics, load_tile_shared_keys(tile.output_dir)))
        in_core = tile.window.intersection(cell.window)
        if not in_core.is_empty:
            ground_parts.append(load_tile_ground(tile.output_dir, tile.window, in_core))
    shared = shared_pixel_mask(window, task.planned_windows)
    merged = merge_statistics(window, parts, shared=shared, grid_width=grid.width)
    # the core's ground sums for a flight plan's take-off (holes sought), where every tile kept them
    ground = None
    if task.ground and all(part is not None for part in ground_parts):
        ground = merge_ground_sums(cell.window, [part for part in ground_parts if part is not None])
    save_cell_statistics(task.statistics_path, merged, ground)
    core = merged.crop(cell.window)
    return CellResult(
        cell_id=cell.id,
        statistics_path=task.statistics_path,
        points=int(core.count.sum()),
        pixels=cell.window.height * cell.window.width,
        empty_pixels=int((core.count == 0).sum()),
        occupied_blocks=occupied_blocks(core.count, cell.window, grid, task.block_px),
        line_moments=line_moments(
            core.source.astype(np.int64) - 1, row_off=cell.window.row_off, col_off=cell.window.col_off
        ),
        failed_tiles=failed,
    )


def footprint_blocks(results: list[CellResult], plan: SurveyPlan, config: Config) -> BlockMap:
    """Gather: the survey's data footprint from the blocks the cells found occupied.

    A given AOI is authoritative (every empty pixel inside it is a hole); without
    one, the data footprint decides what is exterior.
    """
    holes = config.holes
    failed = sorted({i for r in results for i in r.failed_tiles})
    return footprint_map(
        [r.occupied_blocks for r in results],
        plan.grid,
        plan.block_px,
        closing_blocks=math.ceil(holes.footprint_closing_m / holes.footprint_block_m),
        everything=plan.aoi_given,
        area_blocks=functools.partial(survey_area_blocks, plan, tuple(failed)),
    )


def survey_area_blocks(
    plan: SurveyPlan, failed: tuple[int, ...], left: int, top: int, shape: tuple[int, int]
) -> np.ndarray:
    """Which footprint blocks (first column ``left``, first row ``top``, counting up) meet the survey area.

    The area is the one hole detection uses (``detect_holes.detect_tasks``): the tile
    grid's squares as a polygon, else the tiles' windows, less the tiles stage 1 skipped.
    """
    grid, block_px = plan.grid, plan.block_px
    out = np.zeros(shape, bool)
    if plan.tile_grid is not None:
        size = block_px * grid.resolution
        x0 = (left * block_px - grid.offset) * grid.resolution
        y0 = ((top + 1) * block_px - grid.offset) * grid.resolution
        # a block the area merely touches along its edge is not in it
        area = shapely.buffer(plan.area_without(failed), -1e-3 * grid.resolution, join_style="mitre")
        return geometry_mask(area, Affine(size, 0, x0, 0, -size, y0), shape, all_touched=True)
    lost = set(failed)
    for i, window in enumerate(plan.tile_windows):
        if i in lost or window.is_empty:
            continue
        first_col, first_row = block_of(grid, window.row_off, window.col_off, block_px)
        last_col, last_row = block_of(grid, window.row_end - 1, window.col_end - 1, block_px)
        rows = slice(max(top - first_row, 0), max(min(top - last_row + 1, shape[0]), 0))
        cols = slice(max(first_col - left, 0), max(min(last_col - left + 1, shape[1]), 0))
        out[rows, cols] = True
    return out


def survey_line_moments(results: list[CellResult]) -> np.ndarray:
    """Gather: every flight line's pixel moments over the survey (exact sums of the cells')."""
    return merge_line_moments([r.line_moments for r in results])


def survey_coverage_gaps(moments: np.ndarray) -> CoverageGaps:
    """The gaps between the flight lines' swaths, from the survey's line moments."""
    return coverage_gaps(moments)


@dataclass(frozen=True)
class GapVoidTask:
    """Count, over one cell's core, the pixels of each coverage gap and the empty ones."""

    cell_id: str
    window: PixelWindow  # the cell's core
    statistics_path: str
    gaps: CoverageGaps  # the survey's gaps near the core (CoverageGaps.near)
    strip_index: np.ndarray  # the indices of its extent strips among the survey's


def gap_void_tasks(results: list[CellResult], plan: SurveyPlan, gaps: CoverageGaps) -> list[GapVoidTask]:
    """One task per merged cell a gap or strip reaches: they are checked before detection splits holes at them."""
    cells = plan.cell_by_id()
    tasks = []
    for r in results:
        window = cells[r.cell_id].window
        if gaps.checked_near(window):
            tasks.append(GapVoidTask(r.cell_id, window, r.statistics_path, *gaps.near(window)))
    return tasks


def count_gap_voids(task: GapVoidTask) -> tuple[np.ndarray, np.ndarray]:
    """Per gap, then per extent strip near the core: its pixels and the empty ones (:meth:`CoverageGaps.void_counts`),
    with the strips' indices among the survey's."""
    count = load_cell_statistics(task.statistics_path, names=("count",)).crop(task.window).count
    return task.strip_index, task.gaps.void_counts(task.window, count == 0)


def survey_void_gaps(gaps: CoverageGaps, counts: list[tuple[np.ndarray, np.ndarray]]) -> CoverageGaps:
    """Gather: the gaps mostly empty over the survey (the cells' :func:`count_gap_voids` summed)."""
    total = np.zeros((len(gaps.gaps) + len(gaps.extent_strips), 3, 2), np.int64)
    n_gaps = len(gaps.gaps)
    for strips, cell_counts in counts:
        total[:n_gaps] += cell_counts[:n_gaps]
        np.add.at(total, n_gaps + np.asarray(strips, np.int64), cell_counts[n_gaps:])
    logger.debug("coverage gaps, then extent strips: (pixels, empty) in each and its flanks: %s", total.tolist())
    return keep_void_gaps(gaps, total)


# -- the stage's record ----------------------------------------------------------------------


def cell_tasks(state: RunState) -> list[CellTask]:
    """:func:`merge_tasks`, each task naming the read tasks whose results it takes."""
    reads = state[READ_TASKS]
    folders = {task.read_index: result_folder(task) for task in reads}
    return [
        dataclasses.replace(task, reads=tuple(folders[i] for i in touching))
        for task, touching in merge_tasks(state.plan, list(reads), state.staging)
    ]


#: Stage 2: one task per cell, run as soon as the tiles touching it are done.
MERGE_CELLS: Stage[CellTask, tuple[CellResult, ...]] = Stage(
    name="merge_cells",
    recipes=cell_tasks,
    worker=merge_cell,
    key=merge_key,
    label=lambda task: f"cell {task.cell.id} (merge)",
    gather=lambda state, results: in_plan_order(state.plan, results),
    bar="merge cells",
    ident=lambda task: task.cell.id,
    after=lambda task: tuple((BIN_TILES.name, folder) for folder in task.reads),
    priority=lambda task: 1,
    adopt=adopt_result,
    streams=True,  # the rasters of a cell are written as soon as it is merged (when nothing is filled)
)
