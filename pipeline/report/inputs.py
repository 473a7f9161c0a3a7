"""Reading a finished run's output folder into :class:`ReportInputs` for the maps.

The only module of the report that reads files, through :mod:`pipeline.io`: ``dsm.vrt``
and ``fill_mask.vrt`` with :mod:`pipeline.io.raster`, ``holes.gpkg`` and
``flightplan.gpkg`` with :mod:`pipeline.io.vector`. Both are imported inside the
functions, so importing the report stays light.
"""

from __future__ import annotations

import collections
import dataclasses
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from .model import MAX_HOLE_VERTICES, MAX_MAP_PX, ZOOM_PX, Bounds, MapHole, MapRaster, ReportInputs
from .text import _float, _text


def read_report_inputs(
    folder: str | os.PathLike,
    *,
    max_px: int = MAX_MAP_PX,
    zooms: int = 4,
    zoom_px: int = ZOOM_PX,
    route: bool = True,
) -> ReportInputs | None:
    """The report's map inputs, read from a run's output (or staging) folder.

    Reads ``dsm.vrt`` and ``fill_mask.vrt`` downsampled to at most ``max_px`` pixels on
    the long side (GDAL picks the tiles' overviews), the ``holes``, ``hole_parts`` and
    ``survey_area`` layers of ``holes.gpkg`` and, when present, the ``route`` layer of
    ``flightplan.gpkg``; and a closer window (at most ``zoom_px``) around each of the
    ``zooms`` largest holes that do not span most of the survey.

    Parameters
    ----------
    folder : path-like
        A folder holding ``dsm.vrt`` (``OUT``, or the run's staging folder before commit).
    route : bool
        Read the re-flight route; without it, :func:`with_route` adds it later (a run reads the
        maps while it plans the flights).

    Returns
    -------
    ReportInputs or None
        None when the folder holds no ``dsm.vrt``.
    """
    folder = Path(folder)
    if not (folder / "dsm.vrt").exists():
        return None
    overview = _read_view(folder, None, max_px)
    pixel = _map_pixel(overview)
    holes = _read_holes(folder / "holes.gpkg", pixel)
    survey = (overview.bounds[2] - overview.bounds[0], overview.bounds[3] - overview.bounds[1])
    zoom_views: list[tuple[int, MapRaster]] = []
    for hole in sorted(holes, key=lambda h: -h.area_m2):
        if len(zoom_views) >= zooms:
            break
        if hole.bounds is None or not hole.rings:
            continue
        w, h = hole.bounds[2] - hole.bounds[0], hole.bounds[3] - hole.bounds[1]
        if w > 0.5 * survey[0] and h > 0.5 * survey[1]:
            continue  # the overview shows it whole
        zoom_views.append((hole.hole_id, _read_view(folder, _zoom_bounds(hole.bounds, overview.bounds), zoom_px)))
    return ReportInputs(
        overview=overview,
        holes=holes,
        zooms=tuple(zoom_views),
        route=_read_lines(folder / "flightplan.gpkg", "route", pixel) if route else (),
        survey_area=_read_rings(folder / "holes.gpkg", "survey_area", pixel),
        part_area_by_type=_read_part_areas(folder / "holes.gpkg"),
    )


def prepare_maps(folder: str | os.PathLike) -> ReportInputs | None:
    """:func:`read_report_inputs` without the route, each map's pictures drawn (:attr:`MapRaster.images`):
    what a run makes while it plans the flights, :func:`with_route` adding the route after."""
    inputs = read_report_inputs(folder, route=False)
    if inputs is not None:
        for view in (inputs.overview, *(zoom for _, zoom in inputs.zooms)):
            view.images  # noqa: B018  (drawn now, kept on the map)
    return inputs


def with_route(inputs: ReportInputs, folder: str | os.PathLike) -> ReportInputs:
    """``inputs`` with the re-flight route of ``folder``'s ``flightplan.gpkg`` (none where it holds none)."""
    pixel = _map_pixel(inputs.overview)
    return dataclasses.replace(inputs, route=_read_lines(Path(folder) / "flightplan.gpkg", "route", pixel))


def _map_pixel(view: MapRaster) -> float:
    """The larger side of a map's pixel, in survey units: how finely outlines and lines are kept."""
    return max(
        (view.bounds[2] - view.bounds[0]) / view.dsm.shape[1],
        (view.bounds[3] - view.bounds[1]) / view.dsm.shape[0],
    )


def _zoom_bounds(hole: Bounds, limit: Bounds) -> Bounds:
    """A square window around a hole with a margin, moved (not cut) to stay inside the survey grid."""
    cx, cy = (hole[0] + hole[2]) / 2, (hole[1] + hole[3]) / 2
    half = max(hole[2] - hole[0], hole[3] - hole[1]) * 0.8 + 15.0
    half = min(half, (limit[2] - limit[0]) / 2, (limit[3] - limit[1]) / 2)
    cx = min(max(cx, limit[0] + half), limit[2] - half)
    cy = min(max(cy, limit[1] + half), limit[3] - half)
    return (cx - half, cy - half, cx + half, cy + half)


def _read_view(folder: Path, bounds: Bounds | None, max_px: int) -> MapRaster:
    """``dsm.vrt`` (and ``fill_mask.vrt``) over ``bounds`` (default: all), at most ``max_px`` on the long side."""
    from ..io.raster import read_codes, read_view

    dsm, view_bounds = read_view(folder / "dsm.vrt", bounds, max_px)
    filled = None
    if (folder / "fill_mask.vrt").exists():
        codes, nodata = read_codes(folder / "fill_mask.vrt", view_bounds, dsm.shape)
        filled = (codes > 0) & (codes != (255 if nodata is None else int(nodata)))
    return MapRaster(dsm=dsm, bounds=view_bounds, filled=filled)


def _read_holes(gpkg: Path, pixel: float) -> tuple[MapHole, ...]:
    if not gpkg.exists():
        return ()
    import shapely

    from ..io.vector import list_layers, read_layer

    if "holes" not in list_layers(gpkg):
        return ()
    frame = read_layer(gpkg, "holes")
    if frame.empty or "area_m2" not in frame.columns:  # a survey without holes: an empty layer
        return ()
    frame = frame.sort_values("area_m2", ascending=False)
    budget = MAX_HOLE_VERTICES
    holes = []
    for record, geometry in zip(frame.drop(columns="geometry").to_dict("records"), frame.geometry):
        rings: tuple[np.ndarray, ...] = ()
        bounds = label = None
        if geometry is not None and not geometry.is_empty:
            xmin, ymin, xmax, ymax = geometry.bounds
            bounds = (xmin, ymin, xmax, ymax)
            point = geometry.representative_point()
            label = (point.x, point.y)
            if budget > 0 and max(xmax - xmin, ymax - ymin) >= pixel:
                rings = tuple(_rings(shapely.simplify(geometry, pixel / 2)))
                budget -= sum(len(r) for r in rings)
        holes.append(
            MapHole(
                hole_id=int(record["hole_id"]),
                cause=str(record.get("cause") or "unknown"),
                area_m2=float(record.get("area_m2") or 0.0),
                fill_status=str(record.get("fill_status") or ""),
                fill_method=_text(record.get("fill_method")),
                cause_rule=str(record.get("cause_rule") or ""),
                fill_error_m=_float(record.get("fill_error_m")),
                bounds=bounds,
                label_xy=label,
                rings=rings,
            )
        )
    return tuple(holes)


def _read_part_areas(gpkg: Path) -> dict[str, float]:
    if not gpkg.exists():
        return {}
    from ..io.vector import list_layers, read_attributes

    if "hole_parts" not in list_layers(gpkg):
        return {}
    frame = read_attributes(gpkg, "hole_parts", ["category", "shape", "area_m2"])
    if frame is None:
        return {}  # no part: an empty layer
    areas: dict[str, float] = collections.defaultdict(float)
    for category, shape, area in zip(frame["category"], frame["shape"], frame["area_m2"]):
        shape = _text(shape) if category != "closed" else None
        areas[f"{category}{shape}" if shape else str(category)] += float(area)
    return dict(sorted(areas.items()))


def _read_lines(gpkg: Path, layer: str, pixel: float) -> tuple[np.ndarray, ...]:
    if not gpkg.exists():
        return ()
    import shapely

    from ..io.vector import list_layers, read_layer

    if layer not in list_layers(gpkg):
        return ()
    lines = []
    for geometry in read_layer(gpkg, layer).geometry:
        if geometry is None or geometry.is_empty:
            continue
        simple = shapely.simplify(geometry, pixel / 4)
        parts = getattr(simple, "geoms", [simple])
        lines += [np.asarray(part.coords)[:, :2] for part in parts if len(part.coords) >= 2]
    return tuple(lines)


def _read_rings(gpkg: Path, layer: str, pixel: float) -> tuple[np.ndarray, ...]:
    if not gpkg.exists():
        return ()
    import shapely

    from ..io.vector import list_layers, read_layer

    if layer not in list_layers(gpkg):
        return ()
    return tuple(
        ring
        for geometry in read_layer(gpkg, layer).geometry
        if geometry is not None and not geometry.is_empty
        for ring in _rings(shapely.simplify(geometry, pixel / 2))
    )


def _rings(geometry) -> Iterable[np.ndarray]:
    for polygon in getattr(geometry, "geoms", [geometry]):
        if polygon.geom_type != "Polygon" or polygon.is_empty:
            continue
        yield np.asarray(polygon.exterior.coords)[:, :2]
        for interior in polygon.interiors:
            yield np.asarray(interior.coords)[:, :2]
