"""The flight-planning tool: a run's holes and DSM in, re-flight plans out (docs/flightplans.md).

:func:`plan_flights` reads the holes (``holes.gpkg``) and the DSM around them
(:mod:`pipeline.io.flightplan_files`), plans the mission with the kernels of
:mod:`pipeline.flightplan` and writes every flight-plan file. A run calls it over its
repaired DSM; ``holefill plan OUT/holes.gpkg --dsm OUT/dsm.vrt --config drone.toml
--out DIR`` calls it through :func:`pipeline.flight_replan.replan_flights` (atomically):
it needs no point cloud, so a crew can change the drone settings and re-plan in seconds.
The ``[flightplan]`` settings are checked when the configuration is loaded and turned
into :class:`~pipeline.flightplan.FlightParams` by :func:`pipeline.parameters.flight_params`.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyproj
import shapely
from affine import Affine

from .config import Config
from .errors import CRSError, InputDataError
from .flightplan.altitude import ellipsoid_transformer, vertical_crs_for
from .flightplan.mission import FlightPlan, HoleInput, plan_mission
from .flightplan.takeoff_search import TAKEOFF_MAX_M, BoxGrid, GroundGrid
from .io.flightplan_files import (
    CellGround,
    DsmWindows,
    file_bounds,
    open_dsm,
    read_cell_ground,
    read_ground,
    read_holes,
    write_flightplan,
)
from .parameters import flight_params

__all__ = ["plan_flights", "run_point_files", "summarize"]

logger = logging.getLogger(__name__)


def plan_flights(
    holes_gpkg: str | os.PathLike,
    dsm_path: str | os.PathLike,
    config: Config,
    out_dir: str | os.PathLike,
    *,
    home: tuple[float, float] | None = None,
    point_files: Sequence[str | os.PathLike] | None = None,
    cell_ground: CellGround | None = None,
) -> dict[str, Any]:
    """Plan re-flights for the holes of ``holes_gpkg`` over ``dsm_path`` and write all files.

    Parameters
    ----------
    config : Config
        Its ``[flightplan]`` section is used.
    home : (x, y), optional
        Overrides ``flightplan.home``; neither: the open ground nearest to the planned holes.
    point_files : list of paths, optional
        The survey's LAS/LAZ files (in the DSM's CRS), for the ground-class points at
        take-off; default: the inputs listed in ``manifest.json`` beside ``holes_gpkg``,
        where they still exist. Without any, home and its height come from the DSM.
    cell_ground : CellGround, optional
        A run's own: the ground points' sums stage 1 kept with the cells, read instead of
        the point files wherever they were kept.

    Returns
    -------
    dict
        The summary (counts, lengths, durations, files) that also goes into the
        manifest of a run.
    """
    params = flight_params(config)
    holes, holes_crs = read_holes(holes_gpkg)
    if home is None and config.flightplan.home:
        home_x, home_y = config.flightplan.home  # the configuration checked: [] or [x, y]
        home = (home_x, home_y)
    reach = params.coverage.swath_m + params.coverage.margin_m + params.coverage.run_in_m + TAKEOFF_MAX_M
    extent = [h.geometry.bounds for h in holes if h.geometry is not None and not h.geometry.is_empty]
    if home is not None:
        extent.append((home[0], home[1], home[0], home[1]))
    bounds = None
    if extent:
        b = np.array(extent)
        bounds = (b[:, 0].min() - reach, b[:, 1].min() - reach, b[:, 2].max() + reach, b[:, 3].max() + reach)
    if point_files is None:
        point_files = run_point_files(holes_gpkg)
    # the DSM window of the holes, read block by block as the plan needs it (lanes, take-off)
    with open_dsm(dsm_path, bounds) as (dsm, transform, dsm_crs):
        if not _same_crs(dsm_crs, holes_crs):
            raise CRSError(dsm_path, f"the DSM's CRS differs from the holes' CRS ({pyproj.CRS(holes_crs).name})")
        plan = _plan_over(
            dsm, transform, dsm_crs, (holes, holes_crs), config,
            home=home, point_files=point_files, cell_ground=cell_ground,
        )  # fmt: skip
    if plan.home_warning:
        logger.warning("flight plan: %s", plan.home_warning)
    files = write_flightplan(
        plan, out_dir, drone_enum=config.flightplan.dji_drone_enum, payload_enum=config.flightplan.dji_payload_enum
    )
    return summarize(plan, files)


def _plan_over(
    dsm: DsmWindows,
    transform: Affine,
    dsm_crs: str,
    holes_and_crs: tuple[list[HoleInput], str],
    config: Config,
    *,
    home: tuple[float, float] | None,
    point_files: Sequence[str | os.PathLike],
    cell_ground: CellGround | None = None,
) -> FlightPlan:
    """The mission over the DSM window, the ground read near the take-off from ``cell_ground`` or ``point_files``."""
    holes, holes_crs = holes_and_crs
    params = flight_params(config)
    ground = None
    if point_files or cell_ground is not None:
        inputs = list(point_files)
        headers: list[tuple[float, float, float, float]] = []  # the files' bounds, read at the first box

        def read_box(box: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
            r0, c0, r1, c1 = box
            corner = transform @ Affine.translation(c0, r0)
            shape = (r1 - r0, c1 - c0)
            if cell_ground is not None and (kept := read_cell_ground(cell_ground, corner, shape)) is not None:
                return kept
            if not inputs:  # neither kept sums nor points: no ground known in the box
                return np.full(shape, np.nan), np.zeros(shape)
            if not headers:
                headers.extend(file_bounds(inputs))
            return read_ground(inputs, corner, shape, headers)

        # the ground is read in boxes near the take-off: grids that hold those boxes alone
        ground = GroundGrid(BoxGrid(dsm.shape, np.nan), BoxGrid(dsm.shape, 0.0), reader=read_box)
    to_ellipsoid = None
    if params.altitude_reference == "ellipsoid":
        probe = home or _centre(holes)
        to_ellipsoid = ellipsoid_transformer(vertical_crs_for(dsm_crs, config.flightplan.vertical_crs), probe=probe)
    try:
        return plan_mission(
            holes, dsm, transform, crs_wkt=holes_crs, params=params, home=home, to_ellipsoid=to_ellipsoid,
            snap_home=not config.flightplan.home, ground=ground,
        )  # fmt: skip
    except ValueError as e:
        raise InputDataError(dsm.path, str(e)) from None


def _same_crs(a: str, b: str) -> bool:
    """Whether two CRS definitions mean the same CRS.

    GDAL writes WKT1 and pyogrio reads WKT2 of one EPSG CRS, and PROJ does not always
    find them equal (datum ensemble names differ); the same EPSG code settles it.
    """
    crs_a, crs_b = pyproj.CRS.from_user_input(a), pyproj.CRS.from_user_input(b)
    if crs_a.equals(crs_b, ignore_axis_order=True):
        return True
    code = crs_a.to_epsg(min_confidence=90)
    return code is not None and code == crs_b.to_epsg(min_confidence=90)


def summarize(plan: FlightPlan, files: list[Path]) -> dict[str, Any]:
    """Counts, route lengths (greedy vs improved) and sortie durations."""
    planned = [d for d in plan.decisions if d.planned]
    return {
        "holes": len(plan.decisions),
        "holes_planned": len(planned),
        "holes_not_planned": {d.hole_id: d.reason for d in plan.decisions if not d.planned},
        "hole_visible_share": {
            d.hole_id: round(d.visible_share, 4)
            for d in planned
            if d.visible_share is not None and np.isfinite(d.visible_share)
        },
        "patterns": len({p.pattern_id for p in plan.patterns}),
        "lanes": sum(len(s.lanes) for s in plan.sorties),
        "sorties": len(plan.sorties),
        "sortie_durations_s": [round(s.duration_s, 1) for s in plan.sorties],
        "sortie_min_clearance_m": [
            round(s.least_clearance_m, 1) if np.isfinite(s.least_clearance_m) else None for s in plan.sorties
        ],
        "greedy_route_m": round(plan.greedy_length_m, 1),
        "improved_route_m": round(plan.improved_length_m, 1),
        "flown_route_m": round(plan.flown_length_m, 1),
        "home": list(plan.home),
        "home_ground_m": round(plan.home_ground_m, 2),
        "home_height_from": plan.home_source,
        "home_warning": plan.home_warning,
        "altitude_reference": plan.altitude_reference,
        "files": [str(f) for f in files],
    }


def run_point_files(holes_gpkg: str | os.PathLike) -> list[str]:
    """The input point files a run lists in its ``manifest.json`` beside ``holes_gpkg``, those that exist."""
    manifest = Path(holes_gpkg).parent / "manifest.json"
    try:
        inputs = json.loads(manifest.read_text()).get("inputs", [])
    except (OSError, ValueError):
        return []
    paths = [i.get("path", "") for i in inputs] if isinstance(inputs, list) else list(inputs)
    return [p for p in paths if p and Path(p).is_file()]


def _centre(holes: list[HoleInput]) -> tuple[float, float]:
    c = shapely.union_all([h.geometry for h in holes]).centroid
    return (c.x, c.y)
