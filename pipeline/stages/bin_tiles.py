"""Stage 1, one task per input tile: decode its points once and bin them into the global grid."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator
from dataclasses import dataclass

from pyproj import Transformer

from ..config import Config
from ..errors import InputDataError
from ..grid import Grid, PixelWindow
from ..io import pdal_reader
from ..io.intermediate import save_tile_statistics
from ..io.las import PointChunk, iter_point_chunks
from ..plan import SurveyPlan
from ..rasterize import WATER_CLASS, HeightMapAccumulator, point_filter_mask
from ..staging import Staging, input_fingerprint
from ..survey import source_crs_for_task


@dataclass(frozen=True)
class PointFilter:
    """Which points enter the rasters (from ``[filter]``)."""

    drop_classes: tuple[int, ...] = (7, 18)
    keep_classes: tuple[int, ...] = ()
    drop_withheld: bool = True


@dataclass(frozen=True)
class TileTask:
    """Decode one tile once and bin its points into the global grid."""

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
    pdal: pdal_reader.PdalRead | None = None  # read through PDAL (read.reader = "pdal"), else laspy


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


def tile_tasks(plan: SurveyPlan, config: Config, staging: Staging) -> list[TileTask]:
    """One task per tile, in row-major order of their windows so that cells complete early."""
    f = config.filter
    point_filter = PointFilter(tuple(f.drop_classes), tuple(f.keep_classes), f.drop_withheld)
    voxel_height = config.rasterize.voxel_height_m / plan.survey.vertical_unit_m
    grid = plan.grid
    user_pipeline = _user_pipeline(config)
    tasks = []
    for tile, window in zip(plan.survey.tiles, plan.tile_windows):
        source_crs = source_crs_for_task(tile, plan.survey)
        pdal = None
        if config.read.reader == "pdal":
            pdal = pdal_reader.tile_read(user_pipeline, plan.survey.crs_wkt, tile.header, tile.source_crs_wkt)
            source_crs = None if pdal.reprojects else source_crs  # else PDAL's points are in the survey CRS
        fingerprint = input_fingerprint(
            tile.path,
            window,
            grid.resolution,
            grid.col_min,
            grid.row_top,
            grid.offset,
            source_crs,
            point_filter,
            voxel_height,
            *(() if pdal is None else (pdal,)),
        )
        tasks.append(
            TileTask(
                tile_index=tile.index,
                path=tile.path,
                window=window,
                shared_windows=plan.shared_windows[tile.index],
                grid=grid,
                source_crs_wkt=source_crs,
                point_filter=point_filter,
                chunk_points=config.rasterize.chunk_points,
                voxel_height=voxel_height,
                output_dir=str(staging.tile_folder(tile.path, fingerprint)),
                pdal=pdal,
            )
        )
    return sorted(tasks, key=lambda t: (t.window.row_off, t.window.col_off))


def _user_pipeline(config: Config) -> pdal_reader.UserPipeline | None:
    """The checked ``read.pdal_pipeline`` (python-pdal is checked with the laspy reader off)."""
    if config.read.reader != "pdal":
        return None
    if not config.read.pdal_pipeline:
        pdal_reader.import_pdal()
        return None
    return pdal_reader.load_user_pipeline(config.read.pdal_pipeline, streaming=config.read.pdal_streaming)


def _point_chunks(task: TileTask) -> Iterator[PointChunk]:
    """The read dispatch: the tile's points through laspy, or through PDAL and the user's stages."""
    if task.pdal is None:
        return iter_point_chunks(task.path, task.chunk_points)
    return pdal_reader.iter_pdal_chunks(task.path, task.chunk_points, task.pdal)


def rasterize_tile(task: TileTask) -> TileResult:
    """Stream one tile's points in chunks into per-pixel statistics."""
    started = time.perf_counter()
    grid = task.grid
    accumulator = HeightMapAccumulator(
        task.window,
        resolution=grid.resolution,
        col_min=grid.col_min,
        row_top=grid.row_top,
        grid_width=grid.width,
        voxel_height=task.voxel_height,
        offset=grid.offset,
    )
    transformer = (
        Transformer.from_crs(task.source_crs_wkt, grid.crs_wkt, always_xy=True) if task.source_crs_wkt else None
    )
    read = used = outside = 0
    f = task.point_filter
    for chunk in _point_chunks(task):
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
    save_tile_statistics(task.output_dir, accumulator.statistics, accumulator.voxel_keys(task.shared_windows))
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


def adopt_result(task: TileTask, kept: TileResult | TileFailure) -> TileResult | TileFailure:
    """A previous run's result of the same tile (same key), pointed at this run's index and folder."""
    if isinstance(kept, TileResult):
        return dataclasses.replace(kept, tile_index=task.tile_index, output_dir=task.output_dir)
    return dataclasses.replace(kept, tile_index=task.tile_index)
