"""Stage 1, one task per read task: decode its points once and bin them into the global grid.

A read task (:mod:`pipeline.reads`) is a whole LAS/LAZ file, or a group of a COPC
file's octree nodes when the file is split. Either way the worker sees the same
thing: :func:`read_points` yields :class:`~pipeline.io.las.PointChunk` records
(integer coordinates with scale and offset, class, withheld flag, flight line),
which is the whole interface between a reader and the binning; another reader
(e.g. PDAL) only has to yield those.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import Transformer

from ..config import Config
from ..errors import InputDataError
from ..grid import Grid, PixelWindow
from ..io import pdal_reader
from ..io.checksums import input_record
from ..io.copc import iter_copc_nodes, load_point_chunk, save_point_chunk
from ..io.intermediate import save_tile_ground, save_tile_statistics
from ..io.las import PointChunk, PulseFields, iter_point_chunks
from ..parameters import read_params
from ..plan import SurveyPlan
from ..rasterize import (
    WATER_CLASS,
    HeightMapAccumulator,
    PointFilter,
    point_filter_mask,
    removed_by_class_filter,
)
from ..reads import Node, cell_of
from ..sensor.sums import TrajectorySums, trajectory_sums
from ..staging import Staging, input_fingerprint
from ..survey.blocks import BlockPart, BlockWindow
from ..survey.footprint_density import BlockCounter, PulseCounting, pulse_counting
from ..survey.ground_level import GROUND_CLASS, GroundLevel, count_ground_at_zero
from ..survey.scan import source_crs_for_task
from .stage import Dependency, RunState, Stage

#: What a run tells of its tiles as they arrive (skipped, points off their bounds), under the engine's name
#: it has always been logged under (the gather runs in the engine, on the client).
logger = logging.getLogger("pipeline.run")


@dataclass(frozen=True)
class TileTask:
    """Decode one read task (a tile, or some nodes of a COPC file) once and bin its points into the global grid."""

    tile_index: int
    read_index: int  # plan.reads index: the same as tile_index unless a COPC file is split
    path: str
    window: PixelWindow
    shared_windows: tuple[PixelWindow, ...]
    grid: Grid
    source_crs_wkt: str | None  # reproject from this CRS to the grid's, or None
    point_filter: PointFilter
    chunk_points: int
    voxel_height: float  # z units
    output_dir: str
    nodes: tuple[Node, ...] = ()  # COPC chunks to decode; empty: the whole file
    part: str = ""  # "3/12" for a split COPC file's fourth task (labels)
    role: str = "whole"  # "whole", or a split COPC file's "top" or "cell" task (pipeline.reads)
    cell: tuple[int, int] | None = None  # a cell task's cell
    top_dir: str = ""  # a cell task: where its file's top task leaves the points of each cell
    cells: tuple[tuple[int, int], ...] = ()  # a top task: the cells its file has tasks for
    pdal: pdal_reader.PdalRead | None = None  # read through PDAL (read.reader = "pdal"), else laspy
    sensor: bool = False  # decode the pulses' fields and sum them for the flight lines' trajectories
    skip_bad_tile: bool = False  # survey.on_error = "skip": a tile that cannot be decoded is reported, not raised
    counting: PulseCounting | None = None  # count the pulses in the footprint's blocks (the density, run.py)
    ground: bool = False  # sum the ground points' heights per pixel (the flight planner's take-off height)


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
    read_index: int = -1
    read_tasks: int = 1  # tasks the file was read by (after results_by_file)
    ground: GroundLevel = GroundLevel()  # ground-class points binned, and those at z = 0
    trajectory: TrajectorySums = field(default_factory=TrajectorySums.empty)  # per flight line and time bin
    pulse_blocks: BlockPart | None = None  # the footprint's block counts, when counting
    #: The file's size, time and SHA-256 for the manifest (from the task reading it whole, or its top task).
    input: dict[str, Any] | None = None


@dataclass(frozen=True)
class TileFailure:
    """A tile that could not be decoded, when bad tiles are skipped."""

    tile_index: int
    path: str
    reason: str


def tile_tasks(plan: SurveyPlan, config: Config, staging: Staging) -> list[TileTask]:
    """One task per read task of the plan, in row-major order of their windows so that cells complete early.

    A split COPC file's top task comes first (its cell tasks wait for it). Its tasks keep
    their results under ``<file>-<fingerprint>-part<k>``, where the fingerprint also covers
    the task's nodes and cell: a resumed run finds them again.
    """
    params = read_params(config, vertical_unit_m=plan.survey.vertical_unit_m)
    point_filter, voxel_height = params.point_filter, params.voxel_height
    grid = plan.grid
    top_dirs: dict[int, str] = {}
    cells: dict[int, list[tuple[int, int]]] = {}
    block, first_only = pulse_counting(plan.survey) if plan.density_pending else (0.0, False)
    ground = params.ground
    tasks = []
    for read_index, (read, window) in enumerate(zip(plan.reads, plan.read_windows)):
        tile = plan.survey.tiles[read.tile_index]
        source_crs = source_crs_for_task(tile, plan.survey)
        pdal = None
        if params.pdal:  # PDAL reads whole files (the plan does not split them)
            pdal = pdal_reader.tile_read(params.pdal_pipeline, plan.survey.crs_wkt, tile.header, tile.source_crs_wkt)
            source_crs = None if pdal.reprojects else source_crs  # else PDAL's points are in the survey CRS
        key: tuple[object, ...] = (grid.resolution, grid.col_min, grid.row_top, grid.offset, source_crs)
        sensor = params.sensor
        key += (point_filter, voxel_height, sensor) + (() if pdal is None else (pdal,))
        key += ("ground",) if ground else ()  # a tile's result says whether it holds the ground sums
        if read.is_whole_file:
            fingerprint = input_fingerprint(tile.path, window, *key)
        else:
            fingerprint = input_fingerprint(tile.path, window, *key, read.nodes, read.cell, top_dirs.get(tile.index))
            fingerprint += f"-part{read.part:03d}"
        output_dir = str(staging.tile_folder(tile.path, fingerprint))
        if read.role == "top":
            top_dirs[tile.index] = output_dir
        if read.cell is not None:
            cells.setdefault(tile.index, []).append(read.cell)
        tasks.append(
            TileTask(
                tile_index=tile.index,
                read_index=read_index,
                path=tile.path,
                window=window,
                shared_windows=_outermost(plan.shared_windows[read_index]),
                grid=grid,
                source_crs_wkt=source_crs,
                point_filter=point_filter,
                chunk_points=params.chunk_points,
                voxel_height=voxel_height,
                output_dir=output_dir,
                nodes=read.nodes,
                part="" if read.is_whole_file else f"{read.part}/{read.parts}",
                role=read.role,
                cell=read.cell,
                top_dir=top_dirs.get(tile.index, "") if read.role == "cell" else "",
                pdal=pdal,
                sensor=sensor,
                counting=PulseCounting(tile.bounds, block, first_only) if plan.density_pending else None,
                ground=ground,
            )
        )
    tasks = [replace(t, cells=tuple(cells[t.tile_index])) if t.role == "top" else t for t in tasks]
    return sorted(tasks, key=lambda t: (t.role != "top", t.window.row_off, t.window.col_off))


def _outermost(windows: tuple[PixelWindow, ...]) -> tuple[PixelWindow, ...]:
    """The windows not inside another one: the same pixels, each listed once where possible.

    Keys are then gathered once per pixel instead of once per overlap.
    """
    kept: list[PixelWindow] = []
    for window in sorted(set(windows), key=lambda w: -w.height * w.width):
        if not any(window.intersection(outer) == window for outer in kept):
            kept.append(window)
    return tuple(dict.fromkeys(w for w in windows if w in kept))


def read_points(task: TileTask) -> Iterator[PointChunk]:
    """The reader interface: a read task's points, chunk by chunk, each point decoded once.

    laspy for a whole LAS/LAZ file, PDAL (and the user's stages) with ``read.reader =
    "pdal"``, lazrs on the listed octree nodes for part of a split COPC file.
    """
    if task.pdal is not None:
        return pdal_reader.iter_pdal_chunks(task.path, task.chunk_points, task.pdal)
    if task.role == "whole":
        return iter_point_chunks(task.path, task.chunk_points, pulses=task.sensor)
    return iter_copc_nodes(task.path, task.nodes, task.chunk_points, pulses=task.sensor)


def _points_to_bin(task: TileTask) -> Iterator[tuple[PointChunk, bool]]:
    """``(chunk, decoded here)``: the task's own points, then those its file's top task handed to its cell."""
    for chunk in read_points(task):
        yield chunk, True
    if task.cell is not None and task.top_dir:
        handed = Path(task.top_dir) / _handed_name(task.cell)
        if handed.exists():
            yield load_point_chunk(handed), False


def _handed_name(cell: tuple[int, int]) -> str:
    return f"cell_{cell[0]}_{cell[1]}.npz"


def hand_over_top(task: TileTask, *after: object) -> TileResult:
    """A split COPC file's top task: decode the octree's top nodes once and leave each cell's points to its task.

    Bins nothing (its window is empty); the points of a cell the file has no task for
    lie outside the file's bounds and are counted as outside.
    """
    started = time.perf_counter()
    grid, wanted = task.grid, set(task.cells)
    by_cell: dict[tuple[int, int], list[PointChunk]] = {}
    read = outside = 0
    counter = _counter(task)
    transformer = _transformer(task)
    for chunk in read_points(task):
        if counter is not None:
            _count_pulses(counter, chunk, task, transformer)
        x, y, _ = chunk.coordinates()
        cell_x, cell_y = cell_of(grid, x, y)
        keys = np.stack([cell_x, cell_y], axis=1)
        for key in map(tuple, np.unique(keys, axis=0).tolist()):
            keep = (cell_x == key[0]) & (cell_y == key[1])
            if key in wanted:
                by_cell.setdefault(key, []).append(_subset(chunk, keep))
            else:
                outside += int(keep.sum())
        read += len(chunk)
    Path(task.output_dir).mkdir(exist_ok=True)  # never parents (a cancelled run's staging folder stays deleted)
    for key, parts in by_cell.items():
        merged = _concatenate(parts)
        save_point_chunk(Path(task.output_dir) / _handed_name(key), merged, np.ones(len(merged), bool))
    return TileResult(
        tile_index=task.tile_index,
        path=task.path,
        output_dir=task.output_dir,
        window=task.window,
        points_read=read,
        points_used=0,
        points_outside=outside,
        seconds=time.perf_counter() - started,
        read_index=task.read_index,
        pulse_blocks=None if counter is None else counter.counts(),
    )


def _subset(chunk: PointChunk, keep: np.ndarray) -> PointChunk:
    pulses = None if chunk.pulses is None else PulseFields(*(v[keep] for v in vars(chunk.pulses).values()))
    return PointChunk(
        X=chunk.X[keep], Y=chunk.Y[keep], Z=chunk.Z[keep], scales=chunk.scales, offsets=chunk.offsets,
        classification=chunk.classification[keep], withheld=chunk.withheld[keep],
        point_source_id=chunk.point_source_id[keep], pulses=pulses,
    )  # fmt: skip


def _concatenate(parts: list[PointChunk]) -> PointChunk:
    def joined(name: str) -> np.ndarray:
        return np.concatenate([getattr(p, name) for p in parts])

    pulses = None
    if all(p.pulses is not None for p in parts):
        pulses = PulseFields(*(np.concatenate([getattr(p.pulses, f) for p in parts]) for f in vars(parts[0].pulses)))
    return PointChunk(
        X=joined("X"), Y=joined("Y"), Z=joined("Z"), scales=parts[0].scales, offsets=parts[0].offsets,
        classification=joined("classification"), withheld=joined("withheld"),
        point_source_id=joined("point_source_id"), pulses=pulses,
    )  # fmt: skip


def rasterize_tile(task: TileTask, *after: object) -> TileResult:
    """Stream one read task's points in chunks into per-pixel statistics.

    ``after``: results this task waits for (a COPC cell task: its file's top task).
    """
    if task.role == "top":
        return hand_over_top(task)
    started = time.perf_counter()
    grid = task.grid
    accumulator = HeightMapAccumulator(
        task.window, resolution=grid.resolution, col_min=grid.col_min, row_top=grid.row_top,
        grid_width=grid.width, voxel_height=task.voxel_height, offset=grid.offset, ground=task.ground,
    )  # fmt: skip
    transformer = _transformer(task)
    read = used = outside = 0
    ground = GroundLevel()
    sums: list[TrajectorySums] = []
    origin = (grid.x_left, grid.y_top, 0.0)
    f = task.point_filter
    counter = _counter(task)
    for chunk, decoded in _points_to_bin(task):
        if counter is not None and decoded:  # handed-over points were counted by the top task
            _count_pulses(counter, chunk, task, transformer)
        keep = point_filter_mask(
            chunk.classification,
            chunk.withheld,
            drop_classes=f.drop_classes,
            keep_classes=f.keep_classes,
            drop_withheld=f.drop_withheld,
        )
        evidence = {"water": chunk.classification == WATER_CLASS, "source": chunk.point_source_id}
        is_ground = keep & (chunk.classification == GROUND_CLASS)
        if task.ground:  # every ground point the sensor did not withhold, kept by the filter or not
            evidence["ground"] = (chunk.classification == GROUND_CLASS) & ~chunk.withheld
        removed = removed_by_class_filter(chunk.classification, chunk.withheld, keep, filters_classes=f.filters_classes)
        # the sensor's geometry comes from every return but noise, whatever the model keeps
        sensed = keep if removed is None else keep | removed

        if transformer is None:
            n_used, n_outside = accumulator.add(
                chunk.X, chunk.Y, chunk.Z, keep, scales=chunk.scales, offsets=chunk.offsets, **evidence
            )
            ground += count_ground_at_zero(chunk.Z, is_ground, scale=chunk.scales[2], offset=chunk.offsets[2])
            if chunk.pulses is not None:
                raw = (chunk.X, chunk.Y, chunk.Z)
                sums.append(_trajectory_sums(chunk, raw, sensed, origin, chunk.scales, chunk.offsets))
            if removed is not None:
                _count_left_out(accumulator, removed, evidence["water"], chunk.X, chunk.Y, chunk.scales, chunk.offsets)
        else:
            x, y, z = chunk.coordinates()
            x, y = transformer.transform(x, y)
            n_used, n_outside = accumulator.add(x, y, z, keep, **evidence)
            ground += count_ground_at_zero(z, is_ground)
            if chunk.pulses is not None:
                sums.append(_trajectory_sums(chunk, (x, y, z), sensed, origin))
            if removed is not None:
                _count_left_out(accumulator, removed, evidence["water"], x, y)
        read += len(chunk) if decoded else 0  # handed-over points were counted by the top task
        used += n_used
        outside += n_outside
    _check_header_bounds(task, transformer is None, read, outside)
    save_tile_statistics(task.output_dir, accumulator.statistics, accumulator.voxel_keys(task.shared_windows))
    if accumulator.ground is not None:
        save_tile_ground(task.output_dir, accumulator.ground)
    return TileResult(
        tile_index=task.tile_index,
        path=task.path,
        output_dir=task.output_dir,
        window=task.window,
        points_read=read,
        points_used=used,
        points_outside=outside,
        seconds=time.perf_counter() - started,
        read_index=task.read_index,
        ground=ground,
        trajectory=TrajectorySums.merged(sums),
        pulse_blocks=None if counter is None else counter.counts(),
    )


def _transformer(task: TileTask) -> Transformer | None:
    """From the task's source CRS to the grid's, or None where the points are in the grid's CRS."""
    if not task.source_crs_wkt:
        return None
    return Transformer.from_crs(task.source_crs_wkt, task.grid.crs_wkt, always_xy=True)


def _counter(task: TileTask) -> BlockCounter | None:
    """The pulse counter of a task that counts (:attr:`TileTask.counting`), over its file's box."""
    return None if task.counting is None else BlockCounter(task.counting.bounds, task.counting.block)


def _count_pulses(counter: BlockCounter, chunk: PointChunk, task: TileTask, transformer: Transformer | None) -> None:
    """Count a decoded chunk's pulses (first returns, or every point) as the density pre-pass would.

    Every decoded point counts, whatever the filter keeps: the footprint is where the
    sensor measured (:mod:`pipeline.survey.footprint_density`), and the same expressions
    (``X * scale + offset``, then the transformation) give the same blocks.
    """
    assert task.counting is not None
    if task.counting.first_only and chunk.return_number is None:
        raise ValueError(f"{task.path}: the reader gave no return numbers to count first returns by")
    returns = chunk.return_number if task.counting.first_only else None
    if transformer is None:
        counter.add_records(chunk.X, chunk.Y, chunk.scales, chunk.offsets, returns)
        return
    x, y = chunk.X, chunk.Y
    if returns is not None:
        x, y = x[returns == 1], y[returns == 1]
    counter.add(*transformer.transform(x * chunk.scales[0] + chunk.offsets[0], y * chunk.scales[1] + chunk.offsets[1]))


def _count_left_out(
    accumulator: HeightMapAccumulator,
    removed: np.ndarray,
    water: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    scales: tuple[float, float, float] = (1.0, 1.0, 1.0),
    offsets: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> None:
    """Points the class filter left out: water is evidence of water, the others of a cover (buildings, trees)."""
    accumulator.add_counts("water", x, y, removed & water, scales=scales, offsets=offsets)
    accumulator.add_counts("covered", x, y, removed & ~water, scales=scales, offsets=offsets)


def _trajectory_sums(
    chunk: PointChunk,
    xyz: tuple[np.ndarray, np.ndarray, np.ndarray],
    keep: np.ndarray,
    origin: tuple[float, float, float],
    scales: tuple[float, float, float] = (1.0, 1.0, 1.0),
    offsets: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> TrajectorySums:
    """The chunk's sums per flight line and time bin (:mod:`pipeline.sensor.sums`).

    ``xyz``: world coordinates, or the record's integers with their ``scales`` and ``offsets``.
    """
    p = chunk.pulses
    assert p is not None
    x, y, z = xyz
    return TrajectorySums(
        *trajectory_sums(
            x, y, z, chunk.point_source_id, p.gps_time, p.return_number, p.number_of_returns, p.scan_angle_deg, keep,
            origin=origin, scales=scales, offsets=offsets,
        )
    )  # fmt: skip


def _check_header_bounds(task: TileTask, same_crs: bool, read: int, outside: int) -> None:
    """Refuse a file whose points lie outside its header bounds: the header lies, and its grid left them out.

    Only where the bounds are the file's own (a whole file read by laspy in its own CRS); a
    reprojected or PDAL-filtered file's stray points stay a warning and a line of the report.
    """
    if outside and same_crs and task.role == "whole" and task.pdal is None:
        raise InputDataError(
            task.path,
            f"{outside:,} of {read:,} points lie outside the bounds its header declares: the header is wrong "
            "(refused rather than dropping them; repair the header, e.g. with lasinfo -repair_bb)",
        )


def rasterize_tile_or_skip(task: TileTask, *after: object) -> TileResult | TileFailure:
    """:func:`rasterize_tile`, reporting a bad tile instead of raising (``on_error = "skip"``).

    A split COPC file's cell task whose file's top task failed still bins its own
    nodes (without the top's points): the file is listed as skipped through the top
    task's failure, and what its other tasks read stays in the DSM, as for any of
    its tasks that fails.
    """
    try:
        return rasterize_tile(task)
    except InputDataError as e:
        return TileFailure(task.tile_index, task.path, e.reason)


def results_by_file(results: list[TileResult]) -> list[TileResult]:
    """One result per file, in tile order: a split file's tasks summed (points, seconds, tasks)."""
    by_file: dict[int, TileResult] = {}
    for r in sorted(results, key=lambda r: (r.tile_index, r.read_index)):
        kept = by_file.get(r.tile_index)
        by_file[r.tile_index] = (
            r
            if kept is None
            else replace(
                kept,
                points_read=kept.points_read + r.points_read,
                points_used=kept.points_used + r.points_used,
                points_outside=kept.points_outside + r.points_outside,
                seconds=kept.seconds + r.seconds,
                read_tasks=kept.read_tasks + 1,
                ground=kept.ground + r.ground,
                trajectory=kept.trajectory + r.trajectory,
                pulse_blocks=_joined_blocks(kept.pulse_blocks, r.pulse_blocks),
                input=kept.input or r.input,
            )
        )
    return list(by_file.values())


def _joined_blocks(a: BlockPart | None, b: BlockPart | None) -> BlockPart | None:
    """The block counts of two read tasks of one file, listed together (added up when merged)."""
    if a is None or b is None:
        return a if b is None else b
    a, b = (p.occupied() if isinstance(p, BlockWindow) else p for p in (a, b))
    return (np.concatenate([a[0], b[0]]), np.concatenate([a[1], b[1]]), np.concatenate([a[2], b[2]]))


def adopt_result(task: TileTask, kept: TileResult | TileFailure) -> TileResult | TileFailure:
    """A previous run's result of the same read task (same key), pointed at this run's indices and folder."""
    if isinstance(kept, TileResult):
        return replace(kept, tile_index=task.tile_index, read_index=task.read_index, output_dir=task.output_dir)
    return replace(kept, tile_index=task.tile_index)


# -- the stage's records: pipeline.stages.registry lists them, pipeline.run walks them --------


@dataclass(frozen=True)
class DecodedTiles:
    """Stage 1's gathered result: one result per file decoded (in tile order) and the files left out."""

    tiles: tuple[TileResult, ...]
    failed: tuple[dict[str, str], ...]  # {"path", "reason"}: skipped, or none of its points passes the filter
    inputs: Mapping[str, dict[str, Any]]  # path -> size, time and SHA-256


def bin_tile(task: TileTask, *after: object) -> TileResult | TileFailure:
    """The stage's worker: :func:`rasterize_tile`, or :func:`rasterize_tile_or_skip` when bad tiles are skipped.

    The task that reads a file whole (or a split file's top task) then hashes it for the manifest
    (:func:`pipeline.io.checksums.input_record`), while its bytes are in the page cache: hashed by
    tasks of their own, at the lowest priority, the files waited for the end of the decoding, and
    320 tasks of 7 ms each made the last 2.5 s of a 211 M-point run.
    """
    result = rasterize_tile_or_skip(task, *after) if task.skip_bad_tile else rasterize_tile(task, *after)
    if isinstance(result, TileFailure) or task.role not in ("whole", "top"):
        return result  # a skipped tile is no input of the manifest
    return replace(result, input=input_record(task.path))


def result_folder(task: TileTask) -> str:
    """The name of a read task's result folder (its file's stem and fingerprint): what its task keys are made of."""
    return Path(task.output_dir).name


def _read_tasks(state: RunState, results: list[object]) -> tuple[TileTask, ...]:
    skip = state.config.survey.on_error == "skip"
    return tuple(replace(task, skip_bad_tile=skip) for task in tile_tasks(state.plan, state.config, state.staging))


def _top_task(task: TileTask) -> tuple[Dependency, ...]:
    """A split COPC file's cell task takes its file's top task's result (the points the top hands over)."""
    return ((BIN_TILES.name, Path(task.top_dir).name),) if task.role == "cell" and task.top_dir else ()


def _tell(result: TileResult | TileFailure) -> int:
    """As a tile's result arrives: warn of a skipped tile or of points off its bounds; its points (the bar's rate)."""
    if isinstance(result, TileFailure):
        logger.warning("skipping %s: %s", result.path, result.reason)
        return 0
    if result.points_outside:
        logger.warning(
            "%s: %d points lie outside the bounds its header (or, for a split COPC file, its octree nodes) declares; they were not used",
            result.path,
            result.points_outside,
        )
    return result.points_read


def _gather_tiles(state: RunState, results: list[TileResult | TileFailure]) -> DecodedTiles:
    """One result per file (a split file's tasks summed); a file with no point used is listed as skipped."""
    tiles = [r for r in results if isinstance(r, TileResult)]
    _check_points_left(tiles, state.config)
    failed = {r.path: {"path": r.path, "reason": r.reason} for r in results if isinstance(r, TileFailure)}
    tiles = results_by_file(tiles)
    left_out = list(failed.values())  # a split file's failed tasks: once
    for empty in (r for r in tiles if not r.points_used):  # listed and warned like a skipped tile
        reason = f"no point used: none of its {empty.points_read:,} points passes the filter ([filter])"
        logger.warning("skipping %s: %s", empty.path, reason)
        left_out.append({"path": empty.path, "reason": reason})
    # a split file whose top task failed has its cells' results alone: hashed here
    inputs = {r.path: r.input if r.input is not None else input_record(r.path) for r in tiles}
    return DecodedTiles(tuple(tiles), tuple(left_out), inputs)


def _check_points_left(tiles: list[TileResult], config: Config) -> None:
    """Stop with one line when no tile could be decoded or the filter left no point."""
    if not tiles:
        raise InputDataError("INPUT", "no tile could be decoded: every tile failed")
    if not any(r.points_used for r in tiles):
        f = config.filter
        raise InputDataError(
            "INPUT",
            f"no point is left after filtering (filter.keep_classes = {f.keep_classes}, "
            f"filter.drop_classes = {f.drop_classes}, filter.drop_withheld = {str(f.drop_withheld).lower()})",
        )


#: Stage 1's recipes, on the client: its read tasks, whose result folders the merge names too.
READ_TASKS: Stage[object, tuple[TileTask, ...]] = Stage(name="read_tasks", gather=_read_tasks)

#: Stage 1: one task per read task, decoding its points once; a split COPC file's top tasks come first.
BIN_TILES: Stage[TileTask, DecodedTiles] = Stage(
    name="bin_tiles",
    recipes=lambda state: state[READ_TASKS],
    worker=bin_tile,
    key=lambda task: f"rasterize-{result_folder(task)}",
    label=lambda task: f"tile {task.path}" + (f" (COPC read task {task.part})" if task.part else ""),
    gather=_gather_tiles,
    bar="decode + bin tiles",
    ident=result_folder,
    after=_top_task,
    priority=lambda task: 3 if task.role == "top" else 0,
    adopt=adopt_result,
    on_result=_tell,
    streams=True,  # each cell is merged as soon as its tiles are done
    lap="rasterize",
)
