"""Tiny LAS/LAZ files written with laspy for tests (real files, no mocks)."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
from pyproj import CRS


def write_points(
    path: str | Path,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    *,
    classification: np.ndarray | None = None,
    withheld: np.ndarray | None = None,
    version: str = "1.4",
    crs: str | None = "EPSG:2154",
    scale: float = 0.01,
) -> Path:
    """Write points as LAS (``.las``) or LAZ (``.laz``, by suffix): 1.2 -> format 1, 1.4 -> format 6."""
    path = Path(path)
    point_format = 6 if version == "1.4" else 1
    header = laspy.LasHeader(point_format=point_format, version=version)
    header.scales = np.array([scale, scale, scale])
    if len(x):
        header.offsets = np.array([np.floor(np.min(x)), np.floor(np.min(y)), 0.0])
    if crs:
        header.add_crs(CRS.from_user_input(crs))
    las = laspy.LasData(header)
    las.x, las.y, las.z = x, y, z
    if classification is not None:
        las.classification = classification
    if withheld is not None:
        las.withheld = withheld
    las.write(path, do_compress=path.suffix.lower() == ".laz")
    return path


def random_points(rng: np.random.Generator, n: int, bounds=(1000.0, 2000.0, 1100.0, 2080.0)):
    """Points with some empty areas and layered heights, quantised to 1 cm like a LAS file."""
    minx, miny, maxx, maxy = bounds
    x = np.round(rng.uniform(minx, maxx, n), 2)
    y = np.round(rng.uniform(miny, maxy, n), 2)
    z = np.round(50 + 5 * np.sin(x / 9) + rng.gamma(1.0, 3.0, n), 2)
    hole = (x - (minx + 30)) ** 2 + (y - (miny + 30)) ** 2 < 12**2
    return x[~hole], y[~hole], z[~hole]
