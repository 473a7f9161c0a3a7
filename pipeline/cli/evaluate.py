"""``holefill evaluate``: its two jobs, scoring a finished run against truth, and the fill benchmark.

- ``holefill evaluate OUT --truth RASTER``: :func:`pipeline.evaluate.truth.score_run`, printed as JSON;
- ``holefill evaluate --fill SURVEY... --out DIR``: :func:`pipeline.evaluate.fill.evaluate_fill`,
  a table on stdout and DIR/fill_eval.json.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from .messages import note
from .options import config_option, scheduler_option, set_option, with_options, workers_option

if TYPE_CHECKING:
    from ..config import Config


@click.command("evaluate")
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
    default="gdal_fillnodata,nearest_alt,tin_linear,nni,laplace,grass_fillnulls",
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
@workers_option
@scheduler_option("Address of a running Dask scheduler (default: one local cluster for all runs).")
@config_option
@set_option
def evaluate_command(paths: tuple[str, ...], truth_path: str | None, fill_benchmark: bool, **options: Any) -> None:
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
    from ..config import load_config

    config = load_config(options["config_path"], list(options["overrides"]))
    if fill_benchmark:
        if truth_path:
            raise click.UsageError("--fill and --truth are two different evaluations: give one")
        if not paths or not options["out_dir"]:
            raise click.UsageError("the fill benchmark needs SURVEY... and --out DIR")
        _benchmark_fills(paths, with_options(config, workers=options["workers"]), options)
        return
    if len(paths) != 1 or not truth_path:
        raise click.UsageError("give a finished run OUT and --truth RASTER (or --fill SURVEY... --out DIR)")
    _score_against_truth(paths[0], truth_path, config)


def _score_against_truth(out: str, truth_path: str, config: Config) -> None:
    """The first job: the holes of the finished run ``out`` scored against a truth raster, as JSON on stdout."""
    if not Path(out).is_dir():
        raise click.BadParameter(f"{out!r} is not a folder", param_hint="OUT")
    from ..evaluate.truth import score_run

    score = score_run(out, truth_path, min_area_m2=config.holes.min_area_m2)
    click.echo(json.dumps(score.as_dict(), indent=2))


def _benchmark_fills(paths: tuple[str, ...], config: Config, options: dict[str, Any]) -> None:
    """The second job: the fill benchmark over each survey, a table on stdout and in ``--out``."""
    from ..evaluate.fill import BenchmarkPlan, evaluate_fill, format_table, survey_name

    def names(text: str) -> tuple[str, ...]:
        return tuple(item.strip() for item in text.split(",") if item.strip())

    surveys = [[path] for path in paths]
    known = {survey_name(inputs) for inputs in surveys}
    crs = {}
    for item in options[
        "crs_items"
    ]:  # NAME=CRS when NAME is a survey's name; else (a PROJ string too) for every survey
        head, _, value = item.partition("=")
        crs.update({head: value} if head in known else {"*": item})

    def progress(result) -> None:
        state = f"skipped: {result.skipped}" if result.skipped else f"{len(result.holes)} holes, {result.cut_px} px"
        note(f"{result.model} {result.survey}: {state}")

    out_dir, model = options["out_dir"], options["model"]
    benchmark = evaluate_fill(
        surveys,
        out_dir,
        config,
        plan=BenchmarkPlan(
            n_holes=options["n_holes"],
            seed=options["seed"],
            models=("dsm", "dtm") if model == "both" else (model,),
            methods=names(options["methods"]),
            alternatives=names(options["alternatives"]),
            resolution_m=options["resolution_m"],
        ),
        crs=crs,
        scheduler=options["scheduler"],
        on_survey=progress,
    )
    table = format_table(benchmark)
    (Path(out_dir) / "fill_eval.txt").write_text(table + "\n", encoding="utf-8")
    click.echo(table)
    note(f"fill benchmark: {benchmark.seconds:.0f} s -> {Path(out_dir) / 'fill_eval.json'}")
