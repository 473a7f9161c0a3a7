"""Cutting the holes into a survey: removing their points from copies of the input files.

Reads and writes LAS/LAZ (laspy) and writes the cut holes' layer (``cut_holes.gpkg``);
:func:`pixel_indices` and :func:`align` are the lattice arithmetic they share with the
scoring.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import InputDataError
from .placement import CutHole


def pixel_indices(x: np.ndarray, y: np.ndarray, transform: Any) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of points on a north-up raster on the pipeline's absolute lattice.

    The pipeline puts a point in column ``floor(x / res)`` and row
    ``floor(y / res)`` of the global lattice (``pipeline.grid``); a raster's
    transform says where its first pixel is on that lattice.
    """
    resolution = transform.a
    col0 = round(transform.c / resolution)
    row_top = round(transform.f / resolution) - 1
    cols = np.floor(x / resolution).astype(np.int64) - col0
    rows = row_top - np.floor(y / resolution).astype(np.int64)
    return rows, cols


def cut_points(source: str | os.PathLike, target: str | os.PathLike, labels: np.ndarray, transform: Any) -> int:
    """Copy a LAS/LAZ file without the points in the labelled pixels; returns how many were removed."""
    import laspy

    try:
        las = laspy.read(source)
    except Exception as e:  # laspy raises several unrelated types
        raise InputDataError(source, f"cannot be read for cutting: {e}") from None
    rows, cols = pixel_indices(np.asarray(las.x), np.asarray(las.y), transform)
    inside = (rows >= 0) & (rows < labels.shape[0]) & (cols >= 0) & (cols < labels.shape[1])
    remove = np.zeros(len(rows), bool)
    remove[inside] = labels[rows[inside], cols[inside]] > 0
    las.points = las.points[~remove]
    Path(target).parent.mkdir(parents=True, exist_ok=True)
    las.write(str(target), do_compress=Path(target).suffix.lower() == ".laz")
    return int(remove.sum())


def align(array: np.ndarray, transform: Any, to_transform: Any, to_shape: tuple[int, int]) -> np.ndarray:
    """A raster on the same lattice put onto another window of it (NaN where it has no pixel)."""
    resolution = to_transform.a
    dr = round((transform.f - to_transform.f) / resolution)  # rows of `array` above the target's first row
    dc = round((transform.c - to_transform.c) / resolution)
    out = np.full(to_shape, np.nan, np.float64)
    r0, c0 = max(0, dr), max(0, -dc)  # first source row / column inside the target
    tr, tc = max(0, -dr), max(0, dc)  # where it lands
    h = min(array.shape[0] - r0, to_shape[0] - tr)
    w = min(array.shape[1] - c0, to_shape[1] - tc)
    if h > 0 and w > 0:
        out[tr : tr + h, tc : tc + w] = array[r0 : r0 + h, c0 : c0 + w]
    return out


def _write_cut_holes(
    path: Path, labels: np.ndarray, transform: Any, crs_wkt: str, holes: list[CutHole], pixel_size_m: float
) -> None:
    from ...holes.outlines import label_polygons
    from ...io.vector import write_layer

    polygons = label_polygons(labels, transform)
    path.unlink(missing_ok=True)
    records = []
    for hole in holes:
        record = hole.as_dict(pixel_size_m)
        record["bbox_rc"] = ",".join(map(str, record["bbox_rc"]))
        records.append(record)
    write_layer(
        path,
        "cut_holes",
        records,
        [polygons[h.hole_id] for h in holes],
        crs_wkt=crs_wkt,
        geometry_type="MultiPolygon",
    )
