"""Running a survey on Dask: the only module that builds Dask graphs (the client comes from :mod:`pipeline.cluster`).

A run is: scan headers -> plan (grid, cells, tile-to-cell index) -> the stages
-> products. Each stage is one record (:class:`pipeline.stages.stage.Stage`:
recipe builder, worker, key, label, gather) in its module of ``pipeline.stages``,
and :data:`pipeline.stages.registry.STAGES` lists them in order; this module only
walks that list: it submits each stage's tasks with their dependencies, gathers
their results, shows progress, and turns a worker's unexpected exception into one
line naming its tile or cell. The stages' results reach :mod:`pipeline.outputs` as
one frozen record (:class:`~pipeline.stages.registry.RunResults`). Every product is
written into a staging folder inside OUT and moved into place only when the whole
run has succeeded (``pipeline.staging``).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, TypedDict, Unpack

from . import __version__, interrupt
from .budget import MemoryBudget, check_plan_memory, memory_budget
from .cluster import ClusterStart, WorkerWatch, dask_client, quiet_shutdown, task_stream
from .config import Config, config_key, to_dict
from .errors import ClusterError, DiskFullError, HolefillError, InputDataError, TaskError
from .gc_pause import collector_paused
from .io.checksums import output_records
from .io.vector import read_survey_area
from .output_guard import check_before_run, check_same_survey
from .outputs import (
    FLIGHTPLAN_PRODUCTS,
    PRODUCTS,
    RunSummary,
    run_summary,
    with_wall_counts,
    write_layers,
    write_manifest,
    write_wall_layers,
)
from .plan import SurveyPlan, needs_density, plan_survey, plan_with_footprint
from .progress import ProgressBars as _Progress
from .progress import StageTimer as _StageTimer
from .report import ReportInputs, prepare_maps, with_route, write_report
from .stages.bin_tiles import BIN_TILES, TileResult
from .stages.registry import STAGES, RunResults, run_results
from .stages.stage import Dependency, RunState, Stage
from .staging import PARTIAL_PREFIX, Staging, disk_full, input_fingerprint, run_and_keep
from .survey.blocks import FootprintDensity
from .survey.footprint_density import footprint_from_counts, measure_footprint
from .survey.ground_level import NO_TERRAIN
from .survey.scan import scan_survey

logger = logging.getLogger(__name__)


class RunOptions(TypedDict, total=False):
    """The keyword options of :func:`run_survey` (all optional; see its docstring)."""

    scheduler: str | None
    client: Any
    aoi: str | os.PathLike | None
    water: str | os.PathLike | None
    progress: bool
    resume: bool
    overwrite: bool
    incremental: bool
    cluster: ClusterStart | None


def run_survey(
    inputs: list[str] | tuple[str, ...], out_dir: str | os.PathLike, config: Config, **options: Unpack[RunOptions]
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
    client, scheduler, aoi = options.get("client"), options.get("scheduler"), options.get("aoi")
    resume, overwrite = options.get("resume", False), options.get("overwrite", False)
    incremental = options.get("incremental", False)
    check_before_run(out, config_key(config), overwrite=overwrite)
    timer = _StageTimer(started)
    with contextlib.ExitStack() as cluster_scope:
        connect = cluster_scope.enter_context(dask_client(client, scheduler, config, start=options.get("cluster")))
        budget = memory_budget(config, scheduler=scheduler if client is None else "client")
        plan = _plan(inputs, config, aoi, out, budget)  # the headers are scanned while the workers start
        check_same_survey(out, [t.path for t in plan.survey.tiles], overwrite=overwrite or resume)
        water, water_area = _water(options.get("water"), config, plan)
        timer.lap("scan")
        created_out = not out.exists()
        reuse = incremental and _holds_result_of(out, config)
        staging = Staging.create(out, run_key=run_key(plan, config, aoi, water), resume=resume, incremental=reuse)
        if staging.resumed and staging.commit_pending:  # the interrupted run had finished: move it into place
            cluster_scope.close()
            return _finish_commit(staging)
        if plan.density_pending and (footprint := staging.kept_footprint()) is not None:
            plan = plan_with_footprint(plan, footprint, config, aoi=aoi)  # the interrupted run had counted it
        settle = partial(settle_density, aoi=aoi, budget=budget)
        try:
            summary = _run_and_publish(
                connect, cluster_scope, staging, plan, config, (started, timer), water_area,
                progress=options.get("progress", False), keep_work=config.output.keep_intermediate or incremental,
                settle=settle,
            )  # fmt: skip
        except (KeyboardInterrupt, SystemExit, TaskError, DiskFullError, ClusterError) as stop:
            # interrupted, or the cluster lost a worker for good: finished tasks stay for --resume
            interrupt.acknowledge()  # a second TERM must not cut the unlock short
            if isinstance(stop, (KeyboardInterrupt, SystemExit)):
                quiet_shutdown()
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
    settle: Callable[..., RunState] | None = None,
) -> RunSummary:
    """Every stage on the workers, then, the workers stopped (their memory freed), the products.

    The products that do not wait for a deferred stage (the walls) are written while the
    workers run it (:func:`_write_first_products`): the mosaics, the layers of the holes, the
    flight plans and the report's maps. The client planned the flights after the walls' last
    tasks, with the workers idle; where a core is free of them now (one worker on two cores, the
    42 M-point bench survey) the run's last three laps went from 5.1-5.4 s to 3.7-4.3 s.
    ``settle`` (:func:`settle_density`) sees the state after stage 1; where the density it
    counted changes the grid, the stages run again on the new plan, from a clean work folder.
    """
    started, timer = clock
    first: list[_FirstProducts] = []

    def while_deferred_run(state: RunState) -> None:
        first.append(_write_first_products(staging, state.plan, config, run_results(state), timer))

    with _Progress(progress) as bar:
        runner = _Runner(
            connect(), bar, staging, retries=config.dask.retries, no_worker_timeout_s=config.dask.no_worker_timeout_s
        )
        with task_stream(runner.client) as stream:
            try:
                state = _run_stages(
                    runner, RunState(plan, config, staging, water_area), timer,
                    settle=settle, while_deferred_run=while_deferred_run,
                )  # fmt: skip
            except _PlanAgain as again:
                logger.info(
                    "the data footprint is denser than the tile boxes: pixel size %g m, not %g m; decoding again",
                    again.plan.sizing.resolution_m,
                    plan.sizing.resolution_m,
                )
                staging.start_again(again.footprint)
                runner.start_again()
                state = _run_stages(
                    runner, RunState(again.plan, config, staging, water_area), timer,
                    while_deferred_run=while_deferred_run,
                )  # fmt: skip
    timer.tasks = runner.worker_seconds(stream.data)
    cluster_scope.close()
    results = run_results(state, resumed_tasks=runner.resumed_tasks, reused_tasks=runner.reused_tasks)
    return _publish(
        staging, state.plan, config, results, clock, keep_work=keep_work, first=first[-1] if first else None
    )


class _PlanAgain(Exception):
    """Stage 1's count of the footprint changed the grid: the run starts again on ``plan``."""

    def __init__(self, plan: SurveyPlan, footprint: FootprintDensity) -> None:
        super().__init__("the grid changed after stage 1")
        self.plan, self.footprint = plan, footprint


def count_footprint(plan: SurveyPlan, results: list[Any]) -> FootprintDensity | None:
    """The density stage 1 counted on the data footprint, from its read tasks' block counts
    (:mod:`pipeline.survey.footprint_density`); None where the plan needs none.

    Added up block by block, so the same whatever the order or the split of the tasks.
    """
    if not plan.density_pending:
        return None
    parts = [r.pulse_blocks for r in results if isinstance(r, TileResult) and r.pulse_blocks is not None]
    return footprint_from_counts(plan.survey, parts, time.perf_counter(), how="counted in stage 1")


def settle_density(
    state: RunState,
    *,
    aoi: str | os.PathLike | None,
    budget: MemoryBudget | None = None,
    footprint: FootprintDensity | None = None,
) -> RunState:
    """After stage 1 of a plan sized by the headers' density: the density stage 1 counted on the
    data footprint (``footprint``, else :func:`count_footprint` of the gathered tiles), and the
    plan it gives. The same pixel and cell sizes: the run goes on with the settled plan (its hole
    parameters and local densities from the footprint); others: :class:`_PlanAgain`.
    """
    plan = state.plan
    if not plan.density_pending:
        return state
    decoded = state[BIN_TILES]
    if footprint is None:
        footprint = count_footprint(plan, list(decoded.tiles))
    assert footprint is not None
    settled = plan_with_footprint(plan, footprint, state.config, aoi=aoi)
    if settled.grid != plan.grid:
        if budget is not None:
            check_plan_memory(settled, state.config, budget)
        raise _PlanAgain(settled, footprint)
    # the files' counts are in the footprint now: the client keeps one copy, not two
    counted = dataclasses.replace(
        decoded, tiles=tuple(dataclasses.replace(t, pulse_blocks=None) for t in decoded.tiles)
    )
    return dataclasses.replace(state.with_result(BIN_TILES, counted), plan=settled)


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
    staging: Staging,
    plan: SurveyPlan,
    config: Config,
    results: RunResults,
    clock: tuple[float, _StageTimer],
    *,
    keep_work: bool,
    first: _FirstProducts | None = None,
) -> RunSummary:
    """Write the products into the staging folder and move them into OUT, the manifest last.

    ``first``: the products already written while a deferred stage ran (else written here).
    """
    with _writing_products(staging):
        if first is None:
            first = _write_first_products(staging, plan, config, results, clock[1])
        summary = _write_products(staging, plan, config, results, clock, first)
    flight_files = tuple(os.path.basename(f) for f in summary.flightplan.get("files", []))
    interrupt.begin_commit()  # a TERM from here on is ignored: the run completes (exit 0)
    staging.commit(PRODUCTS + flight_files, keep_work=keep_work, replaces=FLIGHTPLAN_PRODUCTS)
    return summary


def _run_stages(
    runner: _Runner,
    state: RunState,
    timer: _StageTimer,
    *,
    settle: Callable[..., RunState] | None = None,
    while_deferred_run: Callable[[RunState], None] | None = None,
) -> RunState:
    """Walk the stages (:data:`pipeline.stages.registry.STAGES`) in order; returns the run state they gathered.

    A stage that streams is submitted with the next one and gathered in the same loop
    (its tasks are their dependencies); a stage without a worker runs on the client.
    A deferred stage is submitted when reached and gathered after all the others: its
    tasks (at a low priority) keep the workers busy while the client works.
    ``settle`` sees the state once stage 1's batch is gathered (:func:`settle_density`);
    ``while_deferred_run`` sees the state of every stage but the deferred ones, before
    they are gathered (only where some were submitted).
    """

    def close(state: RunState, batch: list[tuple[Stage, list[Any]]], submitted: dict[Dependency, Any]) -> RunState:
        decoding = any(stage is BIN_TILES for stage, _ in batch)
        if decoding:
            _import_for_products(state.config)
        # the footprint is counted as soon as stage 1's tiles are in, while the workers merge
        # and write the last cells (0.3-0.5 s of the client's, which came after them)
        counted: list[FootprintDensity | None] = []
        plan = state.plan
        when_gathered = {BIN_TILES.name: lambda results: counted.append(count_footprint(plan, results))}
        state = _gather_batch(runner, state, batch, timer, when_gathered if settle is not None and decoding else None)
        if settle is not None and decoding:
            state = settle(state, footprint=counted[0] if counted else None)
        return state

    batch: list[tuple[Stage, list[Any]]] = []
    deferred: list[tuple[Stage, list[Any]]] = []
    submitted: dict[Dependency, Any] = {}
    for stage in STAGES:
        if not stage.runs(state):
            continue
        if batch and (stage.deferred or stage.worker is None):  # it reads what the open batch gathers
            state, batch, submitted = close(state, batch, submitted), [], {}
        if stage.deferred:
            deferred.append((stage, _submit_stage(runner, stage, state, {})))
            continue
        if stage.worker is None:
            state = state.with_result(stage, stage.gather(state, []))
            if stage.lap:
                timer.lap(stage.lap)
            continue
        batch.append((stage, _submit_stage(runner, stage, state, submitted)))
        if not stage.streams:
            state, batch, submitted = close(state, batch, submitted), [], {}
    if batch:
        state = close(state, batch, submitted)
    if deferred and while_deferred_run is not None:
        while_deferred_run(state)
    for stage_futures in deferred:
        state = _gather_batch(runner, state, [stage_futures], timer)
    return state


def _import_for_products(config: Config) -> None:
    """Import what only the client's last steps need, while the workers decode stage 1.

    The GeoPackage writer (pyogrio, which imports pandas and geopandas: 0.5-0.7 s) and, where
    flights are planned, the planner (0.5 s) and numba's code generator, which the planner's
    kernels (lines of sight, the take-off search) are the client's first to need (0.3-0.5 s
    at the first kernel, as in :mod:`pipeline.worker_start`). Imported at the start they held
    back the first tasks (the client's imports were the start's longest path); imported where
    they are used they lengthened the run's tail, when the workers are done. The client's main
    thread only waits for results meanwhile.
    """
    with collector_paused():  # pipeline.gc_pause
        import pyogrio  # noqa: F401

        if config.plans_flights:
            from numba.core.registry import cpu_target

            from . import flight_planning  # noqa: F401

            cpu_target.target_context.refresh()


def _submit_stage(runner: _Runner, stage: Stage, state: RunState, submitted: dict[Dependency, Any]) -> list[Any]:
    """Submit a stage's tasks, each with the results of the tasks it comes ``after`` as arguments."""
    worker = stage.worker
    assert worker is not None, f"{stage.name} runs on the client"
    futures = []
    for task in stage.recipes(state):
        future = runner.submit(
            worker,
            task,
            *(submitted[dependency] for dependency in stage.after(task)),
            label=stage.label(task),
            key=stage.key(task),
            priority=stage.priority(task),
            adopt=None if stage.adopt is None else partial(stage.adopt, task),
            stage=stage.name,
        )
        submitted[(stage.name, stage.ident_of(task))] = future
        futures.append(future)
    return futures


def _gather_batch(
    runner: _Runner,
    state: RunState,
    batch: list[tuple[Stage, list[Any]]],
    timer: _StageTimer,
    when_gathered: dict[str, Callable[[list[Any]], None]] | None = None,
) -> RunState:
    """Gather the stages submitted together in one loop (one progress bar each), then each stage's gather step.

    A stage that streams into the next takes its lap as its last result arrives, and
    ``when_gathered[stage name]`` sees its results then, while the next stage's tasks run;
    the batch's last stage takes its lap after the gather steps.
    """
    when_gathered = when_gathered or {}
    bars = [runner.bar.add(stage.bar, total=len(futures)) for stage, futures in batch]
    found: list[list[Any]] = [[] for _ in batch]
    owner = [k for k, (_, futures) in enumerate(batch) for _ in futures]

    def collect(index: int, result: Any) -> None:
        k = owner[index]
        stage, futures = batch[k]
        points = stage.on_result(result) if stage.on_result is not None else 0
        found[k].append(result)
        runner.bar.advance(bars[k], points=points)
        if len(found[k]) == len(futures):
            if stage.streams and stage.lap:
                timer.lap(stage.lap)
            if stage.name in when_gathered:
                when_gathered[stage.name](found[k])

    runner.gather_indexed([future for _, futures in batch for future in futures], collect)
    for (stage, _), results in zip(batch, found):
        state = state.with_result(stage, stage.gather(state, results))
    last = batch[-1][0]
    if last.lap and not last.streams:
        timer.lap(last.lap)
    return state


# -- the plan -------------------------------------------------------------------------


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
    # The density on the data footprint: counted by stage 1 as it decodes (the plan is sized by the
    # headers' density meanwhile, and settled after stage 1: settle_density); PDAL's points are the
    # user's pipeline's, so that reader's runs count the files' own points in a pre-pass first.
    pending = needs_density(config) and config.read.reader != "pdal"
    if needs_density(config) and not pending:
        survey = measure_footprint(survey)
    plan = plan_survey(survey, config, aoi=aoi, density_pending=pending)
    if not any(plan.tiles_of_cell.get(cell.id) for cell in plan.cells):  # the planned area's own cells hold none
        raise InputDataError(aoi or "INPUT", "the survey area does not overlap the data of any tile")
    if budget is not None:
        check_plan_memory(plan, config, budget)
    return plan


@dataclass(frozen=True)
class _FirstProducts:
    """What :func:`_write_first_products` wrote: the holes' figures, the flight plans' and the report's maps."""

    holes: dict[str, Any]
    flightplan: dict[str, Any]
    maps: ReportInputs | None


@contextlib.contextmanager
def _writing_products(staging: Staging) -> Iterator[None]:
    """A full disk while the products are written: one line, the finished tasks kept for ``--resume``."""
    try:
        yield
    except OSError as e:
        if disk_full(e, staging.root):
            raise _disk_full_error(staging, "the products") from None
        raise


def _write_first_products(
    staging: Staging, plan: SurveyPlan, config: Config, results: RunResults, timer: _StageTimer
) -> _FirstProducts:
    """The products that do not need the walls: the mosaics, the other layers, the flight plans, the report's maps."""
    with _writing_products(staging):
        hole_summary = write_layers(staging, plan, config, results)
        timer.lap("outputs")  # the mosaics and the layers; the flight plan and the report lap on their own
        # the report's maps are read and drawn while the flights are planned: the DSM, the fill mask and
        # the holes are final, and GDAL, numpy and zlib work outside the GIL (1.3 s of a 2-core run's tail)
        with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="holefill-report-maps") as maps:
            prepared = maps.submit(_report_map, staging)
            flight_summary = _plan_flights(staging, plan, config, results, hole_summary, timer)
            inputs = prepared.result()
    return _FirstProducts(hole_summary, flight_summary, inputs)


def _write_products(
    staging: Staging,
    plan: SurveyPlan,
    config: Config,
    results: RunResults,
    clock: tuple[float, _StageTimer],
    first: _FirstProducts,
) -> RunSummary:
    """The walls' layers, the manifest and the report, from the stages' kept results and the ``first`` products."""
    started, timer = clock
    hole_summary, flight_summary, inputs = first.holes, first.flightplan, first.maps
    if results.holes is not None:
        hole_summary = with_wall_counts(
            hole_summary, write_wall_layers(staging.product("holes.gpkg"), plan, results.walls)
        )
    summary = run_summary(
        results,
        plan,
        staging,
        holes=hole_summary,
        flightplan=flight_summary,
        seconds=time.perf_counter() - started,
        stage_seconds=timer.seconds,  # the same dict: the laps after this one are in the manifest's summary too
        stage_client_cpu_seconds=timer.cpu,
        worker_task_seconds=timer.tasks,
    )
    _log_profile(timer)
    products = [name for name in PRODUCTS if name not in ("manifest.json", "report.html")]
    products += [os.path.basename(f) for f in flight_summary.get("files", [])]
    manifest = write_manifest(
        staging.product("manifest.json"), summary, plan, config, results, outputs=output_records(staging.root, products)
    )
    if inputs is not None:
        inputs = with_route(inputs, staging.root)
    write_report(staging.product("report.html"), manifest, summary.holes.get("largest", []), inputs=inputs)
    timer.lap("report")
    return summary


def _log_profile(timer: _StageTimer) -> None:
    """The run's profile with ``-v``: each stage's wall and client CPU seconds, the workers' task seconds."""
    logger.info(
        "stages, wall / client CPU (s): %s",
        ", ".join(f"{name} {wall:.2f} / {timer.cpu.get(name, 0.0):.2f}" for name, wall in timer.seconds.items()),
    )
    if timer.tasks:
        logger.info(
            "worker tasks, count / compute (s): %s",
            ", ".join(f"{name} {int(v['tasks'])} / {v['seconds']:.2f}" for name, v in timer.tasks.items()),
        )


def _plan_flights(
    staging: Staging,
    plan: SurveyPlan,
    config: Config,
    results: RunResults,
    hole_summary: dict[str, Any],
    timer: _StageTimer,
) -> dict[str, Any]:
    """The re-flight plans over the repaired DSM (when holes were found and flightplan.enabled); their summary."""
    gpkg, vrt = staging.product("holes.gpkg"), staging.product("dsm.vrt")
    if results.holes is None or not config.flightplan.enabled or not vrt.exists():
        return {}
    flight_summary: dict[str, Any] = {}
    if results.ground.normalised:  # safe heights need the terrain, which these heights have taken out
        flight_summary = {"not_planned": NO_TERRAIN} if hole_summary.get("listed") else {}
    else:
        # home: flightplan.home, else the open ground nearest to the holes, from the ground points: their
        # sums stage 1 kept with the cells (parameters.ReadParams.ground), the survey's files where a cell has none
        points = [] if plan.survey.reproject else [t.path for t in plan.survey.tiles]
        # imported here: 0.5 s of modules (the planner, its file formats) a run without holes never needs
        from .flight_planning import plan_flights
        from .io.flightplan_files import CellGround

        cells = tuple((str(staging.cell_statistics(cell.id)), cell.window) for cell in plan.cells)
        kept = CellGround(cells, plan.grid.transform)
        try:
            flight_summary = plan_flights(gpkg, vrt, config, staging.root, point_files=points, cell_ground=kept)
        except InputDataError as e:  # the survey's products stand; only the re-flight cannot be planned
            flight_summary = {"not_planned": e.reason}
    timer.lap("flightplan")
    return flight_summary


def _report_map(staging: Staging) -> ReportInputs | None:
    """What the report's maps show but the route, read from the staged products and drawn; a map that
    cannot be made is left out."""
    try:
        return prepare_maps(staging.root)
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
        self._stage_of: dict[Any, str] = {}  # task key -> its stage's name (the workers' seconds per stage)

    def start_again(self) -> None:
        """A new run id: the tasks of a plan run again never share a key with the first try's."""
        self._run_id = uuid.uuid4().hex[:8]

    def submit(
        self,
        function: Callable,
        *args: Any,
        label: str,
        key: str,
        priority: int = 0,
        adopt: Callable[[Any], Any] | None = None,
        stage: str = "",
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
        self._stage_of[future.key] = stage
        return future

    def worker_seconds(self, task_stream: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
        """Per stage, its tasks that ran on the workers and their compute seconds, from Dask's task stream."""
        out: dict[str, dict[str, float]] = {}
        for record in task_stream:
            stage = self._stage_of.get(record.get("key"))
            if not stage:
                continue
            computed = sum(s["stop"] - s["start"] for s in record.get("startstops", ()) if s.get("action") == "compute")
            entry = out.setdefault(stage, {"tasks": 0, "seconds": 0.0})
            entry["tasks"] += 1
            entry["seconds"] += computed
        return out

    def gather(self, futures: list[Any], collect: Callable[[Any], None]) -> None:
        """Every result, in completion order (the kept ones first), to ``collect(result)``."""
        self.gather_indexed(futures, lambda _index, result: collect(result))

    def gather_indexed(self, futures: list[Any], collect: Callable[[int, Any], None]) -> None:
        """:meth:`gather`, calling ``collect(index of the future in futures, result)``."""
        from distributed import as_completed

        pending = [f for f in futures if not isinstance(f, _Kept)]
        index = {f.key: i for i, f in enumerate(futures) if not isinstance(f, _Kept)}
        try:
            for i, kept in enumerate(futures):
                if isinstance(kept, _Kept):
                    collect(i, kept.value)
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
                    collect(index[future.key], result)
        except BaseException as stop:
            if isinstance(stop, (KeyboardInterrupt, SystemExit)):
                quiet_shutdown()  # before the cancel: a gather in flight then finds its keys forgotten
            self.client.cancel(pending)
            raise

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
