"""``holefill demo``: a synthetic survey with known holes, run and scored against its truth."""

from __future__ import annotations

from pathlib import Path

import click

from .messages import note, report_run
from .options import (
    config_option,
    out_option,
    progress_option,
    progress_shown,
    scheduler_option,
    set_option,
    with_options,
    workers_option,
)


@click.command("demo")
@out_option
@click.option(
    "--size", type=click.Choice(["unit", "demo"]), default="demo", show_default=True, help="Synthetic survey preset."
)
@config_option
@set_option
@workers_option
@scheduler_option("Address of a running Dask scheduler.")
@progress_option
def demo_command(
    out_dir: str,
    size: str,
    config_path: str | None,
    overrides: tuple[str, ...],
    workers: int | None,
    scheduler: str | None,
    progress: bool | None,
) -> None:
    """Generate a synthetic survey with known holes and run the pipeline on it."""
    from ..config import load_config
    from ..evaluate.truth import min_area_px, score_holes
    from ..run import run_survey
    from ..synth import generate_survey, preset, write_truth

    config = with_options(load_config(config_path, overrides), workers=workers)
    out = Path(out_dir)
    survey_dir = out / "survey"
    note(f"generating a synthetic survey ({size}) in {survey_dir} ...")
    synthetic = generate_survey(survey_dir / "tiles", preset(size))
    truth = write_truth(synthetic, survey_dir)
    if config.grid.resolution_m == "auto":  # the truth rasters are on the synthetic survey's grid
        config = config.replace("grid", source="demo", resolution_m=synthetic.spec.resolution)
    note(f"{len(synthetic.tiles)} LAZ tiles, {synthetic.n_points:,} points; truth in {survey_dir}")
    summary = run_survey(
        [str(survey_dir / "tiles")],
        out,
        config,
        scheduler=scheduler,
        aoi=truth["survey_area"],
        overwrite=True,  # the demo makes its survey anew each time: its folder is its own
        progress=progress_shown(progress),
    )
    report_run(summary)
    score = score_holes(
        out / "holes.gpkg",
        truth["hole_cause"],
        min_area_px=min_area_px(summary.holes["min_area_m2"], synthetic.spec.resolution),
    )
    note(
        f"against the truth: hole IoU {score.iou:.3f}, causes right for {score.cause_correct} of "
        f"{score.holes} holes ({score.cause_accuracy:.1%})",
    )
