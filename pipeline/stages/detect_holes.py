"""Hole detection, one task per cell: the hole parts of the cell core (its walls: :mod:`.find_walls`).

Each task keeps its cell's part-label raster under the work folder (the fill
stage reads it) and returns only small tables and outlines to the client.
"""

from __future__ import annotations

import hashlib
import logging
import math
from dataclasses import dataclass, replace

import numpy as np
import scipy.ndimage as ndi
import shapely

from ..config import HOLE_CONTEXT_PX, Config
from ..grid import Cell, Grid, PixelWindow, window_union_mask, z_order
from ..holes import CellEvidence, CellHoles, DetectParams, detect_cell_holes
from ..holes.coverage import (
    IN_GAP,
    IN_MISSING_TILE,
    IN_SWATH,
    OUTSIDE_TILE_EXTENTS,
    UNKNOWN,
    CoverageGaps,
    extent_strips,
)
from ..holes.outlines import label_outlines
from ..io.intermediate import load_cell_statistics, save_labels
from ..io.raster import burn_sum, geometry_mask
from ..plan import HoleParams, SurveyPlan
from ..rasterize import PixelStatistics
from ..sensor.sight import (
    BLOCKED,
    OUTSIDE_SWATHS,
    SEEN,
    ground_targets,
    sight_classes,
    surface_tops,
)
from ..staging import Staging
from ..survey.footprint import BlockMap, aoi_mask
from .bin_tiles import BIN_TILES, TileResult
from .merge_cells import (
    MERGE_CELLS,
    CellResult,
    GapVoidTask,
    count_gap_voids,
    footprint_blocks,
    gap_void_tasks,
    survey_coverage_gaps,
    survey_line_moments,
    survey_void_gaps,
)

# SensorGeometry lived here: results kept by earlier versions name it in this module
from .sensor_geometry import SensorGeometry, fov_from_shadows, read_neighbours, sensor_geometry
from .stage import RunState, Stage, in_plan_order

logger = logging.getLogger(__name__)


#: The statistics detection reads (the occupied voxels are the walls' and vertical holes': :mod:`.find_walls`).
DETECT_STATISTICS = ("zmax", "zmin", "count", "water", "source", "covered")


@dataclass(frozen=True)
class DetectTask:
    """Find and measure the holes of one cell."""

    cell: Cell
    grid: Grid
    statistics_path: str
    labels_path: str
    blocks: BlockMap
    tile_windows: tuple[PixelWindow, ...]
    survey_area_wkb: bytes | None  # the --aoi polygon or the tile grid's squares, else the tile windows
    water_wkb: bytes | None  # the --water polygons
    params: HoleParams
    gaps: CoverageGaps | None = None  # between the flight lines' swaths, survey-wide; missing tiles
    gaps_inside: bool = False  # coverage gaps and missing tiles in the survey area are inside the AOI
    sight: SightInputs | None = None  # the flight lines' swaths and trajectories, where they are known
    planned: bool = False  # the survey area is the --aoi: its pixels beyond every tile were planned, not delivered
    tile_cores: tuple[PixelWindow, ...] = ()  # the pixels whose centres lie in a tile's extent (of tile_windows)


@dataclass(frozen=True)
class SightInputs:
    """What one detection task needs to judge swaths and lines of sight (:mod:`pipeline.sensor.sight`).

    ``tracks`` and ``swaths`` hold the lines whose swath reaches the cell's window grown by
    ``reach_px``; ``neighbours`` the cores and statistics of the cells that window meets.
    """

    tracks: tuple[np.ndarray, ...]  # each line's sensor positions (K, 3), world units
    max_scan_angles: tuple[float, ...]  # each line's largest scan angle (degrees; NaN: unknown)
    swaths: tuple[bytes, ...]  # each line's swath polygon (WKB, world units)
    reach_px: int
    neighbours: tuple[tuple[PixelWindow, str], ...]
    pixel_m: float  # the pixel's side in metres


@dataclass(frozen=True)
class DetectResult:
    cell_holes: CellHoles  # without its label raster (kept in ``labels_path``)
    labels_path: str
    part_outlines: dict[int, bytes]  # WKB polygon per part label, exact pixel edges in global pixel coordinates
    aoi_px: int


def sensor_inputs(
    tiles: list[TileResult], merged: list[CellResult], plan: SurveyPlan, config: Config
) -> tuple[SensorGeometry | None, dict[str, SightInputs] | None]:
    """Gather: the flight lines (None with ``sensor.enabled`` off) and, where they account for the
    survey's points, what each detection task needs to judge swaths and lines of sight."""
    if not config.sensor.enabled:
        return None, None
    geometry = sensor_geometry(tiles, plan, config)
    if not geometry.complete:
        return geometry, None
    if geometry.heights_assumed and (fov := fov_from_shadows(tiles, merged, plan, config)) is not None:
        geometry = sensor_geometry(tiles, plan, config, fov_from_shadows=fov)
    logger.debug("flight lines: %s", [(g.line, g.part, g.method, round(g.flying_height)) for g in geometry.lines])
    return geometry, sight_inputs(plan, merged, geometry, config.sensor.sight_reach_m)


def sight_inputs(
    plan: SurveyPlan, merged: list[CellResult], geometry: SensorGeometry, reach_m: float
) -> dict[str, SightInputs]:
    """Per merged cell: the lines whose swath reaches it, and the cells its lines of sight read."""
    grid = plan.grid
    pixel_m = grid.resolution * plan.survey.horizontal_unit_m
    reach_px = max(1, math.ceil(reach_m / pixel_m))
    cells = plan.cell_by_id()
    paths = {r.cell_id: r.statistics_path for r in merged}
    swaths = list(geometry.swaths)
    boxes = shapely.STRtree(swaths)
    out = {}
    for cell_id in paths:
        window = cells[cell_id].halo_window.expand(reach_px).intersection(grid.window)
        # the merged cells whose core the window meets, by grid arithmetic (a loop over every
        # cell was 320 x 320 window intersections on the 211 M-point survey)
        under = (grid.cell(ix, iy) for ix, iy in grid.cell_indices_under(window))
        neighbours = tuple((cell.window, paths[cell.id]) for cell in under if cell.id in paths)
        x0, y0, x1, y1 = grid.window_bounds(window)
        near = sorted(int(i) for i in boxes.query(shapely.box(x0, y0, x1, y1)))
        # each swath cut to the window (a pixel more all round): the task judges no pixel beyond it, and
        # a whole swath grows with its line, so every cell's task carrying whole ones grew as the
        # survey squared (18 of the 26 MB of pickled detection tasks at 211 M points)
        pad = grid.resolution
        cut = shapely.box(x0 - pad, y0 - pad, x1 + pad, y1 + pad)
        out[cell_id] = SightInputs(
            tracks=tuple(geometry.lines[i].sensor for i in near),
            max_scan_angles=tuple(geometry.lines[i].max_scan_angle_deg for i in near),
            swaths=tuple(shapely.to_wkb(shapely.intersection(swaths[i], cut)) for i in near),
            reach_px=reach_px,
            neighbours=neighbours,
            pixel_m=pixel_m,
        )
    return out


def detect_tasks(
    plan: SurveyPlan,
    params: HoleParams,
    merged: list[CellResult],
    blocks: BlockMap,
    water: shapely.Geometry | None,
    staging: Staging,
    gaps: CoverageGaps | None = None,
    sight: dict[str, SightInputs] | None = None,
) -> list[DetectTask]:
    """One task per merged cell, neighbour after neighbour (:func:`pipeline.grid.z_order`).

    A cell's lines of sight read the cells around it through each worker's cache of cell
    statistics (:func:`pipeline.io.intermediate.load_shared_cell_statistics`); visited west to
    east, a survey 40 cells wide outgrew it (the 211 M-point bench survey: 870 reads missed of
    2,222, against 320 for 320 cells in Z order). The results are gathered in plan order.

    The survey area is the ``--aoi`` polygon or the tile grid's squares (a polygon),
    else the windows of the tiles; tiles that stage 1 skipped are left out of it
    either way (exterior: never a hole of unknown cause). With a tile grid, the
    squares of missing tiles join the coverage gaps.
    """
    cells = plan.cell_by_id()
    failed = sorted({i for r in merged for i in r.failed_tiles})
    polygon = plan.aoi_given or plan.tile_grid is not None
    area_wkb = shapely.to_wkb(plan.area_without(failed)) if polygon else None
    water_wkb = shapely.to_wkb(water) if water is not None else None
    tasks = []
    located = [cells[result.cell_id] for result in merged]
    for k in z_order([cell.index_x for cell in located], [cell.index_y for cell in located]):
        result, cell = merged[k], located[k]
        tasks.append(
            DetectTask(
                cell=cell,
                grid=plan.grid,
                statistics_path=result.statistics_path,
                labels_path=str(staging.cell_labels(cell.id)),
                blocks=blocks.slice_for(plan.grid, cell.halo_window),
                tile_windows=tuple(plan.tile_windows[i] for i in plan.tiles_of_cell[cell.id] if i not in failed),
                tile_cores=tuple(
                    plan.grid.window_of_centres(*plan.survey.tiles[i].bounds)
                    for i in plan.tiles_of_cell[cell.id]
                    if i not in failed
                ),
                survey_area_wkb=area_wkb,
                water_wkb=water_wkb,
                params=params,
                gaps=gaps.near(cell.halo_window)[0] if gaps else None,
                gaps_inside=plan.tile_grid is not None or plan.aoi_given,
                planned=plan.aoi_given,
                sight=None if sight is None else sight[cell.id],
            )
        )
    return tasks


def with_tile_grid(plan: SurveyPlan, gaps: CoverageGaps) -> CoverageGaps:
    """The coverage gaps with the tile grid's missing tiles and its delivered squares (grid pixels).

    The delivered squares and the tiles' extents tell where a tile's data stops short of its
    square (``OUTSIDE_TILE_EXTENTS``, :func:`pipeline.holes.coverage.extent_strips`): a hole
    there is missed coverage, once the strip is found empty beside a measured flank
    (:func:`pipeline.holes.coverage.keep_void_gaps`).
    """
    area = plan.area
    if area is None or area.tile_grid is None:
        return gaps
    tile_grid = area.tile_grid
    half = plan.grid.resolution / 2  # the pixels whose centres lie in the square

    def inner(bounds: tuple[float, float, float, float]) -> PixelWindow:
        x0, y0, x1, y1 = bounds
        return plan.grid.window_of_bounds(x0 + half, y0 + half, x1 - half, y1 - half)

    squares = tuple(inner(tile_grid.square_bounds(s)) for s in tile_grid.squares)  # one per tile, in tile order
    return replace(
        gaps,
        missing_tiles=tuple(inner(b) for b in area.missing_tiles),
        tile_extents=tuple(plan.tile_windows),
        extent_strips=extent_strips(squares, tuple(plan.tile_windows)),
    )


def detect_cell(task: DetectTask) -> DetectResult:
    """The holes of one cell, from its merged statistics (its walls and vertical holes: :mod:`.find_walls`)."""
    cell, grid, params = task.cell, task.grid, task.params
    stats = load_cell_statistics(task.statistics_path, DETECT_STATISTICS)
    coverage = task.gaps.classes(stats.window) if task.gaps is not None else None
    swaths = None
    if task.sight is not None:
        swaths = _swath_masks(task.sight, grid, _swath_window(task, stats.window))
        coverage = _with_swaths(swaths, stats.window, coverage)
    # swept by a line's swath (or band): where the area's cut, not the data, bounds the footprint, inside
    swept = None if coverage is None else coverage == IN_SWATH
    sight = None
    if task.sight is not None:
        assert coverage is not None and swaths is not None
        sight = _sight(task, stats, coverage, swaths)
        coverage = np.where(sight == OUTSIDE_SWATHS, IN_GAP, coverage).astype(np.int8)
    if task.planned:
        coverage = _with_undelivered(task, stats.window, coverage)
    aoi = _aoi(task, stats, coverage, swept)
    holes = _cell_holes(task, stats, aoi, coverage, sight)
    labels = holes.labels if holes.labels is not None else np.zeros(cell.window.shape, np.int32)
    core_rows, core_cols = cell.window.slices_within(stats.window)
    seen = None if sight is None else seen_small_voids(labels, sight[core_rows, core_cols])
    save_labels(task.labels_path, labels, cell.window, seen_voids=seen)
    return DetectResult(
        cell_holes=holes.without_labels(),
        labels_path=task.labels_path,
        part_outlines=_part_outlines(holes, cell, params),
        aoi_px=int(aoi[core_rows, core_cols].sum()),
    )


def seen_small_voids(labels: np.ndarray, sight: np.ndarray) -> np.ndarray:
    """The pixels of the small voids a cell settled (label -1) that the sensor saw unobstructed.

    A settled void (4-connected, as the writer fills it) counts as seen where some of its
    pixels are ``SEEN`` and none ``BLOCKED`` (:func:`pipeline.sensor.sight.sight_classes`): no
    line of sight into it was blocked, so it hides no ground behind a wall or a crown, and is
    filled from its whole rim as a ``no_return`` void is, not from the low side of a step as an
    occlusion (docs/filling.md, "Small voids").
    """
    components, n = ndi.label(labels == -1, structure=_CROSS)
    if n == 0:
        return np.zeros(labels.shape, bool)
    seen_px = np.bincount(components.ravel(), (sight == SEEN).ravel(), minlength=n + 1)
    blocked_px = np.bincount(components.ravel(), (sight == BLOCKED).ravel(), minlength=n + 1)
    seen = (seen_px > 0) & (blocked_px == 0)
    seen[0] = False
    return seen[components]


_CROSS = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], bool)


def _aoi(task: DetectTask, stats: PixelStatistics, coverage: np.ndarray | None, swept: np.ndarray | None) -> np.ndarray:
    """Where an empty pixel of the cell and its halo is a hole: survey area x data footprint.

    With a tile grid, the survey area's coverage gaps and missing tiles are inside
    whatever the footprint says: a missed flight line open at the survey's ends lies
    between two flown lines, a missing tile among the tiles. ``swept`` (pixels a line's
    swath covers) takes in the voids the area's cut opens between data
    (:func:`pipeline.survey.footprint.aoi_mask`).
    """
    window = stats.window
    transform = task.grid.window_transform(window)
    if task.survey_area_wkb is not None:
        survey_area = geometry_mask(shapely.from_wkb(task.survey_area_wkb), transform, window.shape)
        centres = survey_area
    else:
        survey_area = window_union_mask(window, task.tile_windows)
        centres = window_union_mask(window, task.tile_cores)
    if swept is not None:
        # beside the area's cut, a swept pixel counts where the area holds it, not where a point on
        # the extent's edge merely lands in it (a row of pixels beyond a tile's max edge)
        swept = swept & centres
    aoi = aoi_mask(window, task.grid, task.blocks, count=stats.count, survey_area=survey_area, swept=swept)
    if task.gaps_inside and coverage is not None:
        aoi |= survey_area & ((coverage == IN_GAP) | (coverage == IN_MISSING_TILE))
    return aoi


@dataclass(frozen=True)
class SwathMasks:
    """Whether each line's swath covers each pixel of ``window``: ``masks`` of shape (lines, rows, columns)."""

    masks: np.ndarray
    window: PixelWindow

    def within(self, window: PixelWindow) -> np.ndarray:
        """The masks over ``window`` (inside :attr:`window`)."""
        rows, cols = window.slices_within(self.window)
        return self.masks[:, rows, cols]


def _swath_window(task: DetectTask, statistics_window: PixelWindow) -> PixelWindow:
    """The window a cell's swath masks are burnt over: its statistics' window and its core grown by the
    reach of its lines of sight (:func:`_sight`'s window lies inside), in one burn."""
    assert task.sight is not None
    reach = task.cell.window.expand(task.sight.reach_px).intersection(task.grid.window)
    row, col = min(reach.row_off, statistics_window.row_off), min(reach.col_off, statistics_window.col_off)
    row_end, col_end = max(reach.row_end, statistics_window.row_end), max(reach.col_end, statistics_window.col_end)
    return PixelWindow(row, col, row_end - row, col_end - col)


#: Lines burnt at once into one raster, one bit each (:func:`_swath_masks`).
_LINES_PER_BURN = 32


def _swath_masks(sight: SightInputs, grid: Grid, window: PixelWindow) -> SwathMasks:
    """Whether each line's swath covers each pixel of a window (pixel centres inside, as
    :func:`pipeline.io.raster.geometry_mask`). Up to 32 lines are burnt in one pass, line ``k``
    adding ``2**k``: a polygon burns a pixel at most once, so the sum's bit ``k`` is line ``k``'s
    mask (one burn per line, each with GDAL's set-up, cost a tenth of a cell's detection)."""
    transform = grid.window_transform(window)
    masks = np.zeros((len(sight.swaths), *window.shape), bool)
    for first in range(0, len(sight.swaths), _LINES_PER_BURN):
        group = sight.swaths[first : first + _LINES_PER_BURN]
        shapes = [(shapely.from_wkb(swath), 1 << k) for k, swath in enumerate(group)]
        burnt = burn_sum([shape for shape in shapes if not shape[0].is_empty], transform, window.shape)
        for k in range(len(group)):
            masks[first + k] = (burnt >> k) & 1
    return SwathMasks(masks, window)


def _with_swaths(swaths: SwathMasks, window: PixelWindow, coverage: np.ndarray | None) -> np.ndarray:
    """The coverage classes with the swaths: inside one, or outside every one (a coverage gap).

    Missing tiles keep their class, and so do the pixels beyond every tile's extent that a swath covers.
    """
    covered = swaths.within(window).any(axis=0)
    swept = np.where(covered, IN_SWATH, IN_GAP).astype(np.int8)
    if coverage is None:
        return swept
    # beyond a tile's extent and outside every swath: a coverage gap (and so inside the survey area)
    unknown = (coverage == UNKNOWN) | ((coverage == OUTSIDE_TILE_EXTENTS) & ~covered)
    return np.where(unknown, swept, coverage).astype(np.int8)


def _with_undelivered(task: DetectTask, window: PixelWindow, coverage: np.ndarray | None) -> np.ndarray:
    """The pixels beyond every tile's extent as a missing tile's: planned (the --aoi), never delivered."""
    undelivered = ~window_union_mask(window, task.tile_windows)
    base = np.zeros(window.shape, np.int8) if coverage is None else coverage
    return np.where(undelivered & (base != OUTSIDE_TILE_EXTENTS), IN_MISSING_TILE, base).astype(np.int8)


def _sight(task: DetectTask, stats: PixelStatistics, coverage: np.ndarray, swaths: SwathMasks) -> np.ndarray:
    """Per empty pixel of the core inside a swath's extent: outside every swath after all (by the
    scan angles), blocked from every line, or seen by one (over ``stats.window``).

    Lines of sight are followed over the empty pixels' box grown by ``reach_px``, read from the
    cells it meets: it holds every square of the reach around them, as the core grown by the
    reach does, so the classes are the same, and a cell whose voids lie inside reads no other.
    """
    sight, cell, grid = task.sight, task.cell, task.grid
    assert sight is not None
    out = np.zeros(stats.window.shape, np.uint8)
    core = cell.window.slices_within(stats.window)
    empty = (stats.count == 0) & (coverage == IN_SWATH)
    rows, cols = np.nonzero(empty[core])
    if len(rows) == 0:
        return out
    voids = PixelWindow(
        cell.window.row_off + int(rows.min()),
        cell.window.col_off + int(cols.min()),
        int(rows.max() - rows.min()) + 1,
        int(cols.max() - cols.min()) + 1,
    )
    window = voids.expand(sight.reach_px).intersection(grid.window)
    zmax, zmin, measured, water = read_neighbours(sight.neighbours, window)
    candidates = np.zeros(window.shape, bool)
    candidates[voids.slices_within(window)] = empty[voids.slices_within(stats.window)]
    targets = ground_targets(
        zmin,
        measured,
        candidates,
        step=task.params.jump_threshold,
        pixel_size=sight.pixel_m,
    )
    transform = grid.window_transform(window)
    classes = sight_classes(
        candidates,
        np.where(measured, zmax, np.nan),
        targets,
        swaths.within(window),
        list(sight.tracks),
        origin_xy=(transform.c, transform.f),
        pixel_size=grid.resolution,
        reach=sight.reach_px * grid.resolution,
        max_scan_angles=list(sight.max_scan_angles),
        tops=surface_tops(zmax, measured, candidates, pixel_size=sight.pixel_m, water=water),
    )
    out[voids.slices_within(stats.window)] = classes[voids.slices_within(window)]
    return out


def _cell_holes(
    task: DetectTask,
    stats: PixelStatistics,
    aoi: np.ndarray,
    coverage: np.ndarray | None,
    sight: np.ndarray | None = None,
) -> CellHoles:
    params = task.params
    water_mask = (
        geometry_mask(shapely.from_wkb(task.water_wkb), task.grid.window_transform(stats.window), stats.window.shape)
        if task.water_wkb
        else None
    )
    return detect_cell_holes(
        stats.count,
        stats.zmax,
        stats.zmin,
        aoi,
        cell=task.cell,
        grid_window=task.grid.window,
        params=DetectParams(
            jump_threshold=params.jump_threshold,
            connectivity=params.connectivity,
            local_radius_px=HOLE_CONTEXT_PX,
            min_area_px=params.min_area_px,
        ),
        evidence=CellEvidence(
            water_points=stats.water,
            water_mask=water_mask,
            flight_line=stats.source.astype(np.int64) - 1,
            # outside every tile's extent counts as a missing tile's pixel: the delivery stops short there
            coverage=None
            if coverage is None
            else np.where(coverage == OUTSIDE_TILE_EXTENTS, IN_MISSING_TILE, coverage),
            sight=sight,
            covered=stats.covered > 0 if stats.covered.size else None,
        ),
    )


def _part_outlines(holes: CellHoles, cell: Cell, params: HoleParams) -> dict[int, bytes]:
    """Outlines of the cell's parts in integer global pixel coordinates.

    Parts of one hole then merge exactly on the client, whatever the resolution.
    """
    if holes.labels is None or not holes.n_parts:
        return {}
    polygons = label_outlines(
        np.where(holes.labels > 0, holes.labels, 0),
        row_off=cell.window.row_off,
        col_off=cell.window.col_off,
        connectivity=params.connectivity,
    )
    return {label: shapely.to_wkb(polygon) for label, polygon in polygons.items()}


# -- the stage's records ---------------------------------------------------------------------


@dataclass(frozen=True)
class SurveyCoverage:
    """What detection needs of the whole survey, gathered on the client after stage 2."""

    blocks: BlockMap  # the data footprint
    line_moments: np.ndarray  # every flight line's pixel moments (LINE_MOMENT_DTYPE)
    geometry: SensorGeometry | None  # the flight lines' trajectories and swaths (None: sensor.enabled off)
    sight: dict[str, SightInputs] | None  # per cell, where the lines account for the survey's points
    gaps: CoverageGaps  # the coverage gaps and extent strips, before they are checked for voids


def finds_holes(state: RunState) -> bool:
    return state.config.holes.enabled


def survey_coverage(state: RunState, results: list[object]) -> SurveyCoverage:
    """Gather: the footprint, the flight lines and the coverage gaps from stages 1 and 2."""
    plan, config, cells = state.plan, state.config, list(state[MERGE_CELLS])
    line_moments = survey_line_moments(cells)
    geometry, sight = sensor_inputs(list(state[BIN_TILES].tiles), cells, plan, config)
    # with the swaths known, no coverage gap is sought between the bands of the lines' pixels
    bands = line_moments[:0] if sight is not None else line_moments
    gaps = with_tile_grid(plan, survey_coverage_gaps(bands))
    logger.debug("flight-line bands %s; coverage gaps %s", gaps.bands, gaps.gaps)
    return SurveyCoverage(footprint_blocks(cells, plan, config), line_moments, geometry, sight, gaps)


def _has_gaps(state: RunState) -> bool:
    gaps = state[COVERAGE].gaps if finds_holes(state) else None
    return gaps is not None and bool(gaps.gaps or gaps.extent_strips)


def _gaps_key(task: GapVoidTask) -> str:
    evidence = (task.gaps.gaps, task.gaps.extent_strips, task.strip_index.tolist())
    digest = hashlib.sha1(repr(evidence).encode()).hexdigest()[:12]
    return f"gaps-{digest}-{task.cell_id}"


def void_gaps(state: RunState, counts: list[tuple[np.ndarray, np.ndarray]]) -> CoverageGaps:
    """Gather: the coverage gaps and extent strips empty beside measured flanks."""
    gaps = state[COVERAGE].gaps
    kept = survey_void_gaps(gaps, counts)
    logger.debug(
        "coverage gaps: %d of %d, extent strips: %d of %d empty beside measured flanks, kept",
        len(kept.gaps),
        len(gaps.gaps),
        len(kept.extent_strips),
        len(gaps.extent_strips),
    )
    return kept


def cell_detect_tasks(state: RunState) -> list[DetectTask]:
    """:func:`detect_tasks` over the merged cells, with the coverage gathered and the gaps checked."""
    coverage = state[COVERAGE]
    gaps = state.get(GAP_VOIDS, coverage.gaps)
    cells = list(state[MERGE_CELLS])
    plan = state.plan
    return detect_tasks(
        plan, plan.hole_params, cells, coverage.blocks, state.water, state.staging, gaps, coverage.sight
    )


#: On the client, after stage 2: the footprint, the flight lines and the coverage gaps.
COVERAGE: Stage[object, SurveyCoverage] = Stage(name="coverage", gather=survey_coverage, runs=finds_holes)

#: One task per cell a coverage gap or strip reaches: its pixels inside them, and the empty ones.
GAP_VOIDS: Stage[GapVoidTask, CoverageGaps] = Stage(
    name="gap_voids",
    recipes=lambda state: gap_void_tasks(list(state[MERGE_CELLS]), state.plan, state[COVERAGE].gaps),
    worker=count_gap_voids,
    key=_gaps_key,
    label=lambda task: f"cell {task.cell_id} (check gaps)",
    gather=void_gaps,
    bar="check coverage gaps",
    runs=_has_gaps,
)

#: One task per merged cell: its hole parts.
DETECT_HOLES: Stage[DetectTask, tuple[DetectResult, ...]] = Stage(
    name="detect_holes",
    recipes=cell_detect_tasks,
    worker=detect_cell,
    key=lambda task: f"detect-{task.cell.id}",
    label=lambda task: f"cell {task.cell.id} (find holes)",
    gather=lambda state, results: in_plan_order(state.plan, results, lambda d: d.cell_holes.cell.id),
    bar="find holes",
    runs=finds_holes,
)
