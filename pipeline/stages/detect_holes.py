"""Hole detection, one task per cell: hole parts, vertical holes and walls of the cell core.

Each task keeps its cell's part-label raster under the work folder (the fill
stage reads it) and returns only small tables and outlines to the client.
"""

from __future__ import annotations

import hashlib
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import scipy.ndimage as ndi
import shapely

from ..config import HOLE_CONTEXT_PX, Config
from ..grid import Cell, Grid, PixelWindow, window_union_mask
from ..holes import CellEvidence, CellHoles, DetectParams, detect_cell_holes, height_jumps, vertical_holes
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
from ..holes.vertical import vertical_hole_records
from ..holes.walls import Wall, WallParams, find_walls
from ..io.intermediate import load_cell_statistics, save_labels
from ..io.raster import geometry_mask
from ..plan import HoleParams, SurveyPlan
from ..rasterize import PixelStatistics
from ..sensor.sight import (
    OUTSIDE_SWATHS,
    TARGET_RADII_M,
    StepPixels,
    ground_targets,
    pixels_beside_steps,
    shadow_contradictions,
    sight_classes,
    surface_tops,
)
from ..sensor.sums import TrajectorySums
from ..sensor.trajectory import FlightLine, fit_flight_lines, swath_polygon
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
from .stage import RunState, Stage, in_plan_order

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DetectTask:
    """Find and measure the holes, vertical holes and walls of one cell."""

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
    vertical_holes: list[dict]  # records with a "wkb" polygon
    walls: list[Wall]
    jump_px: int
    aoi_px: int


@dataclass(frozen=True)
class SensorGeometry:
    """The survey's flight lines (:mod:`pipeline.sensor.trajectory`) and their swaths (world polygons).

    ``complete``: the lines account for the survey's points (their GPS times place them), so a
    pixel outside every swath was swept by none; else the swaths are written but not judged.
    """

    lines: tuple[FlightLine, ...]
    swaths_wkb: tuple[bytes, ...]  # one polygon per line (WKB: kept results hold data only)
    points_in_lines: int
    points_timed: int
    points_used: int
    fov_from_shadows: float | None = None  # the field of view the shadows gave, where heights are assumed

    @property
    def rim_rules(self) -> bool:
        """Whether the rim's occlusion rules speak too: heights assumed from a field of view nothing measured."""
        return self.heights_assumed and self.fov_from_shadows is None

    @property
    def swaths(self) -> tuple[shapely.Geometry, ...]:
        return tuple(shapely.from_wkb(w) for w in self.swaths_wkb)

    @property
    def heights_assumed(self) -> bool:
        """Whether most points lie in lines whose sensor heights are assumed (single returns, no scan angles)."""
        assumed = sum(line.points for line in self.lines if line.method == "nominal")
        return assumed > 0.5 * max(self.points_in_lines, 1)

    @property
    def complete(self) -> bool:
        return (
            bool(self.lines)
            and self.points_in_lines >= LINES_MIN_POINT_SHARE * self.points_timed
            and self.points_timed >= TIMED_MIN_POINT_SHARE * self.points_used
        )


#: The fitted lines must hold this share of the points with a GPS time ...
LINES_MIN_POINT_SHARE = 0.95
#: ... and those this share of the points used (a survey of tiles without GPS time has no lines).
TIMED_MIN_POINT_SHARE = 0.9


def survey_extent(boxes: list[tuple[float, float, float, float]], seam: float) -> shapely.Geometry:
    """Where the survey holds data: the union of the tiles' boxes, with the seams between neighbours closed.

    A header's box ends at its outermost point, so neighbouring tiles leave a gap of up to a
    point spacing between their boxes (0.01 m on a survey cut at whole metres); left open, every
    tile border would be a boundary of the data and cut the swaths crossing it. Gaps narrower
    than ``2 * seam`` (a pixel: it holds several returns, so a gap under it is no edge of the data)
    are closed.
    """
    union = shapely.union_all([shapely.box(*box) for box in boxes])
    closed = union.buffer(seam, join_style="mitre").buffer(-seam, join_style="mitre")
    return _without_holes(closed)


def _without_holes(area: shapely.Geometry) -> shapely.Geometry:
    """``area`` with its interior rings filled: a void the survey's tiles enclose is no edge of the survey.

    A missed flight line's strip between tiles whose data stops at its edges leaves a hole in the
    union of their boxes; taken for the survey's edge, it made the swath sides facing the strip
    cropped, and the neighbouring lines' tracks were placed 1.4 and 2.6 m off (a simulated Delft
    scan with assumed heights).
    """
    polygons = shapely.get_parts(area)
    return shapely.union_all([shapely.Polygon(shapely.get_exterior_ring(p)) for p in polygons if not p.is_empty])


def sensor_geometry(
    tiles: list[TileResult], plan: SurveyPlan, config: Config, *, fov_from_shadows: float | None = None
) -> SensorGeometry:
    """Gather: the flight lines' trajectories and swaths from the sums of every tile.

    ``fov_from_shadows``: the field of view the survey's shadows give (:func:`fov_from_shadows`),
    taken instead of ``sensor.nominal_fov_deg`` where a line's heights are assumed.
    """
    sums = TrajectorySums.merged([t.trajectory for t in tiles])
    fov = config.sensor.nominal_fov_deg if fov_from_shadows is None else fov_from_shadows
    lines = _line_fitter(sums, plan)(fov)
    return SensorGeometry(
        lines=tuple(lines),
        swaths_wkb=tuple(shapely.to_wkb(swath_polygon(line)) for line in lines),
        points_in_lines=sum(line.points for line in lines),
        points_timed=sums.points,
        points_used=sum(t.points_used for t in tiles),
        fov_from_shadows=fov_from_shadows,
    )


def _line_fitter(sums: TrajectorySums, plan: SurveyPlan) -> Callable[[float], list[FlightLine]]:
    """The survey's flight lines fitted from ``sums`` for a given field of view (the extent made once)."""
    grid = plan.grid
    extent = survey_extent([tile.bounds for tile in plan.survey.tiles], grid.resolution)

    def fit(nominal_fov_deg: float) -> list[FlightLine]:
        origin = (grid.x_left, grid.y_top, 0.0)
        return fit_flight_lines(
            sums.lines, sums.bins, sums.values, origin=origin, nominal_fov_deg=nominal_fov_deg, extent=extent
        )

    return fit


#: Fields of view tried for lines whose heights are assumed (degrees): airborne scanners sweep 20-75.
FOV_SEARCH_DEG = tuple(range(20, 77, 4))
#: Squares of this side (metres, on the absolute pixel lattice, whatever the cells) judge a field of view:
FOV_SQUARE_M = 250.0
#: the ones with most voids beside a step among an even sample of this many ...
FOV_SAMPLE_SQUARES = 24
#: ... of which this many are used.
FOV_EVIDENCE_SQUARES = 4
#: Voids and returned ground beside steps a field of view needs before the shadows speak.
FOV_MIN_EVIDENCE_PX = 200


def fov_from_shadows(
    tiles: list[TileResult], merged: list[CellResult], plan: SurveyPlan, config: Config
) -> float | None:
    """The scanner's field of view at which the survey's shadows fit best, where its heights are assumed.

    Single returns without scan angles give no sensor position: each line's height is its
    swath's half-width over the tangent of half an assumed field of view. The shadows beside
    the survey's steps tell that height: a sensor too low casts them over ground that returned
    points, one too high leaves the voids behind the steps in view
    (:func:`pipeline.sensor.sight.shadow_contradictions`). The field of view whose trajectories
    contradict fewest pixels, over the ``FOV_EVIDENCE_SQUARES`` squares with most voids beside a step,
    searched every 4 degrees from 20 to 76 and then to the degree; None where those squares hold
    fewer than ``FOV_MIN_EVIDENCE_PX`` pixels beside a step (flat open ground casts no shadow), or
    where the best lies at either end of the range (no scanner's field of view fits: the tracks
    are off, as in an extract cut from inside the swaths on both sides).
    The squares do not depend on the cells, so neither does the field of view.
    """
    fitted = _line_fitter(TrajectorySums.merged([t.trajectory for t in tiles]), plan)
    grid = plan.grid
    pixel_m = grid.resolution * plan.survey.horizontal_unit_m
    reach_px = max(1, math.ceil(config.sensor.sight_reach_m / pixel_m))
    windows = _step_windows(merged, plan, reach_px, near_px=max(1, math.ceil(TARGET_RADII_M[-1] / pixel_m)))
    if not windows:
        return None

    def contradictions(fov: float) -> tuple[int, int]:
        lines = fitted(fov)
        swaths = [swath_polygon(line) for line in lines]
        contradicting = judged = 0
        for window, zmax, measured, beside in windows:
            transform = grid.window_transform(window)
            masks = np.zeros((len(swaths), *window.shape), bool)
            for k, swath in enumerate(swaths):
                masks[k] = geometry_mask(swath, transform, window.shape)
            blocked, seen, n = shadow_contradictions(
                zmax, measured, beside, masks, [line.sensor for line in lines],
                origin_xy=(transform.c, transform.f), pixel_size=grid.resolution, reach=reach_px * grid.resolution,
                max_scan_angles=[line.max_scan_angle_deg for line in lines],
            )  # fmt: skip
            contradicting, judged = contradicting + blocked + seen, judged + n
        return contradicting, judged

    assumed = config.sensor.nominal_fov_deg
    at_assumed, judged = contradictions(assumed)
    if judged < FOV_MIN_EVIDENCE_PX:
        return None
    scores = {assumed: at_assumed}
    for fov in FOV_SEARCH_DEG:
        if fov not in scores:
            scores[fov] = contradictions(fov)[0]
    coarse = min(FOV_SEARCH_DEG, key=lambda f: (scores[f], abs(f - assumed)))
    if coarse in (FOV_SEARCH_DEG[0], FOV_SEARCH_DEG[-1]):
        # no airborne scanner's field of view fits: the tracks are off, not the heights (an extract
        # inside the swaths, cut on both sides: IGN's 50 m tile 77050_627755 fitted best at 17 degrees)
        logger.info(
            "field of view from the shadows: none between %d and %d degrees fits",
            *FOV_SEARCH_DEG[:: len(FOV_SEARCH_DEG) - 1],
        )
        return None
    for fov in range(coarse - 3, coarse + 4):
        if fov not in scores:
            scores[fov] = contradictions(fov)[0]
    best = min(scores, key=lambda f: (scores[f], abs(f - assumed)))
    logger.info(
        "field of view from the shadows: %d degrees (%d of %d pixels beside steps contradict it; %d at the assumed %g)",
        best, scores[best], judged, at_assumed, assumed,
    )  # fmt: skip
    return float(best)


def _step_windows(
    merged: list[CellResult], plan: SurveyPlan, reach_px: int, *, near_px: int
) -> list[tuple[PixelWindow, np.ndarray, np.ndarray, StepPixels]]:
    """The windows (a square grown by the reach) of the squares with most voids beside a step.

    The squares, ``FOV_SQUARE_M`` on the absolute pixel lattice, do not depend on the cells: an
    even sample of ``FOV_SAMPLE_SQUARES`` of those the grid meets is ranked by its empty pixels
    within ``near_px`` of a height jump, and the best ``FOV_EVIDENCE_SQUARES`` that hold any are read
    whole: ``(window, zmax, measured, beside)``, ``beside`` the square's own pixels beside a step.
    """
    grid, cells, step = plan.grid, plan.cell_by_id(), plan.hole_params.jump_threshold
    neighbours = tuple((cells[r.cell_id].window, r.statistics_path) for r in merged)
    side = max(1, math.ceil(FOV_SQUARE_M / (grid.resolution * plan.survey.horizontal_unit_m)))
    rows = range((grid.row_top - grid.height + 1) // side, grid.row_top // side + 1)  # absolute rows count upwards
    cols = range(grid.col_min // side, (grid.col_min + grid.width - 1) // side + 1)
    squares = [
        PixelWindow(grid.row_top - (r * side + side - 1), c * side - grid.col_min, side, side).intersection(grid.window)
        for r in reversed(rows)
        for c in cols
    ]
    squares = [w for w in squares if not w.is_empty]
    sample = squares[:: max(1, math.ceil(len(squares) / FOV_SAMPLE_SQUARES))]
    structure = np.ones((3, 3), bool)
    ranked = []
    for k, square in enumerate(sample):
        zmax, zmin, measured, _ = _read_window(neighbours, square)
        jumps = height_jumps(zmax, zmin, jump_threshold=step)
        near = ndi.binary_dilation(jumps, structure=structure, iterations=near_px) if jumps.any() else jumps
        ranked.append((int((near & ~measured).sum()), k))
    out = []
    for voids, k in sorted(ranked, key=lambda r: (-r[0], r[1]))[:FOV_EVIDENCE_SQUARES]:
        if voids == 0:
            break
        window = sample[k].expand(reach_px).intersection(grid.window)
        zmax, zmin, measured, _ = _read_window(neighbours, window)
        core = np.zeros(window.shape, bool)
        core[sample[k].slices_within(window)] = True
        beside = pixels_beside_steps(
            zmax, zmin, measured, step=step, near_px=near_px, pixel_size=grid.resolution, within=core
        )
        out.append((window, zmax, measured, beside))
    return out


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
    """One task per merged cell, in plan order.

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
    for result in merged:
        cell = cells[result.cell_id]
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
    """Holes, vertical holes and walls of one cell, from its merged statistics."""
    cell, grid, params = task.cell, task.grid, task.params
    stats = load_cell_statistics(task.statistics_path)
    coverage = task.gaps.classes(stats.window) if task.gaps is not None else None
    if task.sight is not None:
        coverage = _with_swaths(task.sight, grid, stats.window, coverage)
    # swept by a line's swath (or band): where the area's cut, not the data, bounds the footprint, inside
    swept = None if coverage is None else coverage == IN_SWATH
    sight = None
    if task.sight is not None:
        assert coverage is not None
        sight = _sight(task, stats, coverage)
        coverage = np.where(sight == OUTSIDE_SWATHS, IN_GAP, coverage).astype(np.int8)
    if task.planned:
        coverage = _with_undelivered(task, stats.window, coverage)
    aoi = _aoi(task, stats, coverage, swept)
    holes = _cell_holes(task, stats, aoi, coverage, sight)
    labels = holes.labels if holes.labels is not None else np.zeros(cell.window.shape, np.int32)
    save_labels(task.labels_path, labels, cell.window)
    core_rows, core_cols = cell.window.slices_within(stats.window)
    # float64, as find_walls compares heights: one jump raster serves the count and the walls
    jumps = height_jumps(stats.zmax.astype(np.float64), stats.zmin, jump_threshold=params.jump_threshold)
    vertical = vertical_holes(
        stats.zmax, stats.zmin, stats.voxels, voxel_height=params.voxel_height, jump_threshold=params.jump_threshold
    )[core_rows, core_cols]
    walls = find_walls(
        stats.zmax,
        stats.zmin,
        jump_threshold=params.jump_threshold,
        count=stats.count,
        transform=grid.window_transform(stats.window),
        region=(core_rows, core_cols),
        params=WallParams(min_length_px=params.wall_min_length_px),
        jumps=jumps,
    )
    return DetectResult(
        cell_holes=holes.without_labels(),
        labels_path=task.labels_path,
        part_outlines=_part_outlines(holes, cell, params),
        vertical_holes=vertical_hole_records(
            vertical,
            stats.crop(cell.window),
            grid.window_transform(cell.window),
            voxel_height=params.voxel_height,
            min_px=params.vertical_min_px,
        ),
        walls=walls,
        jump_px=int(jumps[core_rows, core_cols].sum()),
        aoi_px=int(aoi[core_rows, core_cols].sum()),
    )


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


def _swath_masks(sight: SightInputs, grid: Grid, window: PixelWindow) -> np.ndarray:
    """Whether each line's swath covers each pixel of a window: shape (lines, rows, columns)."""
    transform = grid.window_transform(window)
    masks = np.zeros((len(sight.swaths), *window.shape), bool)
    for i, swath in enumerate(sight.swaths):
        masks[i] = geometry_mask(shapely.from_wkb(swath), transform, window.shape)
    return masks


def _with_swaths(sight: SightInputs, grid: Grid, window: PixelWindow, coverage: np.ndarray | None) -> np.ndarray:
    """The coverage classes with the swaths: inside one, or outside every one (a coverage gap).

    Missing tiles keep their class, and so do the pixels beyond every tile's extent that a swath covers.
    """
    covered = _swath_masks(sight, grid, window).any(axis=0)
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


def _sight(task: DetectTask, stats: PixelStatistics, coverage: np.ndarray) -> np.ndarray:
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
    zmax, zmin, measured, water = _read_window(sight.neighbours, window)
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
        _swath_masks(sight, grid, window),
        list(sight.tracks),
        origin_xy=(transform.c, transform.f),
        pixel_size=grid.resolution,
        reach=sight.reach_px * grid.resolution,
        max_scan_angles=list(sight.max_scan_angles),
        tops=surface_tops(zmax, measured, candidates, pixel_size=sight.pixel_m, water=water),
    )
    out[voids.slices_within(stats.window)] = classes[voids.slices_within(window)]
    return out


def _read_window(
    neighbours: tuple[tuple[PixelWindow, str], ...], window: PixelWindow
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Highest and lowest return, whether measured and whether water was, over a window, from the cells it meets."""
    zmax = np.full(window.shape, np.nan)
    zmin = np.full(window.shape, np.nan)
    measured = np.zeros(window.shape, bool)
    water = np.zeros(window.shape, bool)
    for core, path in neighbours:
        overlap = core.intersection(window)
        if overlap.is_empty:
            continue
        stats = load_cell_statistics(path, ("zmax", "zmin", "count", "water")).crop(overlap)
        inside = overlap.slices_within(window)
        zmax[inside], zmin[inside], measured[inside] = stats.zmax, stats.zmin, stats.count > 0
        water[inside] = stats.water > 0
    return zmax, zmin, measured, water


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

#: One task per merged cell: hole parts, vertical holes and walls.
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
