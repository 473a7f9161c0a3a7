"""``holefill plan``: re-plan the re-flights of a finished run from its holes and DSM."""

from __future__ import annotations

import logging

import click

from ..errors import ConfigError
from .messages import note
from .options import config_option, out_option, set_option

logger = logging.getLogger(__package__)  # "pipeline.cli", the name it logged under as one module


@click.command("plan")
@click.argument("holes_gpkg", type=click.Path(dir_okay=False))
@click.option(
    "--dsm", "dsm_path", required=True, type=click.Path(), help="The DSM (GeoTIFF, COG or VRT), e.g. OUT/dsm.vrt."
)
@out_option
@config_option
@set_option
@click.option(
    "--home",
    help="Take-off point X,Y in the survey CRS (flightplan.home; default: the open ground nearest to the holes, docs/flightplans.md).",
)
def plan_command(
    holes_gpkg: str, dsm_path: str, out_dir: str, config_path: str | None, overrides: tuple[str, ...], home: str | None
) -> None:
    """Re-plan re-flights from a finished run's holes.gpkg and DSM, without re-processing."""
    from ..config import load_config
    from ..flight_replan import replan_flights

    config = load_config(config_path, overrides)
    if home is not None:
        try:
            x, y = (float(v) for v in home.split(","))
        except ValueError:
            raise ConfigError(f"--home {home}: expected X,Y in the survey CRS, e.g. 651200,6862100") from None
        config = config.replace("flightplan", source=f"--home {home}", home=[x, y])
    summary = replan_flights(holes_gpkg, dsm_path, config, out_dir)
    note(
        f"{summary['holes_planned']} of {summary['holes']} holes planned: {summary['patterns']} patterns, "
        f"{summary['lanes']} lanes, {summary['sorties']} sorties, route {summary['flown_route_m']:,.0f} m "
        f"(greedy {summary['greedy_route_m']:,.0f} m) -> {out_dir}",
    )
    for hole_id, reason in summary["holes_not_planned"].items():
        logger.info("hole %s not planned: %s", hole_id, reason)
