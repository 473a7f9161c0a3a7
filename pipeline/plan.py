"""The survey plan: everything decided before any point is decoded.

The plan lays one grid over the survey, keeps the cells that hold tiles and meet
the survey area, and records which tiles touch which cells. That relation is
found by grid arithmetic (a tile window covers a range of cell indices), so
planning grows with the number of tiles, never with the number of tile pairs
or with the survey's bounding box in cells.

Pure apart from reading a ``--aoi`` polygon (through :mod:`pipeline.io.vector`).
Each stage builds its own task recipes from the plan (``pipeline.stages``).
"""

from __future__ import annotations

import logging
import math
import os
from collections import defaultdict
from dataclasses import dataclass, replace

import shapely

from .config import AUTO, Config
from .errors import InputDataError
from .grid import Cell, Grid, PixelWindow
from .io.vector import read_survey_area
from .parameters import HoleParams, hole_params
from .reads import ReadPart, plan_reads
from .survey.blocks import FootprintDensity
from .survey.density import (
    Density,
    auto_resolution_m,
    round_cell_size,
    supported_resolution_m,
)
from .survey.footprint import block_size_px
from .survey.scan import Survey
from .survey.tile_grid import TileGrid, grid_survey_area, infer_tile_grid

logger = logging.getLogger(__name__)

#: ``grid.align`` -> the lattice offset of :class:`pipeline.grid.Grid`.
ALIGN_OFFSETS = {"edge": 0.0, "center": 0.5}

#: A tile bound lies on a grid square's edge within this many point spacings (the last
#: point of a tile lies about a spacing before its edge), kept within these metres.
GRID_EDGE_SPACINGS = 3.0
GRID_EDGE_TOLERANCE_M = (0.05, 2.0)

Bounds = tuple[float, float, float, float]


@dataclass(frozen=True)
class SurveyArea:
    """Where the survey is, before any point is read: the ``--aoi`` polygon, the tile grid's squares or the tile extents.

    Attributes
    ----------
    geometry : shapely geometry
        The survey area (without the tiles that stage 1 will skip: :meth:`SurveyPlan.area_without`).
    source : str
        What it is made of, for the ``survey_area`` layer and the manifest.
    tile_grid : TileGrid or None
        The grid the tiles lie on, when the area is made of its squares.
    missing_tiles : tuple of bounds
        Squares without a tile enclosed by squares with one: inside, holes of cause ``missing_tile``.
    skipped_squares : tuple of bounds
        Squares of tiles skipped at the scan (placed by their names): exterior.
    """

    geometry: shapely.Geometry
    source: str
    tile_grid: TileGrid | None = None
    missing_tiles: tuple[Bounds, ...] = ()
    skipped_squares: tuple[Bounds, ...] = ()


@dataclass(frozen=True)
class Sizing:
    """The pixel and cell sizes of a run, settled once from the settings and the survey's density.

    Attributes
    ----------
    resolution_m, cell_size_m : float
        The pixel and cell sides in metres, as used.
    cell_px : int
        Pixels per cell side.
    resolution_source : str
        ``"auto"`` (chosen from the density) or ``"set"`` (``grid.resolution_m``).
    cell_size_requested_m : float or str
        ``grid.cell_size_m`` as set (a number or ``"auto"``); ``cell_size_m`` differs when it was rounded.
    supported_resolution_m : float
        The finest pixel size the density supports (not rounded to a standard size).
    align : str
        ``grid.align``.
    density : Density
        From the headers: points and first returns over the tile bounds.
    """

    resolution_m: float
    cell_size_m: float
    cell_px: int
    resolution_source: str
    cell_size_requested_m: float | str
    supported_resolution_m: float
    align: str
    density: Density

    def as_record(self) -> dict[str, object]:
        """What the manifest records of the sizing."""
        return {
            "resolution_m": self.resolution_m,
            "resolution_source": self.resolution_source,
            "supported_resolution_m": round(self.supported_resolution_m, 4),
            "cell_size_m": self.cell_size_m,
            "cell_size_requested_m": self.cell_size_requested_m,
            "cell_px": self.cell_px,
            "align": self.align,
            "density": self.density.as_record(),
        }


@dataclass(frozen=True)
class SurveyPlan:
    """The grid, the cells to process and the tile-to-cell index.

    Attributes
    ----------
    cells : list of Cell
        Cells whose core meets a tile window and the survey area, north to south,
        west to east.
    tile_windows : list of PixelWindow
        The grid window of each tile's header bounds (``survey.tiles`` order).
    tiles_of_cell : dict
        Cell id -> indices of the tiles whose window meets the cell's halo window.
    reads : list of ReadPart
        The stage-1 read tasks (:mod:`pipeline.reads`): one per file, or several
        for a split COPC file.
    read_windows : list of PixelWindow
        The grid window of each read task's bounds (``reads`` order).
    shared_windows : dict
        Read index -> the overlaps of its window with other read tasks' windows
        (pixels that may receive points from two tasks), in read order.
    reads_of_cell : dict
        Cell id -> indices of the read tasks whose window meets the cell's halo window.
    """

    survey: Survey
    grid: Grid
    cells: list[Cell]
    tile_windows: list[PixelWindow]
    shared_windows: dict[int, tuple[PixelWindow, ...]]
    tiles_of_cell: dict[str, tuple[int, ...]]
    reads: list[ReadPart]
    read_windows: list[PixelWindow]
    reads_of_cell: dict[str, tuple[int, ...]]
    survey_area: shapely.Geometry
    aoi_given: bool
    block_px: int
    sizing: Sizing
    hole_params: HoleParams
    area: SurveyArea | None = None  # how the survey area was found (None: the tile extents)
    # the sizing is the headers' density until stage 1 has counted the footprint (pipeline.run)
    density_pending: bool = False

    def cell_by_id(self) -> dict[str, Cell]:
        return {cell.id: cell for cell in self.cells}

    @property
    def tile_grid(self) -> TileGrid | None:
        """The tile grid whose squares make the survey area, if any."""
        return self.area.tile_grid if self.area is not None else None

    def tile_footprint(self, tile: int) -> shapely.Geometry:
        """Where a tile's data would be: its grid square, or its header bounds without a grid."""
        grid = self.tile_grid
        if grid is not None:
            return shapely.box(*grid.square_bounds(grid.squares[tile]))
        return shapely.box(*self.survey.tiles[tile].bounds)

    def area_without(self, failed: list[int] | tuple[int, ...]) -> shapely.Geometry:
        """The survey area less what only tiles that failed in stage 1 would have covered (exterior)."""
        if not failed:
            return self.survey_area
        lost_tiles = set(failed)
        kept = [self.tile_footprint(i) for i in range(len(self.survey.tiles)) if i not in lost_tiles]
        lost = shapely.difference(shapely.union_all([self.tile_footprint(i) for i in failed]), shapely.union_all(kept))
        return shapely.difference(self.survey_area, lost)

    @property
    def pixel_size_m(self) -> float:
        """The pixel side in metres (the grid's resolution is in CRS units)."""
        return self.grid.resolution * self.survey.horizontal_unit_m

    @property
    def pixel_area_m2(self) -> float:
        return self.pixel_size_m**2


def plan_survey(
    survey: Survey, config: Config, *, aoi: str | os.PathLike | None = None, density_pending: bool = False
) -> SurveyPlan:
    """Lay the global grid over the survey, cut it into cells and index tiles by cell.

    ``density_pending``: sized by the headers' density for now, quietly; stage 1 counts the
    data footprint and the run plans again from it (:func:`pipeline.run.settle_density`).
    """
    sizing = plan_sizing(survey.density, config, quiet=density_pending)
    area = survey_area(survey, config, aoi=aoi)
    planned = (
        [_centres_inside(area.geometry.bounds, sizing.resolution_m / survey.horizontal_unit_m)]
        if (aoi is not None and not area.geometry.is_empty)
        else []
    )
    grid = Grid.covering(
        [t.bounds for t in survey.tiles] + list(area.missing_tiles) + planned,
        resolution=sizing.resolution_m / survey.horizontal_unit_m,
        cell_px=sizing.cell_px,
        halo_px=config.grid.halo_px,
        crs_wkt=survey.crs_wkt,
        offset=ALIGN_OFFSETS[config.grid.align],
    )
    tile_windows = [grid.window_of_bounds(*t.bounds) for t in survey.tiles]
    tiles_of_core = _tiles_by_cell(grid, tile_windows, expand_px=0)
    tiles_of_halo = _tiles_by_cell(grid, tile_windows, expand_px=grid.halo_px)
    # cells under the squares of a tile grid too (missing tiles, gaps between tiles' data), within the
    # lattice: as many squares as tiles, and never the empty margins beyond the data (exterior anyway)
    # and, with an --aoi, the cells of the planned area beyond the tiles: nothing was delivered there
    keys = set(tiles_of_core) | {
        k
        for b in _area_squares(area) + [tuple(area.geometry.bounds)] * bool(planned)
        for k in grid.cell_indices_under(_inner_window(grid, b))
    }
    candidates = [grid.cell(ix, iy) for iy, ix in sorted(((iy, ix) for ix, iy in keys), key=_north_west_first)]
    boxes = shapely.box(*zip(*(grid.window_bounds(c.window) for c in candidates))) if candidates else []
    meets_area = shapely.intersects(boxes, area.geometry) if candidates else []
    cells = [cell for cell, inside in zip(candidates, meets_area) if inside]
    tiles_of_cell = {
        cell.id: tuple(
            i for i in tiles_of_halo[(cell.index_x, cell.index_y)] if _meets(tile_windows[i], cell.halo_window)
        )
        for cell in cells
    }
    reads = plan_reads(survey, grid, False if config.read.reader == "pdal" else config.rasterize.copc_split)
    read_windows = [_read_window(grid, read, tile_windows[read.tile_index]) for read in reads]
    reads_of_core = _tiles_by_cell(grid, read_windows, expand_px=0)
    reads_of_cell = _of_cells(cells, _tiles_by_cell(grid, read_windows, expand_px=grid.halo_px), read_windows)
    block_px = block_size_px(grid, config.holes.footprint_block_m, survey.horizontal_unit_m)
    pixel_size_m = grid.resolution * survey.horizontal_unit_m
    return SurveyPlan(
        survey=survey,
        grid=grid,
        cells=cells,
        tile_windows=tile_windows,
        shared_windows=_shared_windows(read_windows, reads_of_core),
        tiles_of_cell=tiles_of_cell,
        reads=reads,
        read_windows=read_windows,
        reads_of_cell=reads_of_cell,
        survey_area=area.geometry,
        aoi_given=aoi is not None,
        block_px=block_px,
        sizing=sizing,
        hole_params=hole_params(
            config,
            pixel_size_m=pixel_size_m,
            spacing_m=sizing.density.spacing_m,
            vertical_unit_m=survey.vertical_unit_m,
        ),
        area=area,
        density_pending=density_pending,
    )


def survey_area(survey: Survey, config: Config, *, aoi: str | os.PathLike | None = None) -> SurveyArea:
    """The survey area: the ``--aoi`` polygon, else the tile grid's squares (``survey.area``), else the tile extents.

    ``survey.area = "auto"`` infers the grid and falls back to the tile extents with
    a warning saying why there is none; ``"tiles"`` stops there instead;
    ``"footprint"`` never infers a grid. A given AOI is authoritative: no grid is
    inferred.
    """
    if aoi is not None:
        return SurveyArea(read_survey_area(aoi, survey.crs), "--aoi polygon")
    extents = SurveyArea(shapely.union_all([shapely.box(*t.bounds) for t in survey.tiles]), "union of tile extents")
    mode = config.survey.area
    if mode == "footprint":
        return extents
    spacing_m = survey.density.spacing_m
    low, high = GRID_EDGE_TOLERANCE_M
    tolerance_m = min(max(GRID_EDGE_SPACINGS * spacing_m, low), high) if math.isfinite(spacing_m) else high
    inference = infer_tile_grid(
        [t.bounds for t in survey.tiles],
        [t.name for t in survey.tiles],
        tolerance=tolerance_m / survey.horizontal_unit_m,
    )
    if inference.grid is None:
        if mode == "tiles":
            raise InputDataError("INPUT", f'survey.area = "tiles" but the tiles lie on no grid: {inference.reason}')
        if len(survey.tiles) > 1:
            logger.warning("survey area: the tile extents (no tile grid: %s)", inference.reason)
        return extents
    grid = inference.grid
    found = grid_survey_area(grid, skipped_names=[os.path.basename(s["path"]) for s in survey.skipped])
    if found.note:
        logger.warning("tile grid: %s", found.note)
    logger.info(
        "survey area: the squares of %s%s",
        inference.reason,
        f", {len(found.missing)} missing tile(s) inside" if found.missing else "",
    )
    size = f"{grid.size_x:g}" if grid.size_x == grid.size_y else f"{grid.size_x:g} x {grid.size_y:g}"
    return SurveyArea(
        found.area,
        f"tile grid squares ({size})",
        tile_grid=grid,
        missing_tiles=tuple(grid.square_bounds(s) for s in found.missing),
        skipped_squares=tuple(grid.square_bounds(s) for s in found.skipped),
    )


def plan_with_footprint(
    plan: SurveyPlan, footprint: FootprintDensity, config: Config, *, aoi: str | os.PathLike | None = None
) -> SurveyPlan:
    """The plan of the survey whose footprint density stage 1 counted (``plan``: sized by the headers').

    Where the measured density gives the same pixel and cell sizes, the grid, cells and read
    tasks stand and only the sizing and hole parameters change; else the survey is planned
    anew (``plan.grid != result.grid``: stage 1 must run again).
    """
    survey = replace(plan.survey, footprint=footprint)
    sizing = plan_sizing(survey.density, config, quiet=True)
    if (sizing.resolution_m, sizing.cell_px) != (plan.sizing.resolution_m, plan.sizing.cell_px):
        return plan_survey(survey, config, aoi=aoi)
    sizing = plan_sizing(survey.density, config)  # the same, told this time
    return replace(
        plan,
        survey=survey,
        sizing=sizing,
        hole_params=hole_params(
            config,
            pixel_size_m=plan.pixel_size_m,
            spacing_m=sizing.density.spacing_m,
            vertical_unit_m=survey.vertical_unit_m,
        ),
        density_pending=False,
    )


def _centres_inside(bounds: Bounds, resolution: float) -> Bounds:
    """A box shrunk by half a pixel: what the grid must cover for the pixels whose centres lie inside it."""
    minx, miny, maxx, maxy = bounds
    half = resolution / 2
    return (minx + half, miny + half, max(maxx - half, minx + half), max(maxy - half, miny + half))


def _inner_window(grid: Grid, bounds: Bounds) -> PixelWindow:
    """The pixels whose centres lie inside a box (a square's max edge pulls in no further cell)."""
    half = grid.resolution / 2
    minx, miny, maxx, maxy = bounds
    return grid.window_of_bounds(minx + half, miny + half, maxx - half, maxy - half)


def _area_squares(area: SurveyArea) -> list[Bounds]:
    """The bounds of the squares a tile-grid area is made of (none for other areas)."""
    grid = area.tile_grid
    if grid is None:
        return []
    return [grid.square_bounds(s) for s in grid.squares] + list(area.missing_tiles)


def needs_density(config: Config) -> bool:
    """Whether the run settles something from the survey's density ("auto" pixel size or minimum hole area),
    so that it is worth measuring on the data footprint (:func:`pipeline.survey.footprint_density.measure_footprint`)."""
    return config.grid.resolution_m == AUTO or (config.holes.enabled and config.holes.min_area_m2 == AUTO)


def plan_sizing(density: Density, config: Config, *, quiet: bool = False) -> Sizing:
    """Settle ``grid.resolution_m`` ("auto" or a number) and round ``grid.cell_size_m`` to whole pixels.

    Logs the choice, warns when a pixel size set explicitly is finer than the
    density supports, and logs a cell size that had to be rounded (``quiet``: none of it,
    for a sizing that is only a first guess).
    """
    grid = config.grid
    supported = supported_resolution_m(density.pulses_per_m2)
    what = "first returns" if density.first_returns else "points"
    info, warning = (logger.debug, logger.debug) if quiet else (logger.info, logger.warning)
    if grid.resolution_m == AUTO:
        resolution, source = auto_resolution_m(density.pulses_per_m2), "auto"
        info(
            "pixel size %g m chosen for %.3g %s/m2 (point spacing %.3g m)",
            resolution,
            density.pulses_per_m2,
            what,
            density.spacing_m,
        )
    else:
        resolution, source = float(grid.resolution_m), "set"
        if resolution < supported * (1 - 1e-9):
            warning(
                "grid.resolution_m = %g m is finer than the survey supports: %.3g %s/m2 (point spacing %.3g m) "
                "fill a %g m pixel with %.2g on average, so many pixels stay empty by chance; %g m or coarser "
                '(or grid.resolution_m = "auto") gives a complete DSM',
                resolution,
                density.pulses_per_m2,
                what,
                density.spacing_m,
                resolution,
                resolution**2 * density.pulses_per_m2,
                auto_resolution_m(density.pulses_per_m2),
            )
    cell_size, cell_px = round_cell_size(grid.cell_size_m, resolution)
    if grid.cell_size_m == AUTO:
        info("cells of %d x %d pixels: %g m (grid.cell_size_m = %r)", cell_px, cell_px, cell_size, AUTO)
    elif not math.isclose(cell_size, float(grid.cell_size_m), rel_tol=1e-9):
        info(
            "grid.cell_size_m = %g m is not a whole multiple (at least 16) of the %g m pixel: cells are %g m (%d pixels)",
            grid.cell_size_m,
            resolution,
            cell_size,
            cell_px,
        )
    return Sizing(resolution, cell_size, cell_px, source, grid.cell_size_m, supported, grid.align, density)


def _north_west_first(key: tuple[int, int]) -> tuple[int, int]:
    index_y, index_x = key
    return (-index_y, index_x)


def _meets(a: PixelWindow, b: PixelWindow) -> bool:
    return not a.intersection(b).is_empty


def _read_window(grid: Grid, read: ReadPart, file_window: PixelWindow) -> PixelWindow:
    """A read task's window: its file's; a COPC cell task's bounds grown by a pixel (a point on a
    cube face) inside its file's; none for a COPC top task (it bins nothing)."""
    if read.role == "top":
        return PixelWindow(0, 0, 0, 0)
    if read.is_whole_file:
        return file_window
    return grid.window_of_bounds(*read.bounds).expand(1).intersection(file_window)


def _of_cells(
    cells: list[Cell], by_cell: dict[tuple[int, int], list[int]], windows: list[PixelWindow]
) -> dict[str, tuple[int, ...]]:
    """Cell id -> the indices of the read tasks whose window meets the cell's halo window."""
    return {
        cell.id: tuple(i for i in by_cell[(cell.index_x, cell.index_y)] if _meets(windows[i], cell.halo_window))
        for cell in cells
    }


def _tiles_by_cell(grid: Grid, windows: list[PixelWindow], *, expand_px: int) -> dict[tuple[int, int], list[int]]:
    """Cell ``(index_x, index_y)`` -> tiles whose window, grown by ``expand_px``, meets the cell's core.

    A tile window meets a cell's halo (the core grown by the halo) exactly when the
    tile window grown by the halo meets the core.
    """
    index: dict[tuple[int, int], list[int]] = defaultdict(list)
    for tile, window in enumerate(windows):
        if window.is_empty:
            continue
        for key in grid.cell_indices_under(window.expand(expand_px)):
            index[key].append(tile)
    return index


def _shared_windows(
    windows: list[PixelWindow], tiles_of_core: dict[tuple[int, int], list[int]]
) -> dict[int, tuple[PixelWindow, ...]]:
    """Each tile's overlaps with other tiles; overlapping tiles always share a cell core."""
    neighbours: dict[int, set[int]] = defaultdict(set)
    for tiles in tiles_of_core.values():
        for tile in tiles:
            neighbours[tile].update(tiles)
    shared = {}
    for tile, window in enumerate(windows):
        overlaps = (window.intersection(windows[other]) for other in sorted(neighbours[tile] - {tile}))
        shared[tile] = tuple(overlap for overlap in overlaps if not overlap.is_empty)
    return shared
