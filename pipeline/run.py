"""Running a survey on Dask: the only module that builds Dask graphs (the client comes from :mod:`pipeline.cluster`).

A run is: scan headers -> plan (grid, cells, tile-to-cell index) -> stage 1
(one task per tile: decode once, bin) -> stage 2 (one task per cell: merge) ->
the writer stage (one task per cell: DSM tiles) -> detection (one task per
cell) -> linking on the client -> products. Each stage's recipes, worker and
gather step live in ``pipeline.stages``; this module only submits tasks with
their dependencies, gathers results in plan order, shows progress, and turns a
worker's unexpected exception into one line naming its tile or cell. Every
product is written into a staging folder inside OUT and moved into place only
when the whole run has succeeded (``pipeline.staging``).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

from . import __version__, interrupt
from .budget import MemoryBudget, check_plan_memory, memory_budget
from .cluster import ClusterStart, WorkerWatch, dask_client
from .config import Config, config_key, to_dict
from .errors import ClusterError, DiskFullError, HolefillError, InputDataError, TaskError
from .fill import HoleFill
from .flight_planning import plan_flights
from .footprint_density import measure_footprint
from .ground_level import NO_TERRAIN, GroundLevel
from .holes.coverage import CoverageGaps
from .io.checksums import input_record, output_records
from .io.vector import read_survey_area
from .output_guard import check_before_run, check_same_survey
from .outputs import (
    FLIGHTPLAN_PRODUCTS,
    PRODUCTS,
    RunSummary,
    write_hole_layers,
    write_manifest,
    write_mosaics,
    write_survey_layers,
)
from .parameters import fill_params
from .plan import SurveyPlan, needs_density, plan_survey
from .progress import ProgressBars as _Progress
from .progress import StageTimer as _StageTimer
from .report import ReportInputs, read_report_inputs, write_report
from .stages import bin_tiles, detect_holes, fill_holes, link_holes, merge_cells, write_points, write_rasters
from .stages.bin_tiles import TileFailure, TileResult
from .stages.merge_cells import CellResult
from .stages.write_rasters import WriteResult
from .staging import PARTIAL_PREFIX, Staging, disk_full, input_fingerprint, run_and_keep
from .survey import scan_survey

logger = logging.getLogger(__name__)


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
    resume: bool = False,
    overwrite: bool = False,
    incremental: bool = False,
    cluster: ClusterStart | None = None,
) -> RunSummary:
    """Run the pipeline on a survey and write the products into ``out_dir``.

    Parameters
    ----------
    inputs : list of str
        Files, folders or globs of LAS/LAZ/COPC tiles.
    out_dir : path-like
        Output folder (created if needed); older products of the same configuration are replaced.
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
    resume, incremental : bool
        Resume: continue an interrupted run of the same inputs and configuration into
        the same folder (tasks that finished then are not run again). Incremental: keep
        the stage results in ``out_dir/work`` and take from the previous run's those of
        unchanged tiles and cells (a scheduled re-run decodes only new or changed tiles).
    overwrite : bool
        Replace a result of another configuration in ``out_dir`` (refused otherwise).
    cluster : ClusterStart, optional
        A local cluster already being started (the CLI starts it before importing
        this module); default: one started here, unless ``client`` or ``scheduler``.
    """
    started = time.perf_counter()
    out = Path(out_dir).absolute()  # workers of a remote cluster resolve paths on their own machines
    check_before_run(out, config_key(config), overwrite=overwrite)
    timer = _StageTimer(started)
    with contextlib.ExitStack() as cluster_scope:
        connect = cluster_scope.enter_context(dask_client(client, scheduler, config, start=cluster))
        budget = memory_budget(config, scheduler=scheduler if client is None else "client")
        plan = _plan(inputs, config, aoi, out, budget)  # the headers are scanned while the workers start
        check_same_survey(out, [t.path for t in plan.survey.tiles], overwrite=overwrite or resume)
        water, water_area = _water(water, config, plan)
        timer.lap("scan")
        created_out = not out.exists()
        reuse = incremental and _holds_result_of(out, config)
        staging = Staging.create(out, run_key=run_key(plan, config, aoi, water), resume=resume, incremental=reuse)
        if staging.resumed and staging.commit_pending:  # the interrupted run had finished: move it into place
            cluster_scope.close()
            return _finish_commit(staging)
        try:
            summary = _run_and_publish(
                connect, cluster_scope, staging, plan, config, (started, timer), water_area, progress=progress,
                keep_work=config.output.keep_intermediate or incremental,
            )  # fmt: skip
        except (KeyboardInterrupt, SystemExit, TaskError, DiskFullError, ClusterError):
            # interrupted, or the cluster lost a worker for good: finished tasks stay for --resume
            interrupt.acknowledge()  # a second TERM must not cut the unlock short
            staging.keep_for_resume()
            raise
        except BaseException:
            _discard(staging, created_out)
            raise
    return summary


def _run_and_publish(
    connect: Any,
    cluster_scope: contextlib.ExitStack,
    staging: Staging,
    plan: SurveyPlan,
    config: Config,
    clock: tuple[float, _StageTimer],
    water_area: Any,
    *,
    progress: bool,
    keep_work: bool,
) -> RunSummary:
    """Every stage on the workers, then, the workers stopped (their memory freed), the products."""
    started, timer = clock
    with _Progress(progress) as bar:
        runner = _Runner(
            connect(), bar, staging, retries=config.dask.retries, no_worker_timeout_s=config.dask.no_worker_timeout_s
        )
        rasters, detected, holes, fills = _run_stages(runner, plan, config, staging, timer, water_area)
    cluster_scope.close()
    return _publish(
        staging, (plan, config, rasters, detected, holes, fills), started, timer, runner, keep_work=keep_work
    )


def _finish_commit(staging: Staging) -> RunSummary:
    """Finish the commit of an interrupted run whose products were all written; its manifest is the summary."""
    try:
        staging.finish_commit()
    except BaseException:
        staging.keep_for_resume()
        raise
    logger.info("%s: the interrupted run's result was complete; moved into place", staging.out)
    manifest = json.loads((staging.out / "manifest.json").read_text())
    return RunSummary.from_manifest(manifest, str(staging.out))


def _discard(staging: Staging, created_out: bool) -> None:
    """A failed run leaves nothing: its staging folder, and OUT when this run made it (and it is empty)."""
    staging.remove()
    if created_out:
        with contextlib.suppress(OSError):
            staging.out.rmdir()  # only if still empty


def _publish(
    staging: Staging, results: tuple, started: float, timer: _StageTimer, runner: _Runner, *, keep_work: bool
) -> RunSummary:
    """Write the products into the staging folder and move them into OUT, the manifest last."""
    plan, config, rasters, detected, holes, fills = results
    try:
        summary = _write_products(staging, plan, config, rasters, detected, holes, fills, started, timer, runner)
    except OSError as e:
        if disk_full(e, staging.root):
            raise _disk_full_error(staging, "the products") from None
        raise
    flight_files = tuple(os.path.basename(f) for f in summary.flightplan.get("files", []))
    interrupt.begin_commit()  # a TERM from here on is ignored: the run completes (exit 0)
    staging.commit(PRODUCTS + flight_files, keep_work=keep_work, replaces=FLIGHTPLAN_PRODUCTS)
    return summary


def _run_stages(runner: _Runner, plan: SurveyPlan, config: Config, staging: Staging, timer: _StageTimer, water_area):
    """Every stage that runs on the workers, in order; returns their gathered results."""
    filling = config.holes.enabled and config.fill.enabled
    rasters = _run_rasters(runner, plan, config, staging, timer, write=not filling)
    detected, holes, fills = None, None, None
    if config.holes.enabled:
        detected, holes = _run_holes(runner, plan, config, rasters, water_area, staging)
        timer.lap("holes")
    if holes is not None and filling:
        fills = _run_fill(runner, plan, config, holes, rasters, staging)
        timer.lap("fill")
    if fills is not None and config.output.points:
        rasters.points = _run_points(runner, plan, config, rasters, staging)
        timer.lap("points")
    return rasters, detected, holes, fills


# -- stages ---------------------------------------------------------------------------


def _water(water: str | os.PathLike | None, config: Config, plan: SurveyPlan) -> tuple[Any, Any]:
    """The file of known water (``--water`` or ``holes.water``) and its polygons in the survey CRS."""
    water = water or config.holes.water or None
    return water, read_survey_area(water, plan.survey.crs, what="water", within=plan.survey_area) if water else None


def _plan(
    inputs: list[str] | tuple[str, ...],
    config: Config,
    aoi: str | os.PathLike | None,
    out: Path,
    budget: MemoryBudget | None = None,
) -> SurveyPlan:
    """Scan the headers and plan the survey; an AOI off every tile's data, or a plan too large
    for memory (:mod:`pipeline.budget`), stops here.

    What the run writes into ``out`` (repaired point clouds, kept results, partial
    folders) is never read as input, also when ``out`` lies inside an input folder.
    """
    written = (out / "points", out / "work", *out.glob(f"{PARTIAL_PREFIX}*"))
    survey = scan_survey(
        inputs,
        crs=config.survey.crs,
        target_crs=config.survey.target_crs,
        on_error=config.survey.on_error,
        exclude=written,
    )
    if needs_density(config):
        survey = measure_footprint(survey)
    plan = plan_survey(survey, config, aoi=aoi)
    if not any(plan.tiles_of_cell.get(cell.id) for cell in plan.cells):  # the planned area's own cells hold none
        raise InputDataError(aoi or "INPUT", "the survey area does not overlap the data of any tile")
    if budget is not None:
        check_plan_memory(plan, config, budget)
    return plan


@dataclass
class _Rasters:
    """What stages 1, 2 and the writer return, in plan order."""

    tiles: list[TileResult]
    failed: list[dict[str, str]]
    cells: list[CellResult]
    written: list[WriteResult]
    inputs: dict[str, dict[str, Any]]  # path -> size, time and checksum
    points: list[str] = field(default_factory=list)  # the repaired point clouds (output.points)

    def add(self, result: Any) -> str:
        """File one task's result; returns its kind (``input``, ``tile``, ``cell`` or ``written``)."""
        if isinstance(result, dict):
            self.inputs[str(result["path"])] = result
            return "input"
        if isinstance(result, TileResult):
            self.tiles.append(result)
            if result.points_outside:
                logger.warning(
                    "%s: %d points lie outside the bounds its header (or, for a split COPC file, its octree nodes) declares; they were not used",
                    result.path,
                    result.points_outside,
                )
            return "tile"
        if isinstance(result, TileFailure):
            logger.warning("skipping %s: %s", result.path, result.reason)
            self.failed.append({"path": result.path, "reason": result.reason})
            return "tile"
        if isinstance(result, CellResult):
            self.cells.append(result)
            return "cell"
        self.written.append(result)
        return "written"


def _run_rasters(
    runner: _Runner, plan: SurveyPlan, config: Config, staging: Staging, timer: _StageTimer, *, write: bool
) -> _Rasters:
    """Stage 1 (per tile), stage 2 (per cell) and, with ``write``, the writer (per cell) as one graph.

    Each cell depends on the tiles touching it and has a higher priority, so it
    runs as soon as they are done, while other tiles are still decoding; when no
    later stage changes heights, its rasters are written as soon as it is merged.
    """
    tile_tasks = bin_tiles.tile_tasks(plan, config, staging)
    tile_futures = _submit_tiles(runner, tile_tasks, skip=config.survey.on_error == "skip")
    merge_recipes = merge_cells.merge_tasks(plan, tile_tasks, staging)
    tile_tasks_by_index = {task.read_index: task for task in tile_tasks}
    merge_futures = {
        task.cell.id: runner.submit(
            merge_cells.merge_cell,
            task,
            *(tile_futures[i] for i in touching),
            label=f"cell {task.cell.id} (merge)",
            key=merge_cells.merge_key(task, [tile_tasks_by_index[i] for i in touching]),
            priority=1,
            adopt=partial(merge_cells.adopt_result, task),
        )
        for task, touching in merge_recipes
    }
    record_futures = _submit_checksums(runner, tile_tasks)
    write_futures = [
        runner.submit(
            write_rasters.write_cell_rasters,
            task,
            merge_futures[task.cell.id],
            label=f"cell {task.cell.id} (write rasters)",
            key=f"write-{task.cell.id}",
            priority=2,
        )
        for task in (write_rasters.write_tasks(plan, config, list(merge_futures), staging) if write else [])
    ]
    results = _Rasters([], [], [], [], {})
    bars = {
        "input": runner.bar.add("checksums", total=len(record_futures)),
        "tile": runner.bar.add("decode + bin tiles", total=len(tile_futures)),
        "cell": runner.bar.add("merge cells", total=len(merge_futures)),
        "written": runner.bar.add("write rasters", total=len(write_futures)),
    }

    def collect(result: Any) -> None:
        kind = results.add(result)
        runner.bar.advance(bars[kind], points=result.points_read if isinstance(result, TileResult) else 0)
        if kind == "tile" and len(results.tiles) + len(results.failed) == len(tile_futures):
            timer.lap("rasterize")

    runner.gather([*tile_futures.values(), *merge_futures.values(), *write_futures, *record_futures], collect)
    timer.lap("merge_tail")
    _check_points_left(results, config)
    results.tiles = bin_tiles.results_by_file(results.tiles)
    results.failed = list({f["path"]: f for f in results.failed}.values())  # a split file's failed tasks: once
    for empty in (r for r in results.tiles if not r.points_used):  # listed and warned like a skipped tile
        reason = f"no point used: none of its {empty.points_read:,} points passes the filter ([filter])"
        logger.warning("skipping %s: %s", empty.path, reason)
        results.failed.append({"path": empty.path, "reason": reason})
    order = {cell.id: i for i, cell in enumerate(plan.cells)}
    results.cells.sort(key=lambda r: order[r.cell_id])
    results.written.sort(key=lambda r: order[r.cell_id])
    return results


def _submit_tiles(runner: _Runner, tile_tasks: list[bin_tiles.TileTask], *, skip: bool) -> dict[int, Any]:
    """Stage 1: one task per read task (a split COPC file's cell tasks wait for its top task), by read index."""
    tile_function = bin_tiles.rasterize_tile_or_skip if skip else bin_tiles.rasterize_tile
    tile_futures: dict[int, Any] = {}
    tops: dict[int, Any] = {}
    for task in tile_tasks:  # top tasks come first
        tile_futures[task.read_index] = runner.submit(
            tile_function,
            task,
            *([tops[task.tile_index]] if task.role == "cell" and task.tile_index in tops else []),
            label=f"tile {task.path}" + (f" (COPC read task {task.part})" if task.part else ""),
            key=f"rasterize-{Path(task.output_dir).name}",
            priority=3 if task.role == "top" else 0,
            adopt=partial(bin_tiles.adopt_result, task),
        )
        if task.role == "top":
            tops[task.tile_index] = tile_futures[task.read_index]
    return tile_futures


def _submit_checksums(runner: _Runner, tile_tasks: list[bin_tiles.TileTask]) -> list[Any]:
    """Each input file's size, time and SHA-256 for the manifest: once per file, after its decoding."""
    return [
        runner.submit(
            input_record,
            task.path,
            label=f"tile {task.path} (checksum)",
            key=f"sha256-{Path(task.output_dir).name}",
            priority=-1,  # after the decoding, which the file is then cached for
        )
        for task in tile_tasks
        if task.role in ("whole", "top")  # once per file, also when a COPC file is split
    ]


def _check_points_left(results: _Rasters, config: Config) -> None:
    """Stop with one line when no tile could be decoded or the filter left no point."""
    if not results.tiles:
        raise InputDataError("INPUT", "no tile could be decoded: every tile failed")
    if not any(r.points_used for r in results.tiles):
        f = config.filter
        raise InputDataError(
            "INPUT",
            f"no point is left after filtering (filter.keep_classes = {f.keep_classes}, "
            f"filter.drop_classes = {f.drop_classes}, filter.drop_withheld = {str(f.drop_withheld).lower()})",
        )


def _run_holes(runner: _Runner, plan: SurveyPlan, config: Config, rasters: _Rasters, water, staging: Staging):
    """Detection (per cell) on the footprint gathered from stage 2, then linking on the client.

    Where the flight lines' trajectories account for the survey's points, their swaths and
    lines of sight replace the bands of pixels between which coverage gaps were sought.
    """
    params = plan.hole_params
    cells = rasters.cells
    blocks = merge_cells.footprint_blocks(cells, plan, config)
    line_moments = merge_cells.survey_line_moments(cells)
    geometry, sight = detect_holes.sensor_inputs(rasters.tiles, cells, plan, config)
    # with the swaths known, no coverage gap is sought between the bands of the lines' pixels
    bands = line_moments[:0] if sight is not None else line_moments
    gaps = detect_holes.with_tile_grid(plan, merge_cells.survey_coverage_gaps(bands))
    gaps = _void_gaps(runner, plan, cells, gaps)
    tasks = detect_holes.detect_tasks(plan, params, cells, blocks, water, staging, gaps, sight)
    futures = [
        runner.submit(
            detect_holes.detect_cell, task, label=f"cell {task.cell.id} (find holes)", key=f"detect-{task.cell.id}"
        )
        for task in tasks
    ]
    detected: list[detect_holes.DetectResult] = runner.gather_all(futures, "find holes")
    order = {r.cell_id: i for i, r in enumerate(cells)}
    detected.sort(key=lambda d: order[d.cell_holes.cell.id])
    holes = link_holes.link_cells(detected, plan, config, params, line_moments, geometry)
    link_holes.keep_hole_set(holes, str(staging.hole_catalog))
    return detected, holes


def _void_gaps(runner: _Runner, plan: SurveyPlan, cells: list[CellResult], gaps: CoverageGaps) -> CoverageGaps:
    """The coverage gaps and extent strips empty beside measured flanks: a pass over the cells' counts, if any."""
    logger.debug("flight-line bands %s; coverage gaps %s", gaps.bands, gaps.gaps)
    if not (gaps.gaps or gaps.extent_strips):
        return gaps
    digest = hashlib.sha1(repr((gaps.gaps, gaps.extent_strips)).encode()).hexdigest()[:12]
    futures = [
        runner.submit(
            merge_cells.count_gap_voids,
            task,
            label=f"cell {task.cell_id} (check gaps)",
            key=f"gaps-{digest}-{task.cell_id}",
        )
        for task in merge_cells.gap_void_tasks(cells, plan, gaps)
    ]
    counts = runner.gather_all(futures, "check coverage gaps")
    kept = merge_cells.survey_void_gaps(gaps, counts)
    logger.debug(
        "coverage gaps: %d of %d, extent strips: %d of %d empty beside measured flanks, kept",
        len(kept.gaps),
        len(gaps.gaps),
        len(kept.extent_strips),
        len(gaps.extent_strips),
    )
    return kept


def _run_fill(
    runner: _Runner, plan: SurveyPlan, config: Config, holes: link_holes.HoleSet, rasters: _Rasters, staging: Staging
) -> list[HoleFill]:
    """Fill (per cell owning holes), then the writer (per cell) painting the fills into the rasters."""
    survey = plan.survey
    params = fill_params(
        config,
        plan.hole_params,
        pixel_size=plan.grid.resolution,
        horizontal_unit_m=survey.horizontal_unit_m,
        vertical_unit_m=survey.vertical_unit_m,
    )
    merged = [r.cell_id for r in rasters.cells]
    sources = fill_holes.cell_sources(plan, holes, staging, merged)
    tasks, fills = fill_holes.fill_tasks(plan, config, holes, sources, params, staging)
    futures = [
        runner.submit(
            fill_holes.fill_cell_holes, task, label=f"cell {task.owner_cell} (fill)", key=f"fill-{task.owner_cell}"
        )
        for task in tasks
    ]
    for cell_fills_of_task in runner.gather_all(futures, "fill holes"):
        fills.extend(cell_fills_of_task)
    fills.sort(key=lambda f: f.hole_id)
    cell_fills = write_rasters.cell_fills(plan, holes, sources, fills, params)
    write_futures = [
        runner.submit(
            write_rasters.write_cell_rasters,
            task,
            label=f"cell {task.cell.id} (write rasters)",
            key=f"write-{task.cell.id}",
        )
        for task in write_rasters.write_tasks(plan, config, merged, staging, cell_fills)
    ]
    rasters.written += runner.gather_all(write_futures, "write rasters")
    order = {cell.id: i for i, cell in enumerate(plan.cells)}
    rasters.written.sort(key=lambda r: order[r.cell_id])
    return fills


def _run_points(runner: _Runner, plan: SurveyPlan, config: Config, rasters: _Rasters, staging: Staging) -> list[str]:
    """The repaired point clouds (per tile read), after the writer: the fill points come from its rasters."""
    futures = [
        runner.submit(
            write_points.write_tile_points,
            task,
            label=f"tile {task.path} (write points)",
            key=f"points-{Path(task.target).stem}",
        )
        for task in write_points.points_tasks(plan, config, rasters.tiles, rasters.written, staging)
    ]
    results: list[write_points.PointsResult] = runner.gather_all(futures, "write point clouds")
    return write_points.gather_points(results, rasters.written, staging.root)


def _write_products(
    staging: Staging,
    plan: SurveyPlan,
    config: Config,
    rasters: _Rasters,
    detected,
    holes,
    fills,
    started,
    timer,
    runner: _Runner,
) -> RunSummary:
    """The mosaic, the layers, the manifest and the report, from the stages' kept results."""
    t0 = time.perf_counter()
    skipped = plan.survey.skipped + rasters.failed
    write_mosaics(staging, plan, rasters.written)
    gpkg = staging.product("holes.gpkg")
    write_survey_layers(gpkg, plan, rasters.tiles, rasters.cells, rasters.written, skipped)
    hole_summary = (
        write_hole_layers(gpkg, plan, config, holes, detected, fills, rasters.written) if holes is not None else {}
    )
    vrt = staging.product("dsm.vrt")
    flight_summary: dict[str, Any] = {}
    heights = sum((r.ground for r in rasters.tiles), GroundLevel())
    if holes is not None and config.flightplan.enabled and vrt.exists():
        if heights.normalised:  # safe heights need the terrain, which these heights have taken out
            flight_summary = {"not_planned": NO_TERRAIN} if hole_summary.get("listed") else {}
        else:
            # home: flightplan.home, else the open ground nearest to the holes, from the ground points
            points = [] if plan.survey.reproject else [t.path for t in plan.survey.tiles]
            try:
                flight_summary = plan_flights(gpkg, vrt, config, staging.root, point_files=points)
            except InputDataError as e:  # the survey's products stand; only the re-flight cannot be planned
                flight_summary = {"not_planned": e.reason}
        timer.lap("flightplan")
    summary = RunSummary(
        flightplan=flight_summary,
        resumed_tasks=runner.resumed_tasks,
        reused_tasks=runner.reused_tasks,
        holes=hole_summary,
        out_dir=str(staging.out),
        tiles=len(rasters.tiles),
        cells=len(rasters.cells),
        points_read=sum(r.points_read for r in rasters.tiles),
        points_used=sum(r.points_used for r in rasters.tiles),
        points_outside=sum(r.points_outside for r in rasters.tiles),
        seconds=time.perf_counter() - started,
        stage_seconds=timer.seconds,
        skipped=skipped,
        dsm_tiles=sorted(os.path.relpath(r.paths["dsm"], staging.root) for r in rasters.written if r.paths),
        point_files=rasters.points,
        heights=heights.as_record(),
    )
    timer.seconds["outputs"] = time.perf_counter() - t0
    products = [name for name in PRODUCTS if name not in ("manifest.json", "report.html")]
    products += [os.path.basename(f) for f in flight_summary.get("files", [])]
    manifest = write_manifest(
        staging.product("manifest.json"),
        summary,
        plan,
        config,
        rasters.tiles,
        rasters.cells,
        inputs=rasters.inputs,
        outputs=output_records(staging.root, products),
    )
    write_report(
        staging.product("report.html"), manifest, summary.holes.get("largest", []), inputs=_report_map(staging)
    )
    timer.lap("report")
    return summary


def _report_map(staging: Staging) -> ReportInputs | None:
    """What the report's map shows, read from the staged products; a map that cannot be made is left out."""
    try:
        return read_report_inputs(staging.root)
    except Exception as e:  # the report is for reading; it must never cost the run
        logger.warning("report.html without its map: %s", e)
        return None


# -- Dask -----------------------------------------------------------------------------


class _Runner:
    """Submits tasks and gathers their results: the one place every stage goes through.

    Results arrive in completion order; the first failure cancels every future of
    the batch. A :class:`~pipeline.errors.HolefillError` raised by a worker (a bad
    tile) reaches the user as it is; any other exception becomes one
    :class:`~pipeline.errors.TaskError` line naming the task's tile or cell.
    """

    def __init__(
        self,
        client: Any,
        bar: _Progress,
        staging: Staging | None = None,
        *,
        retries: int = 0,
        no_worker_timeout_s: float = 60.0,
    ) -> None:
        self.client = client
        self.retries = retries
        self.no_worker_timeout_s = no_worker_timeout_s
        self.bar = bar
        self.staging = staging
        self.resumed_tasks = 0
        self.reused_tasks = 0  # taken from the previous run (incremental)
        self._run_id = uuid.uuid4().hex[:8]
        self._labels: dict[Any, str] = {}

    def submit(
        self,
        function: Callable,
        *args: Any,
        label: str,
        key: str,
        priority: int = 0,
        adopt: Callable[[Any], Any] | None = None,
    ) -> Any:
        """Submit one task; with a staging folder its result is kept under ``key`` for a resumed run.

        In a resumed run, a task whose result was kept is not run again: a
        :class:`_Kept` stands in for its future (as an argument of later tasks too).
        In an incremental run, so does the previous run's result of the same key,
        passed through ``adopt`` (which points it at this run's files and indices).
        """
        args = tuple(a.value if isinstance(a, _Kept) else a for a in args)
        if self.staging is None:
            future = self.client.submit(
                function, *args, pure=False, priority=priority, retries=self.retries, key=f"{key}-{self._run_id}"
            )
        else:
            kept = self.staging.task_result(key)
            if (found := self.staging.kept(key)) is not None:
                value, how = found
                if how == "resumed":
                    self.resumed_tasks += 1
                else:
                    self.reused_tasks += 1
                    value = adopt(value) if adopt is not None else value
                return _Kept(value)
            future = self.client.submit(
                run_and_keep,
                function,
                str(kept),
                *args,
                pure=False,
                priority=priority,
                retries=self.retries,
                key=f"{key}-{self._run_id}",
            )
        self._labels[future.key] = label
        return future

    def gather(self, futures: list[Any], collect: Callable[[Any], None]) -> None:
        from distributed import as_completed

        pending = [f for f in futures if not isinstance(f, _Kept)]
        try:
            for kept in futures:
                if isinstance(kept, _Kept):
                    collect(kept.value)
            with WorkerWatch(self.client, pending, self.no_worker_timeout_s) as watch:
                for future in as_completed(pending):
                    try:  # a result held by a dead worker is computed again: that waits for a worker too
                        result = self._result(future)
                    except TaskError:
                        if watch.lost:
                            raise watch.error() from None
                        raise
                    if watch.lost:
                        raise watch.error()
                    collect(result)
        except BaseException:
            self.client.cancel(pending)
            raise

    def gather_all(self, futures: list[Any], bar_label: str) -> list[Any]:
        """Every result, in completion order, with a progress bar ``bar_label``."""
        handle = self.bar.add(bar_label, total=len(futures))
        results: list[Any] = []

        def collect(result: Any) -> None:
            results.append(result)
            self.bar.advance(handle)

        self.gather(futures, collect)
        return results

    def _result(self, future: Any) -> Any:
        try:
            return future.result()
        except HolefillError:
            raise
        except Exception as e:  # a worker's unforeseen failure: one line, naming the task
            label = self._labels.get(future.key, str(future.key))
            if self.staging is not None and isinstance(e, OSError) and disk_full(e, self.staging.root):
                raise _disk_full_error(self.staging, label) from None
            raise TaskError(label, e) from None


@dataclass(frozen=True)
class _Kept:
    """The result of a task that an interrupted run finished: stands in for its future."""

    value: Any


def _disk_full_error(staging: Staging, writing: str) -> DiskFullError:
    return DiskFullError(
        f"{staging.out}: no space left on the device (while writing: {writing}); free some space and run "
        "again with --resume: the finished tasks are kept"
    )


def _holds_result_of(out: Path, config: Config) -> bool:
    """Whether ``out`` holds a complete result of this configuration (an incremental run's base)."""
    try:
        manifest = json.loads((out / "manifest.json").read_text())
    except (OSError, ValueError):
        return False
    return bool(manifest.get("complete")) and manifest.get("config_key") == config_key(config)


def run_key(plan: SurveyPlan, config: Config, aoi: Any, water: Any) -> str:
    """What a run is made of: inputs (path, size, time), AOI and water files, configuration, version.

    Only a partial folder of the same key is resumed; the Dask settings do not count.
    """
    parts = [__version__, {k: v for k, v in to_dict(config).items() if k != "dask"}]
    parts += [input_fingerprint(t.path) for t in plan.survey.tiles]
    parts += [input_fingerprint(str(p)) if p else "" for p in (aoi, water)]
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]
