"""Assembling the hole products on the client: global holes, causes, outlines, layers.

The per-cell detection results are small (part tables, edge strips, statistics
and part outlines); here they are linked into global holes
(:func:`pipeline.holes.link_holes`), given a cause
(:func:`pipeline.holes.classify_causes`), outlined (parts of one hole are
dissolved along shared cell edges: exact, since outlines follow pixel edges)
and written as the ``holes``, ``hole_parts``, ``vertical_holes`` and ``walls``
layers of ``holes.gpkg`` (docs/outputs.md).
"""

from __future__ import annotations

import collections
from pathlib import Path
from typing import Any

import numpy as np
import shapely

from .holes import CAUSES, CauseRules, classify_causes, link_holes, ring_metrics
from .io.vector import write_layer
from .holes.outlines import hole_outline, merge_outlines, to_world

#: ``holes.outline`` values -> modes of :func:`pipeline.outlines.hole_outline`.
OUTLINE_MODES = {"pixel": "exact", "simplified": "simplified", "straight": "straight"}


def write_hole_layers(path: Path, plan, config, params, detected: list) -> dict[str, Any]:
    """Link, classify and write the hole layers; return the counts for the report.

    ``params`` (:class:`pipeline.tasks.HoleParams`) are the survey-unit parameters the
    cells were detected with; linking and classification use the same ones.
    """
    grid = plan.grid
    unit = plan.survey.horizontal_unit_m
    z_unit = plan.survey.vertical_unit_m
    pixel_size = grid.resolution
    pixel_area_m2 = (pixel_size * unit) ** 2
    holes_config = config.holes
    catalog = link_holes([d.cell_holes for d in detected], min_area_px=params.min_area_px)
    causes = classify_causes(
        catalog.stats, CauseRules.from_config(config, pixel_size_m=pixel_size * unit, vertical_unit_m=z_unit)
    )
    ring = ring_metrics(catalog.stats)

    # outlines (global pixel coordinates): dissolve the parts of each hole, then to world
    part_geometries: dict[tuple[int, int], shapely.Geometry] = {}
    for cell_index, d in enumerate(detected):
        for label, wkb in d.part_outlines.items():
            part_geometries[(cell_index, label)] = shapely.from_wkb(wkb)
    by_hole: dict[int, list] = collections.defaultdict(list)
    for part in catalog.parts:
        geometry = part_geometries.get((int(part["cell"]), int(part["label"])))
        if geometry is not None:
            by_hole[int(part["hole_id"])].append(geometry)

    hole_records, hole_geometries = [], []
    counts_by_cause: collections.Counter = collections.Counter()
    small_voids = int(catalog.settled_small_voids)
    small_void_m2 = float(getattr(catalog, "settled_small_void_px", 0)) * pixel_area_m2
    listed_ids = set()
    for i, hole in enumerate(catalog.holes):
        if hole["is_small"]:
            small_voids += 1
            small_void_m2 += float(hole["area_px"]) * pixel_area_m2
            continue
        hole_id = int(hole["hole_id"])
        listed_ids.add(hole_id)
        geometry = hole_outline(
            merge_outlines(by_hole.get(hole_id, [])), mode=OUTLINE_MODES[holes_config.outline], transform=grid.transform
        )
        cause = str(causes["cause"][i])
        counts_by_cause[cause] += 1
        ring_px = int(catalog.stats["ring_px"][i])
        hole_records.append(
            {
                "hole_id": hole_id,
                "area_m2": float(hole["area_px"]) * pixel_area_m2,
                "perimeter_m": float(catalog.stats["edge_len_px"][i]) * pixel_size * unit,
                "cause": cause,
                "cause_rule": str(causes["rule"][i]),
                "n_parts": int(hole["n_parts"]),
                "n_cells": int(hole["n_cells"]),
                "max_layer": int(hole["max_layer"]),
                "touches_aoi_boundary": bool(hole["touches_aoi_boundary"]),
                "boundary_z_min": _finite(catalog.stats["ring_z_min"][i], ring_px),
                "boundary_z_mean": _finite(ring["mean_z"][i], ring_px),
                "boundary_z_std": _finite(ring["std_z"][i], ring_px),
                "boundary_z_max": _finite(catalog.stats["ring_z_max"][i], ring_px),
                "boundary_jump_px": int(catalog.stats["ring_jump_px"][i]),
                "boundary_px": ring_px,
                "fill_status": "unfilled",
                "fill_method": None,
            }
        )
        hole_geometries.append(geometry)
    crs = grid.crs_wkt
    write_layer(path, "holes", hole_records, hole_geometries, crs_wkt=crs, geometry_type="MultiPolygon")

    # the hierarchy table: one row per cell part of a listed hole
    part_records, part_geometries_out = [], []
    counts_by_type: collections.Counter = collections.Counter()
    parts = catalog.parts
    for index, part in enumerate(parts):
        hole_id = int(part["hole_id"])
        if hole_id not in listed_ids:
            continue
        neighbours = catalog.neighbour_idx[catalog.neighbour_ptr[index] : catalog.neighbour_ptr[index + 1]]
        category = str(part["category"])
        shape = str(part["shape"]) if category != "closed" else ""
        counts_by_type[f"{category}{shape}" if shape else category] += 1
        part_records.append(
            {
                "hole_id": hole_id,
                "cell_id": str(part["cell_id"]),
                "part_label": int(part["label"]),
                "layer": int(part["layer"]),
                "category": category,
                "open": category != "closed",
                "type": category if category in ("I", "II") else None,
                "shape": shape or None,
                "area_m2": float(part["area_px"]) * pixel_area_m2,
                "neighbours": ";".join(f"{parts[j]['cell_id']}:{int(parts[j]['label'])}" for j in neighbours),
            }
        )
        part_geometries_out.append(to_world(part_geometries[(int(part["cell"]), int(part["label"]))], grid.transform))
    write_layer(path, "hole_parts", part_records, part_geometries_out, crs_wkt=crs, geometry_type="MultiPolygon")

    vertical_records, vertical_geometries = [], []
    for d in detected:
        for record in d.vertical_holes:
            record = dict(record)
            vertical_geometries.append(shapely.from_wkb(record.pop("wkb")))
            record["cell_id"] = d.cell_holes.cell.id
            record["area_m2"] = record["pixels"] * pixel_area_m2
            vertical_records.append(record)
    write_layer(path, "vertical_holes", vertical_records, vertical_geometries, crs_wkt=crs, geometry_type="MultiPolygon")

    wall_records, wall_geometries = [], []
    for d in detected:
        for wall in d.walls:
            wall_records.append(
                {
                    "cell_id": d.cell_holes.cell.id,
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
            wall_geometries.append(shapely.LineString([(wall.x0, wall.y0), (wall.x1, wall.y1)]))
    write_layer(path, "walls", wall_records, wall_geometries, crs_wkt=crs, geometry_type="LineString")

    return {
        "listed": len(hole_records),
        "area_m2": round(sum(r["area_m2"] for r in hole_records), 2),
        "by_cause": {cause: counts_by_cause.get(cause, 0) for cause in CAUSES},
        "parts_by_type": dict(sorted(counts_by_type.items())),
        "small_voids": small_voids,
        "small_void_area_m2": round(small_void_m2, 2),
        "min_area_m2": holes_config.min_area_m2,
        "vertical_hole_groups": len(vertical_records),
        "walls": len(wall_records),
        "height_jump_px": int(sum(d.jump_px for d in detected)),
        "aoi_area_m2": round(sum(d.aoi_px for d in detected) * pixel_area_m2, 2),
        "largest": sorted(hole_records, key=lambda r: -r["area_m2"])[:20],
    }



def _finite(value: float, ring_px: int) -> float | None:
    return float(value) if ring_px and np.isfinite(value) else None
