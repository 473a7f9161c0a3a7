"""The functions Dask runs on workers, and the recipes they receive.

Each task receives a frozen dataclass describing its work (paths, windows,
parameters: never open files or configuration objects), opens what it needs,
calls the pure kernels, writes its one output under a name no other task uses,
and returns a small result. Functions live at module level so they pickle by
reference; any task may run twice without harm.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pyproj import Transformer

import shapely

from .errors import InputDataError
from .footprint import BlockMap, aoi_mask, occupied_blocks, window_union_mask
from .grid import Cell, Grid, PixelWindow
from .holes import CellHoles, detect_cell_holes, height_jumps, vertical_holes
from .holes.outlines import label_outlines
from .holes.walls import Wall, find_walls
from .io.las import iter_point_chunks
from .io.raster import RasterOptions, geometry_mask, label_polygons, write_cog
from .rasterize import (
    STATISTIC_DTYPES,
    STATISTIC_NAMES,
    WATER_CLASS,
    HeightMapAccumulator,
    PixelStatistics,
    merge_statistics,
    point_filter_mask,
    shared_pixel_mask,
)

# Stage-1 arrays are raw binaries of known shape (the tile's window): memory-mapping
# them needs no header parsing, which cost more than the merge itself.


@dataclass(frozen=True)
class PointFilter:
    """Which points enter the rasters (from ``[filter]``)."""

    drop_classes: tuple[int, ...] = (7, 18)
    keep_classes: tuple[int, ...] = ()
    drop_withheld: bool = True


@dataclass(frozen=True)
class TileTask:
    """Stage 1: decode one tile once and bin its points into the global grid."""

    tile_index: int
    path: str
    window: PixelWindow
    shared_windows: tuple[PixelWindow, ...]
    grid: Grid
    source_crs_wkt: str | None  # reproject from this CRS to the grid's, or None
    point_filter: PointFilter
    chunk_points: int
    voxel_height: float  # z units
    output_dir: str


@dataclass(frozen=True)
class TileResult:
    tile_index: int
    path: str
    output_dir: str
    window: PixelWindow
    points_read: int
    points_used: int
    points_outside: int
    seconds: float


@dataclass(frozen=True)
class TileFailure:
    """A tile that could not be decoded, when bad tiles are skipped."""

    tile_index: int
    path: str
    reason: str


@dataclass(frozen=True)
class CellTask:
    """Stage 2: merge the statistics of the tiles touching one cell; write its DSM tile.

    The stage-1 results of those tiles are passed to :func:`merge_cell` as
    arguments, so Dask runs the cell as soon as they exist.
    """

    cell: Cell
    grid: Grid
    planned_windows: tuple[PixelWindow, ...]  # windows of every planned tile touching the cell
    dsm_path: str
    statistics_path: str
    raster_options: RasterOptions
    block_px: int


@dataclass(frozen=True)
class CellResult:
    cell_id: str
    dsm_path: str | None
    statistics_path: str
    points: int
    pixels: int
    empty_pixels: int
    occupied_blocks: np.ndarray  # packed keys of the footprint blocks holding data


@dataclass(frozen=True)
class HoleParams:
    """Hole-stage parameters in survey units (from ``[holes]``)."""

    jump_threshold: float  # z units
    voxel_height: float  # z units
    connectivity: int
    min_area_px: int
    vertical_min_px: int
    wall_min_length_px: float


@dataclass(frozen=True)
class DetectTask:
    """Stage 3: find and measure the holes, vertical holes and walls of one cell."""

    cell: Cell
    grid: Grid
    statistics_path: str
    blocks: BlockMap
    tile_windows: tuple[PixelWindow, ...]
    survey_area_wkb: bytes | None  # the --aoi polygon, else the tile windows are the survey area
    water_wkb: bytes | None  # the --water polygons
    params: HoleParams


@dataclass(frozen=True)
class DetectResult:
    cell_holes: CellHoles  # without its label raster
    part_outlines: dict[int, bytes]  # WKB polygon per part label, exact pixel edges in global pixel coordinates
    vertical_holes: list[dict]  # records with a "wkb" polygon
    walls: list[Wall]
    jump_px: int
    aoi_px: int


def rasterize_tile(task: TileTask) -> TileResult:
    """Stream one tile's points in chunks into per-pixel statistics (stage 1)."""
    started = time.perf_counter()
    grid = task.grid
    accumulator = HeightMapAccumulator(
        task.window,
        resolution=grid.resolution,
        col_min=grid.col_min,
        row_top=grid.row_top,
        grid_width=grid.width,
        voxel_height=task.voxel_height,
    )
    transformer = (
        Transformer.from_crs(task.source_crs_wkt, grid.crs_wkt, always_xy=True)
        if task.source_crs_wkt
        else None
    )
    read = used = outside = 0
    f = task.point_filter
    for chunk in iter_point_chunks(task.path, task.chunk_points):
        keep = point_filter_mask(
            chunk.classification,
            chunk.withheld,
            drop_classes=f.drop_classes,
            keep_classes=f.keep_classes,
            drop_withheld=f.drop_withheld,
        )
        evidence = {"water": chunk.classification == WATER_CLASS, "source": chunk.point_source_id}
        if transformer is None:
            n_used, n_outside = accumulator.add(
                chunk.X, chunk.Y, chunk.Z, keep, scales=chunk.scales, offsets=chunk.offsets, **evidence
            )
        else:
            x, y, z = chunk.coordinates()
            x, y = transformer.transform(x, y)
            n_used, n_outside = accumulator.add(x, y, z, keep, **evidence)
        read += len(chunk)
        used += n_used
        outside += n_outside
    out = Path(task.output_dir)
    out.mkdir(exist_ok=True)  # never parents: a cancelled run's staging folder must stay deleted
    stats = accumulator.statistics
    for name in STATISTIC_NAMES:
        _save_raw(out / f"{name}.bin", getattr(stats, name))
    _save_raw(out / "shared_keys.bin", accumulator.voxel_keys(task.shared_windows).astype(np.int64))
    return TileResult(
        tile_index=task.tile_index,
        path=task.path,
        output_dir=task.output_dir,
        window=task.window,
        points_read=read,
        points_used=used,
        points_outside=outside,
        seconds=time.perf_counter() - started,
    )


def rasterize_tile_or_skip(task: TileTask) -> TileResult | TileFailure:
    """:func:`rasterize_tile`, reporting a bad tile instead of raising (``on_error = "skip"``)."""
    try:
        return rasterize_tile(task)
    except InputDataError as e:
        return TileFailure(task.tile_index, task.path, e.reason)


def merge_cell(task: CellTask, *tiles: TileResult | TileFailure) -> CellResult:
    """Merge tile statistics over a cell and its halo, and write the cell's DSM COG (stage 2).

    ``tiles`` are the stage-1 results of the tiles touching the cell; failed
    (skipped) tiles contribute nothing.
    """
    cell, grid = task.cell, task.grid
    window = cell.halo_window
    parts = []
    for tile in tiles:
        if not isinstance(tile, TileResult):
            continue
        overlap = tile.window.intersection(window)
        if overlap.is_empty:
            continue
        statistics = load_tile_statistics(tile.output_dir, tile.window, overlap)
        parts.append((statistics, np.fromfile(Path(tile.output_dir) / "shared_keys.bin", dtype=np.int64)))
    shared = shared_pixel_mask(window, task.planned_windows)
    merged = merge_statistics(window, parts, shared=shared, grid_width=grid.width)
    save_cell_statistics(task.statistics_path, merged)
    core = merged.crop(cell.window)
    points = int(core.count.sum())
    dsm_path = None
    if points:
        write_cog(
            task.dsm_path,
            core.zmax,
            transform=grid.window_transform(cell.window),
            crs_wkt=grid.crs_wkt,
            options=task.raster_options,
            description="DSM: highest point per pixel",
        )
        dsm_path = task.dsm_path
    return CellResult(
        cell_id=cell.id,
        dsm_path=dsm_path,
        statistics_path=task.statistics_path,
        points=points,
        pixels=cell.window.height * cell.window.width,
        empty_pixels=int((core.count == 0).sum()),
        occupied_blocks=occupied_blocks(core.count, cell.window, grid, task.block_px),
    )


def detect_cell(task: DetectTask) -> DetectResult:
    """Holes, vertical holes and walls of one cell, from its merged statistics (stage 3)."""
    cell, grid, params = task.cell, task.grid, task.params
    stats = load_cell_statistics(task.statistics_path)
    window = stats.window
    transform = grid.window_transform(window)
    if task.survey_area_wkb is not None:
        survey_area = geometry_mask(shapely.from_wkb(task.survey_area_wkb), transform, window.shape)
    else:
        survey_area = window_union_mask(window, task.tile_windows)
    aoi = aoi_mask(window, grid, task.blocks, count=stats.count, survey_area=survey_area)
    water_mask = (
        geometry_mask(shapely.from_wkb(task.water_wkb), transform, window.shape) if task.water_wkb else None
    )
    holes = detect_cell_holes(
        stats.count,
        stats.zmax,
        stats.zmin,
        aoi,
        cell=cell,
        grid_window=grid.window,
        jump_threshold=params.jump_threshold,
        connectivity=params.connectivity,
        water_points=stats.water,
        water_mask=water_mask,
        flight_line=stats.source.astype(np.int64) - 1,
        min_area_px=params.min_area_px,
    )
    core_rows, core_cols = cell.window.slices_within(window)
    core_transform = grid.window_transform(cell.window)
    outlines = {}
    if holes.labels is not None and holes.n_parts:
        # integer pixel coordinates: parts of one hole merge exactly on the client, whatever the resolution
        polygons = label_outlines(
            np.where(holes.labels > 0, holes.labels, 0),
            row_off=cell.window.row_off,
            col_off=cell.window.col_off,
            connectivity=params.connectivity,
        )
        outlines = {label: shapely.to_wkb(polygon) for label, polygon in polygons.items()}
    # float64, as find_walls compares heights: one jump raster serves the count and the walls
    jumps = height_jumps(stats.zmax.astype(np.float64), stats.zmin, jump_threshold=params.jump_threshold)
    vertical = vertical_holes(
        stats.zmax, stats.zmin, stats.voxels, voxel_height=params.voxel_height, jump_threshold=params.jump_threshold
    )[core_rows, core_cols]
    vertical_records = _vertical_hole_records(vertical, stats.crop(cell.window), core_transform, params)
    walls = find_walls(
        stats.zmax,
        stats.zmin,
        jump_threshold=params.jump_threshold,
        count=stats.count,
        transform=transform,
        region=(core_rows, core_cols),
        min_length_px=params.wall_min_length_px,
        jumps=jumps,
    )
    return DetectResult(
        cell_holes=holes.without_labels(),
        part_outlines=outlines,
        vertical_holes=vertical_records,
        walls=walls,
        jump_px=int(jumps[core_rows, core_cols].sum()),
        aoi_px=int(aoi[core_rows, core_cols].sum()),
    )


def _vertical_hole_records(mask: np.ndarray, core: PixelStatistics, transform, params: HoleParams) -> list[dict]:
    """One record per connected group of vertical-hole pixels (UAS eq. 2) in a cell core."""
    import scipy.ndimage as ndi

    labels, n = ndi.label(mask, structure=np.ones((3, 3), bool))
    if n == 0:
        return []
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    keep = sizes >= max(1, params.vertical_min_px)
    keep[0] = False
    labels = np.where(keep[labels], np.cumsum(keep)[labels], 0)
    n = int(keep.sum())
    if n == 0:
        return []
    mask = labels > 0
    index = np.arange(1, n + 1)
    span = (core.zmax.astype(np.float64) - core.zmin)
    expected = np.floor(span / params.voxel_height)
    missing = np.where(mask, np.maximum(expected - core.voxels, 0), 0)
    pixels = ndi.sum_labels(mask, labels, index)
    max_span = ndi.maximum(np.where(mask, span, 0), labels, index)
    missing_voxels = ndi.sum_labels(missing, labels, index)
    top = ndi.maximum(np.where(mask, core.zmax, -np.inf), labels, index)
    polygons = label_polygons(labels, transform, connectivity=8)
    return [
        {
            "pixels": int(pixels[i]),
            "max_height_range": float(max_span[i]),
            "missing_voxels": int(missing_voxels[i]),
            "top": float(top[i]),
            "wkb": shapely.to_wkb(polygons[i + 1]),
        }
        for i in range(n)
        if (i + 1) in polygons
    ]



def load_tile_statistics(output_dir: str, tile_window: PixelWindow, window: PixelWindow) -> PixelStatistics:
    """Read the part of a tile's stage-1 statistics inside ``window`` (memory-mapped)."""
    rows, cols = window.slices_within(tile_window)
    arrays = {}
    for name in STATISTIC_NAMES:
        mapped = np.memmap(Path(output_dir) / f"{name}.bin", dtype=STATISTIC_DTYPES[name], mode="r", shape=tile_window.shape)
        arrays[name] = np.array(mapped[rows, cols])
    return PixelStatistics(window=window, **arrays)


def save_cell_statistics(path: str | os.PathLike, statistics: PixelStatistics) -> None:
    """Store a cell's merged statistics (core + halo) for the later stages."""
    w = statistics.window
    tmp = f"{path}.tmp.npz"
    np.savez(
        tmp,
        window=np.array([w.row_off, w.col_off, w.height, w.width]),
        **{name: getattr(statistics, name) for name in STATISTIC_NAMES},
    )
    os.replace(tmp, path)


def load_cell_statistics(path: str | os.PathLike) -> PixelStatistics:
    with np.load(path) as data:
        window = PixelWindow(*(int(v) for v in data["window"]))
        return PixelStatistics(window=window, **{name: data[name] for name in STATISTIC_NAMES})


def _save_raw(path: Path, array: np.ndarray) -> None:
    tmp = path.with_name(path.name + ".tmp")
    np.ascontiguousarray(array).tofile(tmp)
    os.replace(tmp, path)
