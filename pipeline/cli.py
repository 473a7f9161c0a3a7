"""The ``holefill`` command line: thin commands over library functions.

Commands parse options, turn them into configuration overrides (validated once
by :func:`pipeline.config.load_config`), call one library function and map its
exceptions to exit codes in one place (:data:`EXIT_CODES`). Logging is
configured here and nowhere else.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
from pathlib import Path

import click

from . import __version__
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
        previous = signal.signal(signal.SIGTERM, _terminate)
        try:
            return super().invoke(ctx)
        except HolefillError as e:
            click.echo(f"holefill: error: {e}", err=True)
            code = next(code for cls, code in EXIT_CODES if isinstance(e, cls))
            if isinstance(e, TaskError):
                click.echo("holefill: finished tasks are kept: run again with --resume to continue", err=True)
            ctx.exit(code)
        except KeyboardInterrupt:
            click.echo("holefill: interrupted; finished tasks are kept: run again with --resume to continue", err=True)
            ctx.exit(EXIT_INTERRUPTED)
        finally:
            signal.signal(signal.SIGTERM, previous)


#: Exit status of a run stopped by Ctrl-C or SIGTERM (what shells and schedulers expect).
EXIT_INTERRUPTED = 130
#: Exit status of a run that wrote its outputs but skipped tiles (``--on-error skip``), listed in the manifest.
EXIT_PARTIAL = 5


def _terminate(signum, frame) -> None:
    """SIGTERM (timeout, SLURM, systemd) stops a run the way Ctrl-C does."""
    raise KeyboardInterrupt


def _configure_logging(verbose: int, quiet: int) -> None:
    level = max(logging.DEBUG, logging.WARNING - 10 * (verbose - quiet))
    logging.basicConfig(level=level, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s", force=True)
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
@click.option("-q", "--quiet", count=True, help="Less log output (repeatable).")
def main(verbose: int, quiet: int) -> None:
    """Complete DSMs from airborne lidar surveys: find, explain and fill the holes."""
    _configure_logging(verbose, quiet)


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
@click.option("--progress/--no-progress", default=None, help="Progress bar (default: when stderr is a terminal).")
@click.option("--resume", is_flag=True, help="Continue an interrupted run of the same inputs and configuration.")
def run(
    inputs, out_dir, config_path, overrides, scheduler, workers, crs, target_crs, aoi, water, on_error, progress, resume
):
    """Build the DSM of a survey. INPUT may be files, folders or globs of LAS/LAZ/COPC."""
    from .config import load_config
    from .run import run_survey

    config = _with_options(
        load_config(config_path, overrides), workers=workers, crs=crs, target_crs=target_crs, on_error=on_error
    )
    for name, path in (("AOI", aoi), ("water", water)):
        if path is not None and not Path(path).exists():
            raise InputDataError(path, f"{name} file not found")
    summary = run_survey(
        inputs,
        out_dir,
        config,
        scheduler=scheduler,
        aoi=aoi,
        water=water,
        progress=sys.stderr.isatty() if progress is None else progress,
        resume=resume,
    )
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
    click.echo(f"generating a synthetic survey ({size}) in {survey_dir} ...", err=True)
    synthetic = generate_survey(survey_dir / "tiles", preset(size))
    truth = write_truth(synthetic, survey_dir)
    if config.grid.resolution_m == "auto":  # the truth rasters are on the synthetic survey's grid
        config = config.replace("grid", source="demo", resolution_m=synthetic.spec.resolution)
    click.echo(f"{len(synthetic.tiles)} LAZ tiles, {synthetic.n_points:,} points; truth in {survey_dir}", err=True)
    summary = run_survey(
        [str(survey_dir / "tiles")],
        out,
        config,
        scheduler=scheduler,
        aoi=truth["survey_area"],
        progress=sys.stderr.isatty() if progress is None else progress,
    )
    _report(summary)
    score = score_holes(
        out / "holes.gpkg",
        truth["hole_cause"],
        min_area_px=_min_area_px(summary.holes["min_area_m2"], synthetic.spec.resolution),
    )
    click.echo(
        f"against the truth: hole IoU {score.iou:.3f}, causes right for {score.cause_correct} of "
        f"{score.holes} holes ({score.cause_accuracy:.1%})",
        err=True,
    )


@main.command()
@click.argument("out_dir", type=click.Path(exists=True, file_okay=False))
@click.option(
    "--truth",
    "truth_path",
    required=True,
    type=click.Path(exists=True, dir_okay=False),
    help="Raster of true hole causes (0 none, 1 occlusion, 2 water, 3 missed coverage) on the run's grid.",
)
@config_option
@set_option
def evaluate(out_dir, truth_path, config_path, overrides):
    """Score the holes of a finished run against a truth raster (IoU, cause accuracy)."""
    import json

    import rasterio

    from .config import load_config
    from .evaluate import score_holes

    config = load_config(config_path, list(overrides))
    min_area_m2 = config.holes.min_area_m2
    if min_area_m2 == "auto":  # as the run resolved it
        manifest = json.loads((Path(out_dir) / "manifest.json").read_text())
        min_area_m2 = manifest["holes"]["min_area_m2"]
    with rasterio.open(truth_path) as truth:
        resolution = abs(truth.transform.a)
    score = score_holes(Path(out_dir) / "holes.gpkg", truth_path, min_area_px=_min_area_px(min_area_m2, resolution))
    click.echo(json.dumps(score.as_dict(), indent=2))


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
    click.echo(
        f"{summary['holes_planned']} of {summary['holes']} holes planned: {summary['patterns']} patterns, "
        f"{summary['lanes']} lanes, {summary['sorties']} sorties, route {summary['flown_route_m']:,.0f} m "
        f"(greedy {summary['greedy_route_m']:,.0f} m) -> {out_dir}",
        err=True,
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
        click.echo("configuration is valid", err=True)


#: Command-line options that set a configuration key: option -> (section, key).
OPTION_KEYS = {
    "workers": ("dask", "workers"),
    "crs": ("survey", "crs"),
    "target_crs": ("survey", "target_crs"),
    "on_error": ("survey", "on_error"),
}


def _with_options(config, **options):
    """The configuration with the options given on the command line (validated like a file)."""
    for name, value in options.items():
        if value is not None:
            section, key = OPTION_KEYS[name]
            config = config.replace(section, source=f"--{name.replace('_', '-')} {value}", **{key: value})
    return config


def _report(summary) -> None:
    click.echo(
        f"{summary.tiles} tiles, {summary.points_read:,} points "
        f"({summary.points_per_second / 1e6:.2f} M/s), {summary.cells} cells, "
        f"{len(summary.dsm_tiles)} DSM tiles in {summary.seconds:.1f} s -> {summary.out_dir}",
        err=True,
    )
    holes = summary.holes
    if holes:
        causes = ", ".join(f"{n} {cause}" for cause, n in holes["by_cause"].items() if n)
        types = ", ".join(f"{n} {kind}" for kind, n in holes["parts_by_type"].items())
        click.echo(
            f"{holes['listed']} holes ({holes['area_m2']:,.0f} m2): {causes or 'none'}; parts by type: {types or 'none'}; "
            f"{holes['small_voids']} small voids under {holes['min_area_m2']:g} m2 or sampling gaps; "
            f"{holes['vertical_hole_groups']} vertical holes, {holes['walls']} walls",
            err=True,
        )
    for item in summary.skipped:
        click.echo(f"skipped {item['path']}: {item['reason']}", err=True)


if __name__ == "__main__":  # pragma: no cover
    main()
