"""The point-cloud writer stage (``output.points``), one task per tile that was read.

Each task copies its tile point for point into ``points/<tile stem>.laz`` and appends
one synthetic point per filled DSM pixel the tile *owns*. It runs after the raster
writer and reads the filled pixels from the written ``dsm`` and ``fill_mask`` tiles,
so every fill is there, the small voids a cell settled itself included.

**Ownership.** A filled pixel belongs to the tile whose header bounds (in the survey
CRS) are nearest to its centre; a centre inside several tiles (overlaps, shared
edges) has distance 0 to each and goes to the first of them in survey order (the
order of the inputs as scanned). Every filled pixel therefore lands in exactly one
tile, those in the gaps between tiles included.

A filled pixel lies within ``fill.max_distance_m`` of a measured pixel (or inside a
small void closed by measured pixels), and a measured pixel holds a point inside a
tile's bounds, so its owner's bounds are at most that *reach* (plus two pixels)
away: a task reads only its tile's window grown by the reach, and compares the
tiles within twice the reach.
"""

from __future__ import annotations

import math
import os
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import shapely
from pyproj import Transformer

from ..config import Config
from ..fill import NOT_FILLED
from ..grid import Grid, PixelWindow
from ..io.las_write import AddedPoints, write_repaired_tile
from ..io.raster import read_raster
from ..plan import SurveyPlan
from ..staging import Staging
from ..survey.scan import source_crs_for_task
from .bin_tiles import BIN_TILES, TileResult
from .fill_holes import fills_holes
from .stage import RunState, Stage
from .write_rasters import WRITE_FILLED, WriteResult

Bounds = tuple[float, float, float, float]


@dataclass(frozen=True)
class CellRasters:
    """A written cell tile: where it lies in the grid, its DSM and fill mask."""

    window: PixelWindow
    dsm_path: str
    fill_mask_path: str


@dataclass(frozen=True)
class PointsTask:
    """Write one repaired point cloud."""

    tile_index: int
    path: str  # the input tile
    target: str  # points/<name>.laz in the staging folder
    grid: Grid
    window: PixelWindow  # the pixels this tile may own: its window grown by the reach
    candidates: tuple[tuple[int, Bounds], ...]  # tiles that may own a pixel of the window, in survey order
    cells: tuple[CellRasters, ...]  # written cell tiles meeting the window
    source_crs_wkt: str | None  # the tile's CRS when the grid's differs (points go back to it)
    point_class: int
    chunk_points: int


@dataclass(frozen=True)
class PointsResult:
    tile_index: int
    path: str  # the file written
    copied: int
    added: int


def points_tasks(
    plan: SurveyPlan, config: Config, tiles: list[TileResult], written: list[WriteResult], staging: Staging
) -> list[PointsTask]:
    """One task per tile that was read (skipped tiles excluded), in survey order."""
    grid = plan.grid
    survey_tiles = plan.survey.tiles
    reach = ownership_reach(plan, config)
    reach_px = math.ceil(reach / grid.resolution) + 1
    boxes = [shapely.box(*t.bounds) for t in survey_tiles]
    tree = shapely.STRtree(boxes)
    cells = plan.cell_by_id()
    cell_rasters = [
        CellRasters(cells[r.cell_id].window, r.paths["dsm"], r.paths["fill_mask"])
        for r in written
        if "fill_mask" in r.paths
    ]
    names = output_names([survey_tiles[r.tile_index].path for r in tiles])
    tasks = []
    for result, name in zip(tiles, names):
        tile = survey_tiles[result.tile_index]
        window = plan.tile_windows[tile.index].expand(reach_px).intersection(grid.window)
        near = tree.query(boxes[tile.index], predicate="dwithin", distance=2 * reach + 2 * grid.resolution)
        tasks.append(
            PointsTask(
                tile_index=tile.index,
                path=tile.path,
                target=str(staging.points_file(name)),
                grid=grid,
                window=window,
                candidates=tuple((int(i), survey_tiles[i].bounds) for i in sorted(near.tolist())),
                cells=tuple(c for c in cell_rasters if not c.window.intersection(window).is_empty),
                source_crs_wkt=source_crs_for_task(tile, plan.survey),
                point_class=config.output.points_class,
                chunk_points=config.rasterize.chunk_points,
            )
        )
    return tasks


def ownership_reach(plan: SurveyPlan, config: Config) -> float:
    """How far (survey units) a filled pixel's centre can lie from the bounds of every tile."""
    pixel = plan.grid.resolution
    small_void = math.sqrt(plan.hole_params.min_area_px / math.pi) * pixel
    limit = config.fill.max_distance_m / plan.survey.horizontal_unit_m or math.hypot(*plan.grid.window.shape) * pixel
    return max(limit, small_void) + 2 * pixel  # no limit (0): a filled pixel may be anywhere in the grid


def output_names(paths: list[str]) -> list[str]:
    """``points/`` file names: each tile's stem; a stem shared by several tiles gets ``_<k>`` (k-th in order)."""
    stems = [Path(p).stem for p in paths]
    repeated = {stem for stem, n in Counter(stems).items() if n > 1}
    seen: Counter[str] = Counter()
    names = []
    for stem in stems:
        seen[stem] += 1
        names.append(f"{stem}_{seen[stem]}" if stem in repeated else stem)
    return names


def write_tile_points(task: PointsTask) -> PointsResult:
    """Copy one tile into its repaired LAZ with the fill points it owns appended."""
    x, y, z = owned_fill_points(task)
    if task.source_crs_wkt is not None and len(x):
        back = Transformer.from_crs(task.grid.crs_wkt, task.source_crs_wkt, always_xy=True)
        x, y = back.transform(x, y)
    counts = write_repaired_tile(
        task.path, task.target, AddedPoints(x, y, z, task.point_class), chunk_points=task.chunk_points
    )
    return PointsResult(task.tile_index, task.target, counts.copied, counts.added)


def owned_fill_points(task: PointsTask) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres and heights (grid CRS) of the filled pixels of the task's window that its tile owns."""
    window = task.window
    heights = np.full(window.shape, np.nan, np.float64)
    filled = np.zeros(window.shape, bool)
    for cell in task.cells:
        overlap = cell.window.intersection(window)
        here, there = overlap.slices_within(window), overlap.slices_within(cell.window)
        codes, _, _ = read_raster(cell.fill_mask_path)
        dsm, _, _ = read_raster(cell.dsm_path)
        filled[here] = np.isfinite(codes[there]) & (codes[there] > 0) & (codes[there] < NOT_FILLED)
        heights[here] = dsm[there]
    rows, cols = np.nonzero(filled & np.isfinite(heights))
    # from grid (not window) indices: every task computes the same centre, bit for bit, so ties agree
    grid = task.grid
    x = grid.x_left + (window.col_off + cols + 0.5) * grid.resolution
    y = grid.y_top - (window.row_off + rows + 0.5) * grid.resolution
    indices = np.array([index for index, _ in task.candidates], np.int64)
    bounds = np.array([b for _, b in task.candidates], np.float64).reshape(-1, 4)
    mine = indices[nearest_tile(x, y, bounds)] == task.tile_index if len(x) else np.zeros(0, bool)
    return x[mine], y[mine], heights[rows[mine], cols[mine]]


def nearest_tile(x: np.ndarray, y: np.ndarray, bounds: np.ndarray, *, block: int = 65536) -> np.ndarray:
    """Per point, the row of ``bounds`` (minx, miny, maxx, maxy) nearest to it; ties go to the first row."""
    nearest = np.empty(len(x), np.int64)
    for start in range(0, len(x), block):
        bx, by = x[start : start + block, None], y[start : start + block, None]
        dx = np.maximum(np.maximum(bounds[None, :, 0] - bx, bx - bounds[None, :, 2]), 0.0)
        dy = np.maximum(np.maximum(bounds[None, :, 1] - by, by - bounds[None, :, 3]), 0.0)
        nearest[start : start + block] = np.argmin(np.hypot(dx, dy), axis=1)
    return nearest


def gather_points(results: list[PointsResult], written: list[WriteResult], root: Path) -> list[str]:
    """The gather step: the files written, relative to the run folder, in survey order.

    Checks that every filled pixel of the DSM became exactly one point.
    """
    filled = sum(r.filled_px for r in written)
    added = sum(r.added for r in results)
    if added != filled:
        raise RuntimeError(f"{added} fill points written for {filled} filled pixels (tile ownership)")
    return [os.path.relpath(r.path, root) for r in sorted(results, key=lambda r: r.tile_index)]


# -- the stage's record ----------------------------------------------------------------------


def repaired_tiles(state: RunState) -> list[PointsTask]:
    """:func:`points_tasks` over the decoded tiles and the rasters written after the fill."""
    written = list(state[WRITE_FILLED])
    return points_tasks(state.plan, state.config, list(state[BIN_TILES].tiles), written, state.staging)


#: With ``output.points``, after the writer: one task per tile read (the fill points come from the rasters).
WRITE_POINTS: Stage[PointsTask, tuple[str, ...]] = Stage(
    name="write_points",
    recipes=repaired_tiles,
    worker=write_tile_points,
    key=lambda task: f"points-{Path(task.target).stem}",
    label=lambda task: f"tile {task.path} (write points)",
    gather=lambda state, results: tuple(gather_points(results, list(state[WRITE_FILLED]), state.staging.root)),
    bar="write point clouds",
    runs=lambda state: fills_holes(state) and state.config.output.points,
    lap="points",
)
