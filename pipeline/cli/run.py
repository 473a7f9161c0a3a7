"""``holefill run``: build the DSM of a survey, find, explain and fill its holes, plan the re-flights."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from ..errors import InputDataError
from .group import EXIT_PARTIAL
from .messages import report_run
from .options import (
    OPTION_KEYS,
    config_option,
    out_option,
    progress_option,
    progress_shown,
    scheduler_option,
    set_option,
    with_options,
    workers_option,
)

if TYPE_CHECKING:
    from ..config import Config


@click.command("run")
@click.argument("inputs", nargs=-1, required=True)
@out_option
@config_option
@set_option
@scheduler_option("Address of a running Dask scheduler (default: a local cluster).")
@workers_option
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
@progress_option
@click.option("--resume", is_flag=True, help="Continue an interrupted run of the same inputs and configuration.")
@click.option("--overwrite", is_flag=True, help="Replace a result of another configuration in --out.")
@click.option(
    "--incremental",
    is_flag=True,
    help="Keep stage results in OUT/work; a later --incremental run decodes only new or changed tiles.",
)
def run_command(inputs: tuple[str, ...], out_dir: str, **options: Any) -> None:
    """Build the DSM of a survey. INPUT may be files, folders or globs of LAS/LAZ/COPC."""
    from ..gc_pause import collector_paused

    with collector_paused():  # the start's imports (0.2 s of collections: pipeline.gc_pause)
        from ..cluster import ClusterStart

        config = _config(options)
        for name, path in (("AOI", options["aoi"]), ("water", options["water"])):
            if path is not None and not Path(path).exists():
                raise InputDataError(path, f"{name} file not found")
        scheduler = options["scheduler"]
        # the workers start while the pipeline's modules are imported and the headers scanned
        starting = None if scheduler else ClusterStart.begin(config)
    summary = None
    try:
        with collector_paused():
            from ..run import run_survey

        summary = run_survey(
            inputs,
            out_dir,
            config,
            scheduler=scheduler,
            cluster=starting,
            aoi=options["aoi"],
            water=options["water"],
            progress=progress_shown(options["progress"]),
            resume=options["resume"],
            overwrite=options["overwrite"],
            incremental=options["incremental"],
        )
    finally:
        if starting is not None:
            try:
                starting.close()
            except KeyboardInterrupt:
                if summary is None:
                    raise
                # the result was committed before the interrupt: it stands (exit 0)
    report_run(summary)
    if summary.skipped:  # outputs written, but some tiles are missing from them
        click.get_current_context().exit(EXIT_PARTIAL)


def _config(options: dict[str, Any]) -> Config:
    """The configuration: ``--config``, ``--set``, then the options that set a key, then the PDAL pipeline's."""
    from ..config import load_config

    if options["pdal_pipeline"] is not None and options["reader"] is None:
        options = {**options, "reader": "pdal"}
    config = with_options(
        load_config(options["config_path"], options["overrides"]), **{name: options[name] for name in OPTION_KEYS}
    )
    return _with_pdal(config)


def _with_pdal(config: Config) -> Config:
    """With ``read.reader = "pdal"``: python-pdal must import, the pipeline file is checked, and its
    ``filters.reprojection`` becomes the survey's target CRS (a different --target-crs is refused)."""
    if config.read.reader != "pdal":
        return config
    from ..io.pdal_reader import import_pdal, load_user_pipeline, settle_target_crs

    import_pdal("--reader pdal")
    if not config.read.pdal_pipeline:
        return config
    pipeline = load_user_pipeline(config.read.pdal_pipeline, streaming=config.read.pdal_streaming)
    target_crs = settle_target_crs(pipeline, config.survey.target_crs)
    if target_crs != config.survey.target_crs:
        config = config.replace("survey", source=f"{pipeline.path} (filters.reprojection)", target_crs=target_crs)
    return config
