"""``holefill plan``: re-plan the re-flights of a finished run for another drone or altitude.

Reads the run's ``holes.gpkg`` and DSM, plans, and writes the flight-plan files into the
output folder together or not at all (through a staging folder, like a run). The planning
itself is :func:`pipeline.flight_planning.plan_flights`, which a run calls too.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from .config import Config
from .errors import InputDataError
from .flight_planning import plan_flights
from .outputs import FLIGHTPLAN_PRODUCTS
from .staging import Staging


def replan_flights(
    holes_gpkg: str | os.PathLike, dsm_path: str | os.PathLike, config: Config, out_dir: str | os.PathLike
) -> dict[str, Any]:
    """Plan from a run's outputs into ``out_dir``; the files replace older plans there."""
    for what, path in (("holes file", holes_gpkg), ("DSM", dsm_path)):
        if not Path(path).exists():
            raise InputDataError(path, f"{what} not found")
    staging = Staging.create(out_dir)
    try:
        summary = plan_flights(holes_gpkg, dsm_path, config, staging.root)
        names = tuple(os.path.basename(f) for f in summary["files"])
        staging.commit(names, keep_work=False, replaces=FLIGHTPLAN_PRODUCTS)
    except BaseException:
        staging.remove()
        raise
    summary["files"] = [str(Path(out_dir) / name) for name in names]
    return summary
