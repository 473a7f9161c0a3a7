"""The ``holefill`` command line: thin commands over library functions.

Commands parse options, turn them into configuration overrides (validated once
by :func:`pipeline.config.load_config`), call one library function and map its
exceptions to exit codes in one place (:data:`EXIT_CODES`). Logging is
configured here and nowhere else.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sys
import time
from pathlib import Path

import click

from . import __version__, interrupt
from .errors import ClusterError, ConfigError, CRSError, HolefillError, InputDataError, OutputError, TaskError

#: Exit status per error class (the first matching class wins).
EXIT_CODES: tuple[tuple[type[BaseException], int], ...] = (
    (ConfigError, 2),
    (CRSError, 3),
    (InputDataError, 3),
    (OutputError, 4),
    (ClusterError, 1),
    (HolefillError, 1),
)


class _Group(click.Group):
    """Turn holefill's exceptions into one clear line on stderr and an exit status."""

    def invoke(self, ctx: click.Context):
        previous = interrupt.install()
        try:
            return super().invoke(ctx)
        except HolefillError as e:
            code = next(code for cls, code in EXIT_CODES if isinstance(e, cls))
            _note(f"holefill: error: {e}", level="error", exit_status=code, error=type(e).__name__)
            if isinstance(e, TaskError):
                _note("holefill: finished tasks are kept: run again with --resume to continue", level="error")
            ctx.exit(code)
        except KeyboardInterrupt:
            interrupt.acknowledge()
            _note(
                "holefill: interrupted; finished tasks are kept: run again with --resume to continue",
                level="error",
                exit_status=EXIT_INTERRUPTED,
            )
            ctx.exit(EXIT_INTERRUPTED)
        finally:
            # the holefill command exits now, its outcome settled: a TERM while Python shuts
            # down (Dask's atexit clean-up) must not turn it into 143
            signal.signal(signal.SIGTERM, signal.SIG_IGN if _is_the_command() else previous)


def _is_the_command() -> bool:
    """Whether this process is the ``holefill`` command (not a program or a test calling the CLI in-process)."""
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    return Path(sys.argv[0]).name == "holefill" or getattr(spec, "name", "") in ("pipeline.cli", "pipeline.__main__")


#: Exit status of a run stopped by Ctrl-C or SIGTERM (what shells and schedulers expect).
EXIT_INTERRUPTED = 130
#: Exit status of a run that wrote its outputs but skipped tiles (``--on-error skip``), listed in the manifest.
EXIT_PARTIAL = 5


class _Output:
    """How the command talks on stderr: ``-q`` keeps only errors; ``--log-format json`` writes JSON lines."""

    quiet = False
    json = False


def _note(message: str, *, level: str = "info", **fields: object) -> None:
    """One message for the user on stderr (an error, or a summary line that ``-q`` silences).

    With ``--log-format json`` it is one JSON object per line: ``time``, ``level``,
    ``message`` and the given fields, as a scheduler's log collector reads them.
    """
    if _Output.quiet and level != "error":
        return
    if _Output.json:
        record = {"time": _now(), "level": level, "logger": "holefill", "message": message, **fields}
        click.echo(json.dumps(record, default=str), err=True)
    else:
        click.echo(message, err=True)


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


class _JsonFormatter(logging.Formatter):
    """Log records as JSON lines (``--log-format json``)."""

    def format(self, record: logging.LogRecord) -> str:
        return json.dumps(
            {"time": _now(), "level": record.levelname.lower(), "logger": record.name, "message": record.getMessage()}
        )


def _configure_logging(verbose: int, quiet: int, log_format: str = "text") -> None:
    _Output.quiet = quiet > 0
    _Output.json = log_format == "json"
    level = max(logging.DEBUG, logging.WARNING - 10 * (verbose - quiet))
    logging.basicConfig(level=level, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s", force=True)
    if _Output.json:
        for handler in logging.getLogger().handlers:
            handler.setFormatter(_JsonFormatter())
    quiet_level = logging.INFO if verbose >= 2 else logging.ERROR
    # distributed installs its own handlers when imported; its configuration says at which level
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", logging.getLevelName(max(level, quiet_level)).lower())
    for noisy in ("distributed", "tornado", "asyncio", "numba", "rasterio", "pyogrio", "bokeh"):
        logging.getLogger(noisy).setLevel(max(level, quiet_level))


config_option = click.option(
    "--config", "config_path", type=click.Path(dir_okay=False), help="TOML configuration file."
)
set_option = click.option(
    "--set",
    "overrides",
    multiple=True,
    metavar="SECTION.KEY=VALUE",
    help="Override one configuration key (repeatable), e.g. --set grid.resolution_m=0.5.",
)


@click.group(cls=_Group)
@click.version_option(__version__, prog_name="holefill")
@click.option("-v", "--verbose", count=True, help="More log output (repeatable).")
@click.option("-q", "--quiet", count=True, help="Less log output (repeatable); -q: errors only.")
@click.option(
    "--log-format",
    type=click.Choice(["text", "json"]),
    default="text",
    envvar="HOLEFILL_LOG_FORMAT",
    show_default=True,
    help="json: every message and log record as one JSON object per line on stderr (for scheduled runs).",
)
def main(verbose: int, quiet: int, log_format: str) -> None:
    """Complete DSMs from airborne lidar surveys: find, explain and fill the holes."""
    _configure_logging(verbose, quiet, log_format)


@main.command()
@click.argument("inputs", nargs=-1, required=True)
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Output folder.")
@config_option
@set_option
@click.option("--scheduler", help="Address of a running Dask scheduler (default: a local cluster).")
@click.option("--workers", type=int, help="Local worker processes (dask.workers).")
@click.option("--crs", help="CRS of tiles that have none, e.g. EPSG:28992 (survey.crs).")
@click.option("--target-crs", help="Reproject every tile to this CRS while streaming (survey.target_crs).")
@click.option("--aoi", type=click.Path(dir_okay=False), help="Polygon file: the survey area.")
@click.option("--water", type=click.Path(dir_okay=False), help="Polygon file of known water (holes.water).")
@click.option("--on-error", type=click.Choice(["fail", "skip"]), help="What a bad tile does (survey.on_error).")
@click.option(
    "--reader", type=click.Choice(["laspy", "pdal"]), help="Point reader (read.reader); pdal needs python-pdal."
)
@click.option(
    "--pdal-pipeline",
    type=click.Path(dir_okay=False),
    help="JSON file of PDAL filter stages run on each tile before binning (read.pdal_pipeline; implies --reader pdal).",
)
@click.option("--progress/--no-progress", default=None, help="Progress bar (default: when stderr is a terminal).")
@click.option("--resume", is_flag=True, help="Continue an interrupted run of the same inputs and configuration.")
@click.option("--overwrite", is_flag=True, help="Replace a result of another configuration in --out.")
@click.option(
    "--incremental",
    is_flag=True,
    help="Keep stage results in OUT/work; a later --incremental run decodes only new or changed tiles.",
)
def run(
    inputs,
    out_dir,
    config_path,
    overrides,
    scheduler,
    workers,
    crs,
    target_crs,
    aoi,
    water,
    on_error,
    reader,
    pdal_pipeline,
    progress,
    resume,
    overwrite,
    incremental,
):
    """Build the DSM of a survey. INPUT may be files, folders or globs of LAS/LAZ/COPC."""
    from .cluster import ClusterStart
    from .config import load_config

    if pdal_pipeline is not None and reader is None:
        reader = "pdal"
    config = _with_options(
        load_config(config_path, overrides),
        workers=workers,
        crs=crs,
        target_crs=target_crs,
        on_error=on_error,
        reader=reader,
        pdal_pipeline=pdal_pipeline,
    )
    config = _with_pdal(config)
    for name, path in (("AOI", aoi), ("water", water)):
        if path is not None and not Path(path).exists():
            raise InputDataError(path, f"{name} file not found")
    # the workers start while the pipeline's modules are imported and the headers scanned
    starting = None if scheduler else ClusterStart.begin(config)
    summary = None
    try:
        from .run import run_survey

        summary = run_survey(
            inputs,
            out_dir,
            config,
            scheduler=scheduler,
            cluster=starting,
            aoi=aoi,
            water=water,
            progress=sys.stderr.isatty() if progress is None else progress,
            resume=resume,
            overwrite=overwrite,
            incremental=incremental,
        )
    finally:
        if starting is not None:
            try:
                starting.close()
            except KeyboardInterrupt:
                if summary is None:
                    raise
                # the result was committed before the interrupt: it stands (exit 0)
    _report(summary)
    if summary.skipped:  # outputs written, but some tiles are missing from them
        click.get_current_context().exit(EXIT_PARTIAL)


@main.command()
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Output folder.")
@click.option(
    "--size", type=click.Choice(["unit", "demo"]), default="demo", show_default=True, help="Synthetic survey preset."
)
@config_option
@set_option
@click.option("--workers", type=int, help="Local worker processes (dask.workers).")
@click.option("--scheduler", help="Address of a running Dask scheduler.")
@click.option("--progress/--no-progress", default=None, help="Progress bar (default: when stderr is a terminal).")
def demo(out_dir, size, config_path, overrides, workers, scheduler, progress):
    """Generate a synthetic survey with known holes and run the pipeline on it."""
    from .config import load_config
    from .evaluate import score_holes
    from .run import run_survey
    from .synth import generate_survey, preset, write_truth

    config = _with_options(load_config(config_path, overrides), workers=workers)
    out = Path(out_dir)
    survey_dir = out / "survey"
    _note(f"generating a synthetic survey ({size}) in {survey_dir} ...")
    synthetic = generate_survey(survey_dir / "tiles", preset(size))
    truth = write_truth(synthetic, survey_dir)
    if config.grid.resolution_m == "auto":  # the truth rasters are on the synthetic survey's grid
        config = config.replace("grid", source="demo", resolution_m=synthetic.spec.resolution)
    _note(f"{len(synthetic.tiles)} LAZ tiles, {synthetic.n_points:,} points; truth in {survey_dir}")
    summary = run_survey(
        [str(survey_dir / "tiles")],
        out,
        config,
        scheduler=scheduler,
        aoi=truth["survey_area"],
        overwrite=True,  # the demo makes its survey anew each time: its folder is its own
        progress=sys.stderr.isatty() if progress is None else progress,
    )
    _report(summary)
    score = score_holes(
        out / "holes.gpkg",
        truth["hole_cause"],
        min_area_px=_min_area_px(summary.holes["min_area_m2"], synthetic.spec.resolution),
    )
    _note(
        f"against the truth: hole IoU {score.iou:.3f}, causes right for {score.cause_correct} of "
        f"{score.holes} holes ({score.cause_accuracy:.1%})",
    )


@main.command()
@click.argument("paths", nargs=-1, metavar="OUT | SURVEY...")
@click.option(
    "--truth",
    "truth_path",
    type=click.Path(exists=True, dir_okay=False),
    help="Score the holes of the finished run OUT: raster of true hole causes (0 none, 1 occlusion, "
    "2 water, 3 missed coverage) on the run's grid.",
)
@click.option(
    "--fill",
    "fill_benchmark",
    is_flag=True,
    help="Fill benchmark: cut artificial holes into each SURVEY (a file, a folder of tiles or a quoted glob), "
    "fill them with every method and the usual alternatives, and score the fills.",
)
@click.option("--out", "out_dir", type=click.Path(file_okay=False), help="Fill benchmark: output folder.")
@click.option("--holes", "n_holes", type=click.IntRange(min=1), default=20, show_default=True, help="Holes per survey.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the hole placement.")
@click.option(
    "--model",
    type=click.Choice(["dsm", "dtm", "both"]),
    default="dsm",
    show_default=True,
    help="Surface: DSM (all classes), DTM (filter.keep_classes = [2]) or both.",
)
@click.option(
    "--methods",
    default=",".join(["default", "auto-nocause", "tin", "mls", "idw", "nearest"]),
    show_default=True,
    help="Pipeline runs, comma-separated (default is always run); also mls-nocause, idw-nocause.",
)
@click.option(
    "--alternatives",
    default="gdal_fillnodata,tin_linear,nni,laplace,grass_fillnulls",
    show_default=True,
    help="Alternatives, comma-separated; empty for none.",
)
@click.option(
    "--resolution",
    "resolution_m",
    type=click.FloatRange(min=0, min_open=True),
    help="Pixel size (m) for every survey; default: 1 m, coarser for surveys under 1 point/m2.",
)
@click.option(
    "--crs",
    "crs_items",
    multiple=True,
    metavar="[SURVEY=]CRS",
    help="CRS of files that have none, for every survey or for one by name (repeatable).",
)
@click.option("--workers", type=int, help="Local worker processes (dask.workers).")
@click.option("--scheduler", help="Address of a running Dask scheduler (default: one local cluster for all runs).")
@config_option
@set_option
def evaluate(
    paths,
    truth_path,
    fill_benchmark,
    out_dir,
    n_holes,
    seed,
    model,
    methods,
    alternatives,
    resolution_m,
    crs_items,
    workers,
    scheduler,
    config_path,
    overrides,
):
    """Score a run against truth, or benchmark the hole filling.

    \b
    holefill evaluate OUT --truth RASTER
        Score the holes of the finished run OUT (IoU, cause accuracy) as JSON.
    holefill evaluate --fill SURVEY... --out DIR [--holes N] [--seed S] [--model dsm|dtm|both]
        Cut seeded holes (2-50 m) into copies of each survey, run the pipeline once per
        fill method, fill the same holes with GDAL fillnodata, a linear TIN, natural
        neighbours and Laplace (startinpy), GRASS r.fillnulls where installed, and report
        RMSE, MAE, max error and bias on the removed pixels: a table on stdout and
        DIR/fill_eval.json.
    """
    import json

    from .config import load_config

    config = load_config(config_path, list(overrides))
    if fill_benchmark:
        if truth_path:
            raise click.UsageError("--fill and --truth are two different evaluations: give one")
        if not paths or not out_dir:
            raise click.UsageError("the fill benchmark needs SURVEY... and --out DIR")
        _fill_benchmark(
            paths,
            out_dir,
            _with_options(config, workers=workers),
            n_holes=n_holes,
            seed=seed,
            model=model,
            methods=methods,
            alternatives=alternatives,
            resolution_m=resolution_m,
            crs_items=crs_items,
            scheduler=scheduler,
        )
        return
    if len(paths) != 1 or not truth_path:
        raise click.UsageError("give a finished run OUT and --truth RASTER (or --fill SURVEY... --out DIR)")
    if not Path(paths[0]).is_dir():
        raise click.BadParameter(f"{paths[0]!r} is not a folder", param_hint="OUT")

    from .evaluate import check_truth_lattice, score_holes

    out = Path(paths[0])
    if not (out / "holes.gpkg").exists():
        raise InputDataError(out, "holds no finished holefill run (no holes.gpkg)")
    manifest = json.loads((out / "manifest.json").read_text()) if (out / "manifest.json").exists() else None
    min_area_m2 = config.holes.min_area_m2
    if min_area_m2 == "auto":  # as the run resolved it
        if manifest is None:
            raise InputDataError(out, "has no manifest.json to tell holes.min_area_m2: give --set holes.min_area_m2=")
        min_area_m2 = manifest["holes"]["min_area_m2"]
    resolution = check_truth_lattice(truth_path, _run_lattice(out, manifest))
    score = score_holes(out / "holes.gpkg", truth_path, min_area_px=_min_area_px(min_area_m2, resolution))
    click.echo(json.dumps(score.as_dict(), indent=2))


def _run_lattice(out: Path, manifest: dict | None) -> tuple[float, float, float, str]:
    """The run's pixel lattice ``(resolution, left, top, crs_wkt)``: from its manifest, else its DSM."""
    if manifest is not None and "grid" in manifest:
        grid = manifest["grid"]
        return float(grid["resolution"]), grid["bounds"][0], grid["bounds"][3], manifest.get("crs", {}).get("wkt", "")
    from .io.raster import raster_lattice

    if not (out / "dsm.vrt").exists():
        raise InputDataError(out, "has neither manifest.json nor dsm.vrt to tell the run's pixel grid")
    resolution, left, top, crs_wkt = raster_lattice(out / "dsm.vrt")
    return float(resolution or 0.0), left, top, crs_wkt


def _fill_benchmark(
    paths, out_dir, config, *, n_holes, seed, model, methods, alternatives, resolution_m, crs_items, scheduler
):
    from .evaluate_fill import evaluate_fill, format_table, survey_name

    def names(text: str) -> tuple[str, ...]:
        return tuple(item.strip() for item in text.split(",") if item.strip())

    surveys = [[path] for path in paths]
    known = {survey_name(inputs) for inputs in surveys}
    crs = {}
    for item in crs_items:  # NAME=CRS when NAME is a survey's name; else (a PROJ string too) for every survey
        head, _, value = item.partition("=")
        crs.update({head: value} if head in known else {"*": item})

    def progress(result) -> None:
        state = f"skipped: {result.skipped}" if result.skipped else f"{len(result.holes)} holes, {result.cut_px} px"
        _note(f"{result.model} {result.survey}: {state}")

    benchmark = evaluate_fill(
        surveys,
        out_dir,
        config,
        n_holes=n_holes,
        seed=seed,
        models=("dsm", "dtm") if model == "both" else (model,),
        methods=names(methods),
        alternatives=names(alternatives),
        resolution_m=resolution_m,
        crs=crs,
        scheduler=scheduler,
        on_survey=progress,
    )
    table = format_table(benchmark)
    (Path(out_dir) / "fill_eval.txt").write_text(table + "\n")
    click.echo(table)
    _note(f"fill benchmark: {benchmark.seconds:.0f} s -> {Path(out_dir) / 'fill_eval.json'}")


def _min_area_px(min_area_m2: float, resolution: float) -> int:
    import math

    return max(1, math.ceil(min_area_m2 / resolution**2))


@main.command("plan")
@click.argument("holes_gpkg", type=click.Path(dir_okay=False))
@click.option(
    "--dsm", "dsm_path", required=True, type=click.Path(), help="The DSM (GeoTIFF, COG or VRT), e.g. OUT/dsm.vrt."
)
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Output folder.")
@config_option
@set_option
@click.option(
    "--home", help="Take-off point X,Y in the survey CRS (flightplan.home; default: the centre of the holes)."
)
def plan_command(holes_gpkg, dsm_path, out_dir, config_path, overrides, home):
    """Re-plan re-flights from a finished run's holes.gpkg and DSM, without re-processing."""
    from .config import load_config
    from .flight_replan import replan_flights

    config = load_config(config_path, overrides)
    if home is not None:
        try:
            x, y = (float(v) for v in home.split(","))
        except ValueError:
            raise ConfigError(f"--home {home}: expected X,Y in the survey CRS, e.g. 651200,6862100") from None
        config = config.replace("flightplan", source=f"--home {home}", home=[x, y])
    summary = replan_flights(holes_gpkg, dsm_path, config, out_dir)
    _note(
        f"{summary['holes_planned']} of {summary['holes']} holes planned: {summary['patterns']} patterns, "
        f"{summary['lanes']} lanes, {summary['sorties']} sorties, route {summary['flown_route_m']:,.0f} m "
        f"(greedy {summary['greedy_route_m']:,.0f} m) -> {out_dir}",
    )
    for hole_id, reason in summary["holes_not_planned"].items():
        logging.getLogger(__name__).info("hole %s not planned: %s", hole_id, reason)


@main.command("config")
@click.option("--show", is_flag=True, help="Print the resolved configuration as TOML.")
@config_option
@set_option
def config_command(show, config_path, overrides):
    """Validate a configuration (and print it with --show)."""
    from .config import load_config

    config = load_config(config_path, list(overrides))
    if show:
        click.echo(config.to_toml())
    else:
        _note("configuration is valid")


#: Command-line options that set a configuration key: option -> (section, key).
OPTION_KEYS = {
    "workers": ("dask", "workers"),
    "crs": ("survey", "crs"),
    "target_crs": ("survey", "target_crs"),
    "on_error": ("survey", "on_error"),
    "reader": ("read", "reader"),
    "pdal_pipeline": ("read", "pdal_pipeline"),
}


def _with_options(config, **options):
    """The configuration with the options given on the command line (validated like a file)."""
    for name, value in options.items():
        if value is not None:
            section, key = OPTION_KEYS[name]
            config = config.replace(section, source=f"--{name.replace('_', '-')} {value}", **{key: value})
    return config


def _with_pdal(config):
    """With ``read.reader = "pdal"``: python-pdal must import, the pipeline file is checked, and its
    ``filters.reprojection`` becomes the survey's target CRS (a different --target-crs is refused)."""
    if config.read.reader != "pdal":
        return config
    from .io.pdal_reader import import_pdal, load_user_pipeline, settle_target_crs

    import_pdal("--reader pdal")
    if not config.read.pdal_pipeline:
        return config
    pipeline = load_user_pipeline(config.read.pdal_pipeline, streaming=config.read.pdal_streaming)
    target_crs = settle_target_crs(pipeline, config.survey.target_crs)
    if target_crs != config.survey.target_crs:
        config = config.replace("survey", source=f"{pipeline.path} (filters.reprojection)", target_crs=target_crs)
    return config


def _report(summary) -> None:
    _note(
        f"{summary.tiles} tiles, {summary.points_read:,} points "
        f"({summary.points_per_second / 1e6:.2f} M/s; {summary.points_used:,} used), {summary.cells} cells, "
        f"{len(summary.dsm_tiles)} DSM tiles in {summary.seconds:.1f} s -> {summary.out_dir}",
    )
    holes = summary.holes
    if holes:
        causes = ", ".join(f"{n} {cause}" for cause, n in holes["by_cause"].items() if n)
        types = ", ".join(f"{n} {kind}" for kind, n in holes["parts_by_type"].items())
        _note(
            f"{holes['listed']} holes ({holes['area_m2']:,.0f} m2): {causes or 'none'}; parts by type: {types or 'none'}; "
            f"{holes['small_voids']} small voids under {holes['min_area_m2']:.3g} m2 or sampling gaps; "
            f"{holes['vertical_hole_groups']} vertical holes, {holes['walls']} walls",
        )
    if summary.heights.get("heights") == "above_ground":
        _note(
            f"heights are above the ground ({summary.heights['ground_points_at_zero']:,} of "
            f"{summary.heights['ground_points']:,} ground points at z = 0): the DSM is a height-above-ground model"
        )
    if summary.points_outside:
        _note(
            f"{summary.points_outside:,} points lie outside their tile's header bounds and were not used",
            level="warning",
        )
    if "not_planned" in summary.flightplan:
        _note(f"no re-flight plan: {summary.flightplan['not_planned']}", level="warning")
    if summary.reused_tasks:
        _note(f"incremental: {summary.reused_tasks} results of unchanged tiles and cells reused")
    for item in summary.skipped:
        _note(f"skipped {item['path']}: {item['reason']}", level="warning", skipped=item["path"])
    if _Output.json:  # the whole run in one record
        _note(
            "holefill run: done",
            event="run_complete",
            out_dir=summary.out_dir,
            tiles=summary.tiles,
            cells=summary.cells,
            points_read=summary.points_read,
            seconds=round(summary.seconds, 3),
            holes=holes.get("listed", 0) if holes else 0,
            skipped=len(summary.skipped),
            reused_tasks=summary.reused_tasks,
            resumed_tasks=summary.resumed_tasks,
        )


if __name__ == "__main__":  # pragma: no cover
    main()
