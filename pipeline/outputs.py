"""The products of a run: the DSM mosaic, the GeoPackage layers, the manifest.

Writers only: everything here turns kept stage results into files inside the
run's staging folder (``docs/outputs.md`` documents every product and field).
"""

from __future__ import annotations

import collections
import functools
import json
import math
import os
import socket
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from pyproj import CRS

from . import __version__
from .config import Config, config_key, to_dict
from .fill import NOT_FILLED
from .fill.by_cause import FILLED, HoleFill
from .fill.by_cause import UNFILLED as UNFILLED_STATUS
from .holes import CAUSES
from .holes.outlines import hole_outline, merge_outlines, to_world
from .io.raster import NODATA, write_vrt
from .io.vector import write_layer, write_layer_in_parts
from .plan import SurveyPlan
from .stages.bin_tiles import TileResult
from .stages.detect_holes import DetectResult
from .stages.find_walls import WallResult
from .stages.link_holes import HoleSet
from .stages.merge_cells import CellResult
from .stages.registry import RunResults
from .stages.write_rasters import DESCRIPTIONS, WriteResult
from .staging import Staging
from .survey.scan import tile_index_records

#: Products a run moves from the staging folder into OUT (and replaces there).
PRODUCTS = (
    "dsm",
    "dsm.vrt",
    "fill_mask",
    "fill_mask.vrt",
    "fill_distance",
    "fill_distance.vrt",
    "dsm_unfilled",
    "dsm_unfilled.vrt",
    "holes.gpkg",
    "points",
    "manifest.json",
    "report.html",
)

#: Flight-plan products: their number depends on the sorties, so older ones are matched by name.
FLIGHTPLAN_PRODUCTS = (
    "flightplan.gpkg",
    "flightplan*.plan",
    "flightplan*.waypoints",
    "flightplan*.kmz",
    "flightplan*.kml",
)

#: ``holes.outline`` values -> modes of :func:`pipeline.outlines.hole_outline`.
OUTLINE_MODES = {"pixel": "exact", "simplified": "simplified", "straight": "straight"}


@dataclass
class RunSummary:
    """What a run did; also written to ``manifest.json``."""

    out_dir: str
    tiles: int
    cells: int
    points_read: int
    points_used: int
    seconds: float
    stage_seconds: dict[str, float] = field(default_factory=dict)
    skipped: list[dict[str, str]] = field(default_factory=list)
    dsm_tiles: list[str] = field(default_factory=list)
    holes: dict[str, Any] = field(default_factory=dict)
    flightplan: dict[str, Any] = field(default_factory=dict)
    resumed_tasks: int = 0  # tasks an interrupted run had finished, not run again
    point_files: list[str] = field(default_factory=list)  # points/*.laz (output.points)
    reused_tasks: int = 0  # results of unchanged tiles and cells taken from the previous run (incremental)
    heights: dict[str, Any] = field(default_factory=dict)  # elevations or above the ground (survey.ground_level)
    points_outside: int = 0  # points outside their file's header bounds (reprojected or PDAL reads): not used
    stage_client_cpu_seconds: dict[str, float] = field(default_factory=dict)  # CPU of this process per stage lap
    worker_task_seconds: dict[str, dict[str, float]] = field(default_factory=dict)  # Dask stage -> tasks, seconds

    @property
    def points_per_second(self) -> float:
        return self.points_read / self.seconds if self.seconds else 0.0

    @classmethod
    def from_manifest(cls, manifest: dict[str, Any], out_dir: str) -> RunSummary:
        """The summary a finished run wrote into its manifest (a resumed run that only had to commit)."""
        summary, outputs = manifest.get("summary", {}), manifest.get("outputs", {})
        flightplan = dict(manifest.get("flightplan") or {})
        flightplan["files"] = [os.path.join(out_dir, name) for name in outputs.get("flightplan", [])]
        return cls(
            out_dir=out_dir,
            tiles=int(summary.get("tiles", 0)),
            cells=int(summary.get("cells", 0)),
            points_read=int(summary.get("points_read", 0)),
            points_used=int(summary.get("points_used", 0)),
            points_outside=int(summary.get("points_outside", 0)),
            seconds=float(summary.get("seconds", 0.0)),
            stage_seconds=dict(summary.get("stage_seconds", {})),
            skipped=list(manifest.get("skipped", [])),
            dsm_tiles=list(outputs.get("dsm_tiles", [])),
            holes=dict(manifest.get("holes") or {}),
            flightplan=flightplan,
            resumed_tasks=int(summary.get("resumed_tasks", 0)),
            point_files=list(outputs.get("points", [])),
            reused_tasks=int(summary.get("reused_tasks", 0)),
            heights=dict(manifest.get("heights") or {}),
            stage_client_cpu_seconds=dict(summary.get("stage_client_cpu_seconds", {})),
            worker_task_seconds=dict(summary.get("worker_task_seconds", {})),
        )


def write_layers(staging: Staging, plan: SurveyPlan, config: Config, results: RunResults) -> dict[str, Any]:
    """The mosaics and the layers of ``holes.gpkg`` but the walls'; returns the holes' figures (empty
    without hole detection).

    The walls' layers (:func:`write_wall_layers`) come from a stage gathered last: the flight plans
    and the report's maps are made from these products while the workers fit the last walls.
    """
    write_mosaics(staging, plan, results.written)
    gpkg = staging.product("holes.gpkg")
    write_survey_layers(gpkg, plan, results.tiles, results.cells, results.written, results.skipped(plan))
    if results.holes is None:
        return {}
    return write_hole_layers(gpkg, plan, config, results.holes, results.detected, results.fills, results.written)


def run_summary(
    results: RunResults,
    plan: SurveyPlan,
    staging: Staging,
    *,
    holes: dict[str, Any],
    flightplan: dict[str, Any],
    seconds: float,
    stage_seconds: dict[str, float],
    stage_client_cpu_seconds: dict[str, float] | None = None,
    worker_task_seconds: dict[str, dict[str, float]] | None = None,
) -> RunSummary:
    """What the run did, for the manifest and the command's last lines."""
    tiles = results.tiles
    return RunSummary(
        flightplan=flightplan,
        resumed_tasks=results.resumed_tasks,
        reused_tasks=results.reused_tasks,
        holes=holes,
        out_dir=str(staging.out),
        tiles=len(tiles),
        cells=len(results.cells),
        points_read=sum(r.points_read for r in tiles),
        points_used=sum(r.points_used for r in tiles),
        points_outside=sum(r.points_outside for r in tiles),
        seconds=seconds,
        stage_seconds=stage_seconds,
        stage_client_cpu_seconds=stage_client_cpu_seconds or {},
        worker_task_seconds=worker_task_seconds or {},
        skipped=results.skipped(plan),
        dsm_tiles=sorted(os.path.relpath(r.paths["dsm"], staging.root) for r in results.written if r.paths),
        point_files=list(results.points),
        heights=results.ground.as_record(),
    )


def write_mosaics(staging: Staging, plan: SurveyPlan, written: Sequence[WriteResult]) -> None:
    """One VRT per raster product over its cell tiles (none when no cell holds a point)."""
    grid = plan.grid
    cells = plan.cell_by_id()
    products = sorted({product for r in written for product in r.paths})
    filled = any("fill_mask" in r.paths for r in written)
    for product in products:
        sources = []
        for r in written:
            if product in r.paths:
                w = cells[r.cell_id].window
                sources.append((r.paths[product], w.row_off, w.col_off, w.height, w.width))
        byte = product == "fill_mask"
        write_vrt(
            staging.product(f"{product}.vrt"),
            sources,
            width=grid.width,
            height=grid.height,
            transform=grid.transform,
            crs_wkt=grid.crs_wkt,
            dtype="Byte" if byte else "Float32",
            nodata=NOT_FILLED if byte else NODATA,
            description=DESCRIPTIONS["dsm_filled" if product == "dsm" and filled else product],
        )


def write_survey_layers(
    gpkg: Path,
    plan: SurveyPlan,
    tile_results: Sequence[TileResult],
    cell_results: Sequence[CellResult],
    written: Sequence[WriteResult],
    skipped: list[dict[str, str]],
) -> None:
    """The ``tiles``, ``cells`` and ``survey_area`` layers."""
    grid = plan.grid
    done = {r.tile_index: r for r in tile_results}
    skipped_paths = {s["path"] for s in skipped}
    tile_records, tile_geometries = [], []
    for record in tile_index_records(plan.survey):
        bounds: Any = record.pop("bounds")
        result = done.get(int(record["tile_id"]))  # type: ignore[call-overload]
        record["points_used"] = result.points_used if result else 0
        record["status"] = (
            ("ok" if result.points_used else "no points")
            if result
            else ("skipped" if record["path"] in skipped_paths else "failed")
        )
        tile_records.append(record)
        tile_geometries.append(shapely.box(*bounds))
    write_layer(gpkg, "tiles", tile_records, tile_geometries, crs_wkt=grid.crs_wkt, geometry_type="Polygon")
    cells = plan.cell_by_id()
    dsm_files = {w.cell_id: w.paths.get("dsm") for w in written}
    cell_records, cell_geometries = [], []
    for r in cell_results:
        cell = cells[r.cell_id]
        dsm_path = dsm_files.get(r.cell_id)
        cell_records.append(
            {
                "cell_id": cell.id,
                "index_x": cell.index_x,
                "index_y": cell.index_y,
                "row_off": cell.window.row_off,
                "col_off": cell.window.col_off,
                "width_px": cell.window.width,
                "height_px": cell.window.height,
                "points": r.points,
                "empty_pixels": r.empty_pixels,
                "empty_fraction": r.empty_pixels / r.pixels if r.pixels else 0.0,
                "dsm_file": os.path.relpath(dsm_path, gpkg.parent) if dsm_path else None,
            }
        )
        cell_geometries.append(shapely.box(*grid.window_bounds(cell.window)))
    write_layer(gpkg, "cells", cell_records, cell_geometries, crs_wkt=grid.crs_wkt, geometry_type="Polygon")
    failed = [i for i in range(len(plan.survey.tiles)) if i not in done]
    write_survey_area_layer(gpkg, plan, failed)


def write_survey_area_layer(gpkg: Path, plan: SurveyPlan, failed: list[int]) -> None:
    """The ``survey_area`` layer: the area (status ``inside``), then the skipped tiles' areas (``skipped``: exterior)."""
    area = plan.area
    source = area.source if area is not None else ("--aoi polygon" if plan.aoi_given else "union of tile extents")
    records: list[dict[str, Any]] = [{"status": "inside", "source": source}]
    geometries = [plan.area_without(failed)]
    for i in failed:
        records.append({"status": "skipped", "source": plan.survey.tiles[i].name})
        geometries.append(plan.tile_footprint(i))
    for bounds in area.skipped_squares if area is not None else ():
        records.append({"status": "skipped", "source": "a tile skipped at the scan (placed by its name)"})
        geometries.append(shapely.box(*bounds))
    write_layer(gpkg, "survey_area", records, geometries, crs_wkt=plan.grid.crs_wkt)


_INT, _FLOAT, _TEXT, _BOOL = "int64", "float64", "object", "bool"

#: The fields of each hole layer, written also when a layer has no feature (docs/outputs.md).
LAYER_FIELDS: dict[str, dict[str, str]] = {
    "holes": {
        "hole_id": _INT,
        "area_m2": _FLOAT,
        "perimeter_m": _FLOAT,
        "cause": _TEXT,
        "cause_rule": _TEXT,
        "n_parts": _INT,
        "n_cells": _INT,
        "max_layer": _INT,
        "touches_aoi_boundary": _BOOL,
        "boundary_z_min": _FLOAT,
        "boundary_z_mean": _FLOAT,
        "boundary_z_std": _FLOAT,
        "boundary_z_max": _FLOAT,
        "boundary_jump_px": _INT,
        "boundary_px": _INT,
        "azimuth_deg": _FLOAT,
        "fill_status": _TEXT,
        "fill_method": _TEXT,
        "fill_error_m": _FLOAT,
        "fill_max_distance_m": _FLOAT,
        "fill_note": _TEXT,
    },
    "hole_parts": {
        "hole_id": _INT,
        "cell_id": _TEXT,
        "part_label": _INT,
        "layer": _INT,
        "category": _TEXT,
        "open": _BOOL,
        "type": _TEXT,
        "shape": _TEXT,
        "area_m2": _FLOAT,
        "neighbours": _TEXT,
    },
    "vertical_holes": {
        "pixels": _INT,
        "max_height_range": _FLOAT,
        "missing_voxels": _INT,
        "top": _FLOAT,
        "cell_id": _TEXT,
        "area_m2": _FLOAT,
    },
    "walls": {
        "cell_id": _TEXT,
        "bottom": _FLOAT,
        "top": _FLOAT,
        "height": _FLOAT,
        "length_m": _FLOAT,
        "fit_rms": _FLOAT,
        "edge_width_px": _FLOAT,
        "support_px": _INT,
        "jump_px": _INT,
    },
    "flight_lines": {
        "point_source_id": _INT,
        "pass": _INT,
        "method": _TEXT,
        "height_assumed": _BOOL,
        "start_time": _FLOAT,
        "end_time": _FLOAT,
        "azimuth_deg": _FLOAT,
        "flying_height": _FLOAT,
        "swath_left": _FLOAT,
        "swath_right": _FLOAT,
        "max_scan_angle_deg": _FLOAT,
        "points": _INT,
        "judged": _BOOL,
    },
}
LAYER_FIELDS["swaths"] = LAYER_FIELDS["flight_lines"]


def write_hole_layers(
    gpkg: Path,
    plan: SurveyPlan,
    config: Config,
    holes: HoleSet,
    detected: Sequence[DetectResult],
    fills: Sequence[HoleFill] | None = None,
    written: Sequence[WriteResult] | None = None,
) -> dict[str, Any]:
    """The ``holes``, ``hole_parts``, ``flight_lines`` and ``swaths`` layers; returns the report's counts.

    ``written``: the writer stage's results, whose filled pixels (those of ``fill_mask``)
    the fill figures add up.
    """
    crs = plan.grid.crs_wkt
    part_outlines = {
        (cell_index, label): shapely.from_wkb(wkb)
        for cell_index, d in enumerate(detected)
        for label, wkb in d.part_outlines.items()
    }
    hole_records, hole_geometries = _hole_records(plan, config, holes, part_outlines, fills)
    listed = {r["hole_id"] for r in hole_records}
    part_records, part_geometries, counts_by_type = _part_records(plan, holes, part_outlines, listed)
    line_records, line_geometries, swath_geometries = _flight_line_records(holes)
    for layer, records, geometries, geometry_type in (
        ("holes", hole_records, hole_geometries, "MultiPolygon"),
        ("hole_parts", part_records, part_geometries, "MultiPolygon"),
        ("flight_lines", line_records, line_geometries, "LineString Z"),
        ("swaths", line_records, swath_geometries, "MultiPolygon"),
    ):
        write_layer(
            gpkg, layer, records, geometries, crs_wkt=crs, geometry_type=geometry_type, fields=LAYER_FIELDS[layer]
        )
    catalog = holes.catalog
    counts_by_cause = collections.Counter(r["cause"] for r in hole_records)
    return {
        "listed": len(hole_records),
        "area_m2": round(sum(r["area_m2"] for r in hole_records), 2),
        "by_cause": {cause: counts_by_cause.get(cause, 0) for cause in CAUSES},
        "parts_by_type": dict(sorted(counts_by_type.items())),
        "small_voids": catalog.small_void_count,
        "small_void_area_m2": round(catalog.small_void_px * plan.pixel_area_m2, 2),
        "min_area_m2": plan.hole_params.min_area_m2,
        "min_area_source": "auto" if config.holes.min_area_m2 == "auto" else "set",
        "sampling_gap_width_m": round(plan.hole_params.sampling_gap_px * plan.pixel_size_m, 4),
        "sampling_gaps": holes.sampling_gaps,
        "sampling_gap_area_m2": round(holes.sampling_gap_px * plan.pixel_area_m2, 2),
        "aoi_area_m2": round(sum(d.aoi_px for d in detected) * plan.pixel_area_m2, 2),
        "assumed_heights": _assumed_heights(holes, config),
        "largest": sorted(hole_records, key=lambda r: -r["area_m2"])[:20],
        "fill": _fill_counts(plan, catalog, fills, listed, written or []) if fills is not None else {},
    }


#: Features of a wall layer written at a time (a part of :func:`~.io.vector.write_layer_in_parts`).
WALL_LAYER_PART = 25_000


def write_wall_layers(gpkg: Path, plan: SurveyPlan, walls: Sequence[WallResult]) -> dict[str, int]:
    """The ``vertical_holes`` and ``walls`` layers, from each cell's walls and vertical holes; returns their counts
    (for the report's figures beside :func:`write_hole_layers`'s).

    Written a few cells at a time, so that only those cells' records and outlines are
    built at once (a 1 B point survey's 209,208 vertical holes were the client's largest
    moment, 500 MB over what it held before)."""
    crs = plan.grid.crs_wkt
    for layer, geometry_type in (("vertical_holes", "MultiPolygon"), ("walls", "LineString")):
        records_of = _vertical_records if layer == "vertical_holes" else _wall_records
        parts = (records_of(plan, group) for group in _cell_groups(walls, layer))
        write_layer_in_parts(gpkg, layer, parts, crs_wkt=crs, geometry_type=geometry_type, fields=LAYER_FIELDS[layer])
    return {  # a record per vertical-hole group and per wall
        "vertical_hole_groups": sum(len(w.vertical_holes) for w in walls),
        "walls": sum(len(w.walls) for w in walls),
        "height_jump_px": int(sum(w.jump_px for w in walls)),
    }


def _cell_groups(walls: Sequence[WallResult], layer: str) -> Iterator[list[WallResult]]:
    """The cells' results in order, in groups of about :data:`WALL_LAYER_PART` features of ``layer``."""
    group: list[WallResult] = []
    features = 0
    for w in walls:
        group.append(w)
        features += len(w.vertical_holes) if layer == "vertical_holes" else len(w.walls)
        if features >= WALL_LAYER_PART:
            yield group
            group, features = [], 0
    if group:
        yield group


def with_wall_counts(hole_summary: dict[str, Any], wall_counts: dict[str, int]) -> dict[str, Any]:
    """The holes' figures with :func:`write_wall_layers`'s counts, where the report and the manifest have
    always listed them (after the sampling gaps)."""
    merged: dict[str, Any] = {}
    for key, value in hole_summary.items():
        merged[key] = value
        if key == "sampling_gap_area_m2":
            merged.update(wall_counts)
    merged.update({k: v for k, v in wall_counts.items() if k not in merged})
    return merged


def _assumed_heights(holes: HoleSet, config: Config) -> dict | None:
    """Where the sensor's heights are assumed (single returns, no scan angles): the field of view they
    come from, and whether the survey's shadows gave it (docs/holes.md); None where they are measured."""
    geometry = holes.geometry
    if geometry is None or not geometry.heights_assumed:
        return None
    from_shadows = geometry.fov_from_shadows is not None
    fov = geometry.fov_from_shadows if from_shadows else config.sensor.nominal_fov_deg
    return {"field_of_view_deg": fov, "from": "shadows" if from_shadows else "sensor.nominal_fov_deg"}


def _hole_records(
    plan: SurveyPlan, config: Config, holes: HoleSet, part_outlines: dict, fills: Sequence[HoleFill] | None
) -> tuple[list, list]:
    """One record per listed hole, with its outline dissolved from its parts (exact: pixel edges)."""
    fill_of = {f.hole_id: f for f in fills or []}
    catalog, causes, ring = holes.catalog, holes.causes, holes.ring
    by_hole: dict[int, list] = collections.defaultdict(list)
    for part in catalog.parts:
        geometry = part_outlines.get((int(part["cell"]), int(part["label"])))
        if geometry is not None:
            by_hole[int(part["hole_id"])].append(geometry)
    stats = catalog.stats
    records, geometries = [], []
    for i, hole in enumerate(catalog.holes):
        if hole["is_small"]:
            continue
        hole_id = int(hole["hole_id"])
        ring_px = int(stats["ring_px"][i])
        records.append(
            {
                "hole_id": hole_id,
                "area_m2": float(hole["area_px"]) * plan.pixel_area_m2,
                "perimeter_m": float(stats["edge_len_px"][i]) * plan.grid.resolution * plan.survey.horizontal_unit_m,
                "cause": str(causes["cause"][i]),
                "cause_rule": str(causes["rule"][i]),
                "n_parts": int(hole["n_parts"]),
                "n_cells": int(hole["n_cells"]),
                "max_layer": int(hole["max_layer"]),
                "touches_aoi_boundary": bool(hole["touches_aoi_boundary"]),
                "boundary_z_min": _finite(stats["ring_z_min"][i], ring_px),
                "boundary_z_mean": _finite(ring["mean_z"][i], ring_px),
                "boundary_z_std": _finite(ring["std_z"][i], ring_px),
                "boundary_z_max": _finite(stats["ring_z_max"][i], ring_px),
                "boundary_jump_px": int(stats["ring_jump_px"][i]),
                "boundary_px": ring_px,
                "azimuth_deg": _finite(holes.azimuth_deg[i], 1),
                **_fill_fields(fill_of.get(hole_id), plan),
            }
        )
        geometries.append(
            hole_outline(
                merge_outlines(by_hole.get(hole_id, [])),
                mode=OUTLINE_MODES[config.holes.outline],
                transform=plan.grid.transform,
            )
        )
    return records, geometries


def _fill_fields(fill: HoleFill | None, plan: SurveyPlan) -> dict[str, Any]:
    """The ``holes`` layer's fill fields: status, method, error estimate and reach, in metres."""
    if fill is None:
        return {
            "fill_status": UNFILLED_STATUS,
            "fill_method": None,
            "fill_error_m": None,
            "fill_max_distance_m": None,
            "fill_note": None,
        }
    return {
        "fill_status": fill.status,
        "fill_method": fill.method,
        "fill_error_m": _finite(fill.error_estimate * plan.survey.vertical_unit_m, 1),
        "fill_max_distance_m": _finite(fill.max_distance * plan.survey.horizontal_unit_m, 1),
        "fill_note": fill.detail or None,
    }


def _fill_counts(
    plan: SurveyPlan, catalog, fills: Sequence[HoleFill], listed: set[int], written: Sequence[WriteResult]
) -> dict[str, Any]:
    """Fill figures for the manifest and the report: holes and pixels by status and method.

    ``filled_area_m2`` is what ``fill_mask`` holds (the writer counts its filled pixels
    per cell core), split into the listed holes and the small voids (those under the
    minimum area, sampling gaps, and the small voids closed inside a cell, which the
    writer fills itself).
    """
    by_status = collections.Counter(f.status for f in fills)
    by_method = collections.Counter(f.method for f in fills if f.status == FILLED)
    area = {int(h["hole_id"]): float(h["area_px"]) for h in catalog.holes}
    skipped_m2 = sum(area.get(f.hole_id, 0.0) for f in fills if f.status != FILLED) * plan.pixel_area_m2
    listed_px = sum(f.pixels for f in fills if f.hole_id in listed)
    filled_px = sum(r.filled_px for r in written) if written else sum(f.pixels for f in fills)
    return {
        "holes_by_status": dict(sorted(by_status.items())),
        "holes_by_method": dict(sorted(by_method.items())),
        "filled_area_m2": round(filled_px * plan.pixel_area_m2, 2),
        "filled_holes_area_m2": round(listed_px * plan.pixel_area_m2, 2),
        "filled_small_voids_area_m2": round(max(filled_px - listed_px, 0) * plan.pixel_area_m2, 2),
        "skipped_area_m2": round(skipped_m2, 2),
    }


def _part_records(plan: SurveyPlan, holes: HoleSet, part_outlines: dict, listed: set[int]):
    """The hierarchy table: one row per cell part of a listed hole."""
    catalog = holes.catalog
    parts = catalog.parts
    records, geometries = [], []
    counts_by_type: collections.Counter = collections.Counter()
    for index, part in enumerate(parts):
        if int(part["hole_id"]) not in listed:
            continue
        neighbours = catalog.neighbour_idx[catalog.neighbour_ptr[index] : catalog.neighbour_ptr[index + 1]]
        category = str(part["category"])
        shape = str(part["shape"]) if category != "closed" else ""
        counts_by_type[f"{category}{shape}" if shape else category] += 1
        records.append(
            {
                "hole_id": int(part["hole_id"]),
                "cell_id": str(part["cell_id"]),
                "part_label": int(part["label"]),
                "layer": int(part["layer"]),
                "category": category,
                "open": category != "closed",
                "type": category if category in ("I", "II") else None,
                "shape": shape or None,
                "area_m2": float(part["area_px"]) * plan.pixel_area_m2,
                "neighbours": ";".join(f"{parts[j]['cell_id']}:{int(parts[j]['label'])}" for j in neighbours),
            }
        )
        geometries.append(to_world(part_outlines[(int(part["cell"]), int(part["label"]))], plan.grid.transform))
    return records, geometries, counts_by_type


def _flight_line_records(holes: HoleSet) -> tuple[list, list, list]:
    """The ``flight_lines`` (the sensor's trajectory, with heights) and ``swaths`` layers: one feature per line."""
    geometry = holes.geometry
    if geometry is None:
        return [], [], []
    records, tracks, swaths = [], [], []
    for line, swath in zip(geometry.lines, geometry.swaths):
        records.append(
            {
                "point_source_id": line.line,
                "pass": line.part,
                "method": line.method,
                "height_assumed": line.method == "nominal",
                "start_time": float(line.times[0]),
                "end_time": float(line.times[-1]),
                "azimuth_deg": round(line.azimuth_deg, 2),
                "flying_height": round(line.flying_height, 2),
                "swath_left": round(line.half_width_left, 2),
                "swath_right": round(line.half_width_right, 2),
                "max_scan_angle_deg": None if math.isnan(line.max_scan_angle_deg) else line.max_scan_angle_deg,
                "points": line.points,
                "judged": geometry.complete,
            }
        )
        track = line.sensor if len(line.sensor) > 1 else np.vstack([line.sensor, line.sensor])
        tracks.append(shapely.LineString(track))
        swaths.append(shapely.MultiPolygon([swath]) if swath.geom_type == "Polygon" else swath)
    return records, tracks, swaths


def _vertical_records(plan: SurveyPlan, walls: Sequence[WallResult]) -> tuple[list, list]:
    records, outlines = [], []
    for w in walls:
        for record in w.vertical_holes:
            record = dict(record)
            outlines.append(record.pop("wkb"))
            record["cell_id"] = w.cell_id
            record["area_m2"] = record["pixels"] * plan.pixel_area_m2
            records.append(record)
    # the outlines read in one call: one call per outline was 0.35 s of the 211 M-point run's 44,796
    return records, list(shapely.from_wkb(np.array(outlines, dtype=object))) if outlines else []


def _wall_records(plan: SurveyPlan, walls: Sequence[WallResult]) -> tuple[list, list]:
    unit = plan.survey.horizontal_unit_m
    records, geometries = [], []
    for w in walls:
        for wall in w.walls:
            records.append(
                {
                    "cell_id": w.cell_id,
                    "bottom": wall.bottom,
                    "top": wall.top,
                    "height": wall.height,
                    "length_m": wall.length * unit,
                    "fit_rms": wall.rms,
                    "edge_width_px": wall.width_px,
                    "support_px": wall.n_support,
                    "jump_px": wall.n_jump_px,
                }
            )
            geometries.append(shapely.LineString([(wall.x0, wall.y0), (wall.x1, wall.y1)]))
    return records, geometries


def _finite(value: float, ring_px: int) -> float | None:
    return float(value) if ring_px and np.isfinite(value) else None


def _survey_area_record(plan: SurveyPlan) -> dict[str, object]:
    """What the manifest records of the survey area: its source and the tile grid, if any."""
    area = plan.area
    if area is None:
        return {"source": "--aoi polygon" if plan.aoi_given else "union of tile extents"}
    grid = area.tile_grid
    return {
        "source": area.source,
        "tile_grid": grid.as_record() if grid is not None else None,
        "missing_tiles": [list(b) for b in area.missing_tiles],
        "skipped_squares": [list(b) for b in area.skipped_squares],
    }


def write_manifest(
    path: Path,
    summary: RunSummary,
    plan: SurveyPlan,
    config: Config,
    results: RunResults,
    *,
    outputs: list[dict[str, Any]] | None = None,
) -> dict:
    """``manifest.json``: the resolved configuration, inputs, outputs and figures of the run.

    ``results.inputs``: size, modification time and SHA-256 of each input file, by path;
    ``outputs``: path, size and SHA-256 of each product file (the report and the
    manifest itself excepted).
    """
    grid = plan.grid
    inputs, tile_results, cell_results = results.inputs, results.tiles, results.cells
    headers = {t.path: t for t in plan.survey.tiles}
    manifest = {
        "complete": True,  # written last: a manifest in OUT means one complete result (pipeline.staging)
        "config_key": config_key(config),  # a later run with another configuration is refused unless --overwrite
        "holefill_version": __version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "host": socket.gethostname(),
        "config": to_dict(config),
        "crs": {"wkt": grid.crs_wkt, "name": CRS.from_wkt(grid.crs_wkt).name},
        "grid": {
            "resolution": grid.resolution,
            "resolution_unit_m": plan.survey.horizontal_unit_m,
            "width": grid.width,
            "height": grid.height,
            "bounds": grid.bounds,
            "cell_px": grid.cell_px,
            "halo_px": grid.halo_px,
            "align": plan.sizing.align,
            "sizing": plan.sizing.as_record(),
        },
        "inputs": [_input_entry(r, headers[r.path], inputs.get(r.path, {})) for r in tile_results],
        "skipped": summary.skipped,
        "survey_area": _survey_area_record(plan),
        "heights": summary.heights,
        "outputs": {
            "dsm_vrt": "dsm.vrt" if summary.dsm_tiles else None,
            "dsm_tiles": summary.dsm_tiles,
            "holes_gpkg": "holes.gpkg",
            "points": summary.point_files,
            "flightplan": [os.path.basename(f) for f in summary.flightplan.get("files", [])],
            "files": outputs or [],
        },
        "summary": {
            "tiles": summary.tiles,
            "cells": summary.cells,
            "points_read": summary.points_read,
            "points_used": summary.points_used,
            "points_outside": summary.points_outside,
            "seconds": round(summary.seconds, 3),
            "points_per_second": round(summary.points_per_second),
            "stage_seconds": {k: round(v, 3) for k, v in summary.stage_seconds.items()},
            "stage_client_cpu_seconds": {k: round(v, 3) for k, v in summary.stage_client_cpu_seconds.items()},
            "worker_task_seconds": {
                k: {"tasks": int(v["tasks"]), "seconds": round(v["seconds"], 3)}
                for k, v in summary.worker_task_seconds.items()
            },
            "empty_pixels": sum(r.empty_pixels for r in cell_results),
            "resumed_tasks": summary.resumed_tasks,
            "reused_tasks": summary.reused_tasks,
        },
        "holes": summary.holes,
        "flightplan": {k: v for k, v in summary.flightplan.items() if k != "files"},
    }
    path.write_text(json.dumps(manifest, indent=2, default=str))
    return manifest


def _input_entry(result: TileResult, tile: Any, record: dict[str, Any]) -> dict[str, Any]:
    """One input of the manifest: the file (size, time, checksum), its header and what was read."""
    header = tile.header
    return {
        "path": result.path,
        "bytes": record.get("bytes", header.file_size),
        "mtime": record.get("mtime"),
        "sha256": record.get("sha256"),
        "format": header.format,
        "header_points": header.point_count,
        "crs": _crs_name(tile.source_crs_wkt) if tile.source_crs_wkt else None,
        "points_read": result.points_read,
        "points_used": result.points_used,
        "seconds": round(result.seconds, 3),
        "read_tasks": result.read_tasks,
    }


@functools.lru_cache(maxsize=64)
def _crs_name(wkt: str) -> str:
    return CRS.from_wkt(wkt).name
