"""How the ``holefill`` command talks: messages on stderr (text, or JSON lines), logging, a run's summary.

Logging is configured here (:func:`configure_logging`, called by the group) and nowhere
else; the library only logs.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
from typing import TYPE_CHECKING

import click

if TYPE_CHECKING:
    from ..outputs import RunSummary


class Output:
    """How the command talks on stderr: ``-q`` keeps only errors; ``--log-format json`` writes JSON lines."""

    quiet = False
    json = False


def note(message: str, *, level: str = "info", **fields: object) -> None:
    """One message for the user on stderr (an error, or a summary line that ``-q`` silences).

    With ``--log-format json`` it is one JSON object per line: ``time``, ``level``,
    ``message`` and the given fields, as a scheduler's log collector reads them.
    """
    if Output.quiet and level != "error":
        return
    if Output.json:
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


def configure_logging(verbose: int, quiet: int, log_format: str = "text") -> None:
    Output.quiet = quiet > 0
    Output.json = log_format == "json"
    level = max(logging.DEBUG, logging.WARNING - 10 * (verbose - quiet))
    logging.basicConfig(level=level, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s", force=True)
    if Output.json:
        for handler in logging.getLogger().handlers:
            handler.setFormatter(_JsonFormatter())
    quiet_level = logging.INFO if verbose >= 2 else logging.ERROR
    # distributed installs its own handlers when imported; its configuration says at which level
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", logging.getLevelName(max(level, quiet_level)).lower())
    for noisy in ("distributed", "tornado", "asyncio", "numba", "rasterio", "pyogrio", "bokeh"):
        logging.getLogger(noisy).setLevel(max(level, quiet_level))


def report_run(summary: RunSummary) -> None:
    """The last lines of ``holefill run`` and ``holefill demo``: what the run did."""
    note(
        f"{summary.tiles} tiles, {summary.points_read:,} points "
        f"({summary.points_per_second / 1e6:.2f} M/s; {summary.points_used:,} used), {summary.cells} cells, "
        f"{len(summary.dsm_tiles)} DSM tiles in {summary.seconds:.1f} s -> {summary.out_dir}",
    )
    holes = summary.holes
    if holes:
        causes = ", ".join(f"{n} {cause}" for cause, n in holes["by_cause"].items() if n)
        types = ", ".join(f"{n} {kind}" for kind, n in holes["parts_by_type"].items())
        note(
            f"{holes['listed']} holes ({holes['area_m2']:,.0f} m2): {causes or 'none'}; parts by type: {types or 'none'}; "
            f"{holes['small_voids']} small voids under {holes['min_area_m2']:.3g} m2 or sampling gaps; "
            f"{holes['vertical_hole_groups']} vertical holes, {holes['walls']} walls",
        )
    if summary.heights.get("heights") == "above_ground":
        note(
            f"heights are above the ground ({summary.heights['ground_points_at_zero']:,} of "
            f"{summary.heights['ground_points']:,} ground points at z = 0): the DSM is a height-above-ground model"
        )
    if summary.points_outside:
        note(
            f"{summary.points_outside:,} points lie outside their tile's header bounds and were not used",
            level="warning",
        )
    if "not_planned" in summary.flightplan:
        note(f"no re-flight plan: {summary.flightplan['not_planned']}", level="warning")
    if summary.reused_tasks:
        note(f"incremental: {summary.reused_tasks} results of unchanged tiles and cells reused")
    for item in summary.skipped:
        note(f"skipped {item['path']}: {item['reason']}", level="warning", skipped=item["path"])
    if Output.json:  # the whole run in one record
        note(
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
