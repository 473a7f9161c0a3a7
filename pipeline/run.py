"""Building and running the Dask graph: the only module that knows about Dask.

A run is: scan headers -> plan the grid, cells and tile windows -> stage 1 (one
task per tile: decode once, bin) -> stage 2 (one task per cell: merge, write the
DSM tile) -> mosaic and vector layers -> manifest. Every product is written into
a staging folder inside OUT and moved into place only when the whole run has
succeeded, so a failed run leaves no half-written output.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import shutil
import socket
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import shapely
from pyproj import CRS, Transformer

from . import __version__
from .config import Config, to_dict
from .errors import CRSError, InputDataError, OutputError
from .footprint import block_size_px, footprint_map
from .grid import Cell, Grid, PixelWindow
from .hole_layers import write_hole_layers
from .io.raster import RasterOptions, write_vrt
from .io.vector import write_layer
from .report import write_report
from .survey import Survey, scan_survey, source_crs_for_task, tile_index_records
from .tasks import (
    CellResult,
    CellTask,
    DetectTask,
    HoleParams,
    detect_cell,
    PointFilter,
    TileFailure,
    TileResult,
    TileTask,
    merge_cell,
    rasterize_tile,
    rasterize_tile_or_skip,
)

logger = logging.getLogger(__name__)

#: Products a run moves from the staging folder into OUT (and replaces there).
PRODUCTS = ("dsm", "dsm.vrt", "holes.gpkg", "manifest.json", "report.html")


@dataclass
class RunSummary:
    """What a run did; also written to ``manifest.json``."""

    out_dir: str
    tiles: int
    cells: int
    points_read: int
    points_used: int
    seconds: float
    stage_seconds: dict[str, float] = field(default_factory=dict)
    skipped: list[dict[str, str]] = field(default_factory=list)
    dsm_tiles: list[str] = field(default_factory=list)
    holes: dict[str, Any] = field(default_factory=dict)

    @property
    def points_per_second(self) -> float:
        return self.points_read / self.seconds if self.seconds else 0.0


@dataclass(frozen=True)
class SurveyPlan:
    """Everything decided before any point is decoded."""

    survey: Survey
    grid: Grid
    cells: list[Cell]
    tile_windows: list[PixelWindow]
    survey_area: shapely.Geometry
    aoi_given: bool
    block_px: int

    def tile_tasks(self, config: Config, work_dir: Path) -> list[TileTask]:
        f = config.filter
        point_filter = PointFilter(tuple(f.drop_classes), tuple(f.keep_classes), f.drop_withheld)
        voxel_height = config.rasterize.voxel_height_m / self.survey.vertical_unit_m
        tasks = []
        for tile, window in zip(self.survey.tiles, self.tile_windows):
            shared = tuple(
                overlap
                for other_index, other in enumerate(self.tile_windows)
                if other_index != tile.index and not (overlap := window.intersection(other)).is_empty
            )
            tasks.append(
                TileTask(
                    tile_index=tile.index,
                    path=tile.path,
                    window=window,
                    shared_windows=shared,
                    grid=self.grid,
                    source_crs_wkt=source_crs_for_task(tile, self.survey),
                    point_filter=point_filter,
                    chunk_points=config.rasterize.chunk_points,
                    voxel_height=voxel_height,
                    output_dir=str(work_dir / "tiles" / f"tile_{tile.index:05d}"),
                )
            )
        return tasks


def plan_survey(survey: Survey, config: Config, *, aoi: str | os.PathLike | None = None) -> SurveyPlan:
    """Lay the global grid over the survey and cut it into cells."""
    resolution = config.grid.resolution_m / survey.horizontal_unit_m
    grid = Grid.covering(
        [t.bounds for t in survey.tiles],
        resolution=resolution,
        cell_px=config.cell_size_px,
        halo_px=config.grid.halo_px,
        crs_wkt=survey.crs_wkt,
    )
    tile_windows = [grid.window_of_bounds(*t.bounds) for t in survey.tiles]
    if aoi is not None:
        survey_area = read_survey_area(aoi, survey.crs)
    else:
        survey_area = shapely.union_all([shapely.box(*t.bounds) for t in survey.tiles])
    cells = []
    for cell in grid.cells():
        touches_tile = any(not w.intersection(cell.window).is_empty for w in tile_windows)
        if touches_tile and shapely.intersects(shapely.box(*grid.window_bounds(cell.window)), survey_area):
            cells.append(cell)
    block_px = block_size_px(grid, config.holes.footprint_block_m, survey.horizontal_unit_m)
    return SurveyPlan(survey, grid, cells, tile_windows, survey_area, aoi is not None, block_px)


def read_survey_area(path: str | os.PathLike, crs: CRS, *, what: str = "AOI") -> shapely.Geometry:
    """The union of the polygons of a vector file, in the survey CRS."""
    import pyogrio

    try:
        frame = pyogrio.read_dataframe(path)
    except Exception as e:
        raise InputDataError(path, f"{what} file cannot be read: {e}") from None
    polygons = [g for g in frame.geometry if g is not None and g.geom_type in ("Polygon", "MultiPolygon")]
    if not polygons:
        raise InputDataError(path, f"{what} file holds no polygon")
    if frame.crs is None:
        raise CRSError(path, f"{what} file has no CRS")
    area = shapely.union_all(polygons)
    if not CRS.from_user_input(frame.crs).equals(crs, ignore_axis_order=True):
        transformer = Transformer.from_crs(frame.crs, crs, always_xy=True)
        area = shapely.transform(area, lambda xy: _transform_xy(transformer, xy))
    return shapely.make_valid(area)


def _transform_xy(transformer: Transformer, xy):
    import numpy as np

    x, y = transformer.transform(xy[:, 0], xy[:, 1])
    return np.column_stack([x, y])


def run_survey(
    inputs: list[str] | tuple[str, ...],
    out_dir: str | os.PathLike,
    config: Config,
    *,
    scheduler: str | None = None,
    client: Any = None,
    aoi: str | os.PathLike | None = None,
    water: str | os.PathLike | None = None,
    progress: bool = False,
) -> RunSummary:
    """Run the pipeline on a survey and write the products into ``out_dir``.

    Parameters
    ----------
    inputs : list of str
        Files, folders or globs of LAS/LAZ/COPC tiles.
    out_dir : path-like
        Output folder (created if needed); existing products are replaced.
    config : Config
        The validated configuration.
    scheduler : str, optional
        Address of a running Dask scheduler; default: a local cluster sized by
        ``config.dask``.
    client : distributed.Client, optional
        An existing client (takes precedence over ``scheduler``).
    aoi : path-like, optional
        A polygon file: the survey area, instead of the union of tile extents.
    water : path-like, optional
        A polygon file of known water (default: ``config.holes.water``).
    progress : bool
        Show a progress bar on stderr.
    """
    started = time.perf_counter()
    stage_seconds: dict[str, float] = {}
    out = Path(out_dir)
    survey = scan_survey(
        inputs, crs=config.survey.crs, target_crs=config.survey.target_crs, on_error=config.survey.on_error
    )
    plan = plan_survey(survey, config, aoi=aoi)
    water = water or config.holes.water or None
    water = read_survey_area(water, survey.crs, what="water") if water else None
    stage_seconds["scan"] = time.perf_counter() - started
    created_out = not out.exists()
    staging = _make_staging(out)
    try:
        with _dask_client(client, scheduler, config) as dask_client, _Progress(progress) as bar:
            tile_results, failed, cell_results = _run_stages(dask_client, plan, config, staging, bar, stage_seconds)
            detected = None
            if config.holes.enabled:
                t0 = time.perf_counter()
                detected = _run_detection(dask_client, plan, config, cell_results, bar, water)
                stage_seconds["holes"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        skipped = survey.skipped + failed
        _write_outputs(staging, plan, tile_results, cell_results, skipped)
        hole_summary = write_hole_layers(staging / "holes.gpkg", plan, config, hole_params(plan, config), detected) if detected is not None else {}
        summary = RunSummary(
            holes=hole_summary,
            out_dir=str(out),
            tiles=len(tile_results),
            cells=len(cell_results),
            points_read=sum(r.points_read for r in tile_results),
            points_used=sum(r.points_used for r in tile_results),
            seconds=time.perf_counter() - started,
            stage_seconds=stage_seconds,
            skipped=skipped,
            dsm_tiles=sorted(os.path.relpath(r.dsm_path, staging) for r in cell_results if r.dsm_path),
        )
        stage_seconds["outputs"] = time.perf_counter() - t0
        manifest = _write_manifest(staging / "manifest.json", summary, plan, config, tile_results, cell_results)
        write_report(staging / "report.html", manifest, summary.holes.get("largest", []))
        _commit(staging, out, keep_work=config.output.keep_intermediate)
    except BaseException:
        _remove_staging(staging)
        if created_out:
            with contextlib.suppress(OSError):
                out.rmdir()  # only if still empty
        raise
    return summary


# -- stages ---------------------------------------------------------------------------


def _run_stages(client, plan: SurveyPlan, config: Config, staging: Path, bar: _Progress, stage_seconds: dict):
    """Submit stage 1 (per tile) and stage 2 (per cell) as one graph.

    Each cell depends on the tiles touching it and has a higher priority, so it
    runs as soon as they are done, while other tiles are still decoding; tiles
    are submitted in row-major order so that cells complete early.
    """
    from distributed import as_completed

    started = time.perf_counter()
    skip = config.survey.on_error == "skip"
    tile_tasks = sorted(plan.tile_tasks(config, staging / "work"), key=lambda t: (t.window.row_off, t.window.col_off))
    options = RasterOptions(
        compress=config.output.compress,
        compress_level=config.output.compress_level,
        blocksize=config.output.blocksize,
        overview_resampling=config.output.overview_resampling,
    )
    run_id = uuid.uuid4().hex[:8]
    tile_function = rasterize_tile_or_skip if skip else rasterize_tile
    tile_futures = {
        task.tile_index: client.submit(tile_function, task, pure=False, key=f"rasterize-{run_id}-{task.tile_index}")
        for task in tile_tasks
    }
    cell_futures = []
    for cell in plan.cells:
        touching = [t for t in tile_tasks if not t.window.intersection(cell.halo_window).is_empty]
        if not touching:
            continue
        task = CellTask(
            cell=cell,
            grid=plan.grid,
            planned_windows=tuple(t.window for t in touching),
            dsm_path=str(staging / "dsm" / f"dsm_{cell.id}.tif"),
            statistics_path=str(staging / "work" / "cells" / f"cell_{cell.id}.npz"),
            raster_options=options,
            block_px=plan.block_px,
        )
        dependencies = [tile_futures[t.tile_index] for t in touching]
        cell_futures.append(
            client.submit(merge_cell, task, *dependencies, pure=False, priority=1, key=f"merge-{run_id}-{cell.id}")
        )
    tiles_bar = bar.add("decode + bin tiles", total=len(tile_futures))
    cells_bar = bar.add("merge cells + write DSM", total=len(cell_futures))
    tile_results: list[TileResult] = []
    failed: list[dict[str, str]] = []
    cell_results: list[CellResult] = []
    all_futures = [*tile_futures.values(), *cell_futures]
    try:
        for future in as_completed(all_futures):
            result = future.result()  # a tile error in "fail" mode raises here
            if isinstance(result, TileResult):
                tile_results.append(result)
                if result.points_outside:
                    logger.warning(
                        "%s: %d points lie outside the bounds its header declares; they were not used",
                        result.path,
                        result.points_outside,
                    )
                bar.advance(tiles_bar, points=result.points_read)
                if len(tile_results) + len(failed) == len(tile_futures):
                    stage_seconds["rasterize"] = time.perf_counter() - started
            elif isinstance(result, TileFailure):
                logger.warning("skipping %s: %s", result.path, result.reason)
                failed.append({"path": result.path, "reason": result.reason})
                bar.advance(tiles_bar)
            else:
                cell_results.append(result)
                bar.advance(cells_bar)
    except BaseException:
        client.cancel(all_futures)
        raise
    stage_seconds["merge_tail"] = time.perf_counter() - started - stage_seconds.get("rasterize", 0.0)
    if not tile_results:
        raise InputDataError("INPUT", "no tile could be decoded: every tile failed")
    tile_results.sort(key=lambda r: r.tile_index)
    order = {cell.id: i for i, cell in enumerate(plan.cells)}
    cell_results.sort(key=lambda r: order[r.cell_id])
    return tile_results, failed, cell_results


def hole_params(plan: SurveyPlan, config: Config) -> HoleParams:
    """The ``[holes]`` settings in the survey's units: computed once, for detection and linking alike."""
    holes = config.holes
    unit = plan.survey.horizontal_unit_m
    pixel_area_m2 = (plan.grid.resolution * unit) ** 2
    return HoleParams(
        jump_threshold=holes.jump_threshold_m / plan.survey.vertical_unit_m,
        voxel_height=config.rasterize.voxel_height_m / plan.survey.vertical_unit_m,
        connectivity=holes.connectivity,
        min_area_px=math.ceil(holes.min_area_m2 / pixel_area_m2),
        vertical_min_px=math.ceil(holes.vertical_min_area_m2 / pixel_area_m2),
        wall_min_length_px=holes.wall_min_length_m / unit / plan.grid.resolution,
    )


def _run_detection(client, plan: SurveyPlan, config: Config, cell_results, bar: _Progress, water) -> list:
    """Stage 3: the footprint on the client, then one detection task per cell."""
    from distributed import as_completed

    holes = config.holes
    closing_blocks = math.ceil(holes.footprint_closing_m / holes.footprint_block_m)
    # a given AOI is authoritative: every empty pixel inside it is a hole; without one,
    # the data footprint decides what is exterior
    blocks = footprint_map(
        [r.occupied_blocks for r in cell_results],
        plan.grid,
        plan.block_px,
        closing_blocks=closing_blocks,
        everything=plan.aoi_given,
    )
    params = hole_params(plan, config)
    cells = {c.id: c for c in plan.cells}
    area_wkb = shapely.to_wkb(plan.survey_area) if plan.aoi_given else None
    water_wkb = shapely.to_wkb(water) if water is not None else None
    futures = []
    for result in cell_results:
        cell = cells[result.cell_id]
        task = DetectTask(
            cell=cell,
            grid=plan.grid,
            statistics_path=result.statistics_path,
            blocks=blocks.slice_for(plan.grid, cell.halo_window),
            tile_windows=tuple(w for w in plan.tile_windows if not w.intersection(cell.halo_window).is_empty),
            survey_area_wkb=area_wkb,
            water_wkb=water_wkb,
            params=params,
        )
        futures.append(client.submit(detect_cell, task, pure=False))
    handle = bar.add("find holes", total=len(futures))
    detected = []
    try:
        for future in as_completed(futures):
            detected.append(future.result())
            bar.advance(handle)
    except BaseException:
        client.cancel(futures)
        raise
    order = {r.cell_id: i for i, r in enumerate(cell_results)}
    detected.sort(key=lambda d: order[d.cell_holes.cell.id])
    return detected


# -- outputs --------------------------------------------------------------------------


def _write_outputs(staging: Path, plan: SurveyPlan, tile_results, cell_results, skipped) -> None:
    grid = plan.grid
    cells_by_id = {c.id: c for c in plan.cells}
    sources = []
    for r in cell_results:
        if r.dsm_path:
            w = cells_by_id[r.cell_id].window
            sources.append((r.dsm_path, w.row_off, w.col_off, w.height, w.width))
    if sources:
        write_vrt(
            staging / "dsm.vrt",
            sources,
            width=grid.width,
            height=grid.height,
            transform=grid.transform,
            crs_wkt=grid.crs_wkt,
            description="DSM: highest point per pixel",
        )
    gpkg = staging / "holes.gpkg"
    done = {r.tile_index: r for r in tile_results}
    skipped_paths = {s["path"] for s in skipped}
    tile_records, tile_geometries = [], []
    for record in tile_index_records(plan.survey):
        bounds = record.pop("bounds")
        result = done.get(record["tile_id"])
        record["points_used"] = result.points_used if result else 0
        record["status"] = "ok" if result else ("skipped" if record["path"] in skipped_paths else "failed")
        tile_records.append(record)
        tile_geometries.append(shapely.box(*bounds))
    write_layer(gpkg, "tiles", tile_records, tile_geometries, crs_wkt=grid.crs_wkt, geometry_type="Polygon")
    cell_records, cell_geometries = [], []
    for r in cell_results:
        cell = cells_by_id[r.cell_id]
        cell_records.append(
            {
                "cell_id": cell.id,
                "index_x": cell.index_x,
                "index_y": cell.index_y,
                "row_off": cell.window.row_off,
                "col_off": cell.window.col_off,
                "width_px": cell.window.width,
                "height_px": cell.window.height,
                "points": r.points,
                "empty_pixels": r.empty_pixels,
                "empty_fraction": r.empty_pixels / r.pixels if r.pixels else 0.0,
                "dsm_file": os.path.relpath(r.dsm_path, staging) if r.dsm_path else None,
            }
        )
        cell_geometries.append(shapely.box(*grid.window_bounds(cell.window)))
    write_layer(gpkg, "cells", cell_records, cell_geometries, crs_wkt=grid.crs_wkt, geometry_type="Polygon")
    write_layer(
        gpkg,
        "survey_area",
        [{"source": "--aoi polygon" if plan.aoi_given else "union of tile extents"}],
        [plan.survey_area],
        crs_wkt=grid.crs_wkt,
    )


def _write_manifest(path: Path, summary: RunSummary, plan: SurveyPlan, config: Config, tile_results, cell_results) -> dict:
    grid = plan.grid
    manifest = {
        "holefill_version": __version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "host": socket.gethostname(),
        "config": to_dict(config),
        "crs": {"wkt": grid.crs_wkt, "name": CRS.from_wkt(grid.crs_wkt).name},
        "grid": {
            "resolution": grid.resolution,
            "resolution_unit_m": plan.survey.horizontal_unit_m,
            "width": grid.width,
            "height": grid.height,
            "bounds": grid.bounds,
            "cell_px": grid.cell_px,
            "halo_px": grid.halo_px,
        },
        "inputs": [
            {"path": r.path, "points_read": r.points_read, "points_used": r.points_used, "seconds": round(r.seconds, 3)}
            for r in tile_results
        ],
        "skipped": summary.skipped,
        "outputs": {
            "dsm_vrt": "dsm.vrt" if summary.dsm_tiles else None,
            "dsm_tiles": summary.dsm_tiles,
            "holes_gpkg": "holes.gpkg",
        },
        "summary": {
            "tiles": summary.tiles,
            "cells": summary.cells,
            "points_read": summary.points_read,
            "points_used": summary.points_used,
            "seconds": round(summary.seconds, 3),
            "points_per_second": round(summary.points_per_second),
            "stage_seconds": {k: round(v, 3) for k, v in summary.stage_seconds.items()},
            "empty_pixels": sum(r.empty_pixels for r in cell_results),
        },
        "holes": summary.holes,
    }
    path.write_text(json.dumps(manifest, indent=2, default=str))
    return manifest


def _make_staging(out: Path) -> Path:
    """The run's private folder inside OUT; tasks write only into its subfolders made here."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        staging = out / f".holefill-partial-{uuid.uuid4().hex[:10]}"
        staging.mkdir()
        for sub in ("work/tiles", "work/cells", "dsm"):
            (staging / sub).mkdir(parents=True)
        probe = staging / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise OutputError(f"{out}: output folder cannot be created or written: {e.strerror or e}") from None
    return staging


def _commit(staging: Path, out: Path, *, keep_work: bool) -> None:
    """Move every product from the staging folder into OUT, replacing older ones."""
    for name in PRODUCTS + (("work",) if keep_work else ()):
        source = staging / name
        if not source.exists():
            continue
        target = out / name
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        elif target.exists():
            target.unlink()
        os.replace(source, target)
    shutil.rmtree(staging, ignore_errors=True)


def _remove_staging(staging: Path) -> None:
    """Delete a failed run's staging folder; a task still finishing may race the first try."""
    for _ in range(5):
        shutil.rmtree(staging, ignore_errors=True)
        if not staging.exists():
            return
        time.sleep(0.2)


# -- Dask and progress ----------------------------------------------------------------


@contextlib.contextmanager
def _dask_client(client, scheduler: str | None, config: Config) -> Iterator[Any]:
    if client is not None:
        yield client
        return
    from distributed import Client, LocalCluster

    if scheduler:
        with Client(scheduler) as remote:
            yield remote
        return
    workers = config.dask.workers or os.cpu_count() or 1
    verbose = logging.getLogger("distributed").isEnabledFor(logging.INFO)
    with LocalCluster(
        n_workers=workers,
        threads_per_worker=1,
        processes=True,
        memory_limit=config.dask.memory_limit,
        dashboard_address=":0",  # any free port: never collide with another cluster
        silence_logs=logging.INFO if verbose else logging.CRITICAL,  # task errors reach the client anyway
    ) as cluster, Client(cluster) as local:
        yield local


class _Progress:
    """rich progress bars on stderr: tasks done, points per second, time left."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self._progress = None
        self._points: dict[int, int] = {}
        self._started = time.perf_counter()

    def __enter__(self) -> _Progress:
        if self.enabled:
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            self._progress = Progress(
                TextColumn("{task.description:<24}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[rate]}"),
                TimeRemainingColumn(),
                console=Console(stderr=True),
            )
            self._progress.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self._progress is not None:
            self._progress.__exit__(*exc)

    def add(self, description: str, *, total: int) -> int:
        """A new bar; returns its handle."""
        handle = len(self._points)
        self._points[handle] = 0
        if self._progress is not None:
            handle = self._progress.add_task(description, total=total, rate="")
            self._points[handle] = 0
        return handle

    def advance(self, handle: int, *, points: int = 0) -> None:
        self._points[handle] = self._points.get(handle, 0) + points
        if self._progress is not None:
            elapsed = max(time.perf_counter() - self._started, 1e-9)
            rate = f"{self._points[handle] / elapsed / 1e6:6.2f} M pts/s" if self._points[handle] else ""
            self._progress.update(handle, advance=1, rate=rate)
