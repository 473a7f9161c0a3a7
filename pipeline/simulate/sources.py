"""Real terrains to simulate scans over: the registry :data:`TERRAINS` and :func:`load_terrain`.

Each entry names files of ``../shared/data`` (see its PROVENANCE.md), the CRS to use when
the files carry none, the terrain cell size (about the files' point spacing) and the size
of the scene: small files are mirrored (:func:`.terrain.mirror_terrain`) to it, large ones
cropped to their middle. The scene's lower-left corner is the file's, moved down to a
multiple of :data:`SCENE_ORIGIN_STEP_M`, so that tiles of every standard size (100, 125,
200, 250 m) and pixels of every standard size lie on their lattices.
"""

from __future__ import annotations

import math
import os
import pathlib
from dataclasses import dataclass

import numpy as np

from .terrain import Terrain, mirror_terrain, terrain_from_points

#: The scene's corner lies on multiples of this (metres): a common multiple of the tile sizes.
SCENE_ORIGIN_STEP_M = 1000.0


@dataclass(frozen=True)
class TerrainSource:
    """A real survey to build a terrain from.

    Attributes
    ----------
    files : tuple of str
        File names under the data folder (merged).
    description : str
    crs : str
        CRS to use when the files carry none ("" to read it from the first file).
    cell_m : float
        Terrain cell size.
    scene_m : float
        Side of the square scene (a multiple of 100 and 125 m is safest: 500 m; 400 m
        takes 100 and 200 m tiles).
    """

    files: tuple[str, ...]
    description: str
    crs: str = ""
    cell_m: float = 0.5
    scene_m: float = 400.0


#: The terrains the benchmarks draw from; keys are the names ``--terrains`` takes.
TERRAINS: dict[str, TerrainSource] = {
    "delft": TerrainSource(
        ("ahn3_delft_1.laz",), "AHN3 Delft: dense urban, canals (class 9 + voids)", crs="EPSG:28992", scene_m=400.0
    ),
    "bcts": TerrainSource(
        ("lasr_bcts_2.laz", "lasr_bcts_3.laz"), "BC forest on a slope (2 tiles merged)", scene_m=400.0
    ),
    "topography": TerrainSource(
        ("lidr_topography.laz",), "hilly forest with lakes (class 9), 1 pt/m2", cell_m=1.0, scene_m=500.0
    ),
    "amsterdam": TerrainSource(
        ("ahn_amsterdam_2386_9702.laz",), "AHN Amsterdam: a large building and trees", crs="EPSG:28992", scene_m=200.0
    ),
    "ign_water": TerrainSource(("ign_crop2_water.laz",), "IGN: trees and a river corner (class 9)", scene_m=200.0),
    "ign_bat": TerrainSource(("ign_bat.laz",), "IGN: a long building and trees", scene_m=200.0),
}


def load_terrain(name: str, data_dir: str | os.PathLike, *, scene_m: float | None = None) -> Terrain:
    """Read the files of ``TERRAINS[name]`` and make the scene's terrain.

    Parameters
    ----------
    name : str
        A key of :data:`TERRAINS`.
    data_dir : path-like
        The folder holding the files (``../shared/data``).
    scene_m : float, optional
        Side of the square scene; default the entry's ``scene_m``.

    Returns
    -------
    Terrain
        Square, ``scene_m`` wide, its lower-left corner on multiples of
        :data:`SCENE_ORIGIN_STEP_M`, in the source's CRS.
    """
    if name not in TERRAINS:
        raise ValueError(f"unknown terrain {name!r}; choose from {sorted(TERRAINS)}")
    source = TERRAINS[name]
    paths = [pathlib.Path(data_dir) / file_name for file_name in source.files]
    points = read_points(paths)
    crs = source.crs or file_crs(paths[0])
    cell = source.cell_m
    x0, y0, x1, y1 = footprint_box(points["x"], points["y"])
    # the cells lie inside the data's footprint (no half-empty border cells)
    bounds = (
        math.ceil(x0 / cell) * cell,
        math.ceil(y0 / cell) * cell,
        math.floor(x1 / cell) * cell,
        math.floor(y1 / cell) * cell,
    )
    terrain = terrain_from_points(
        points["x"], points["y"], points["z"], points["classification"], cell_m=cell, bounds=bounds, name=name, crs=crs
    )
    side = float(scene_m or source.scene_m)
    scene = mirror_terrain(terrain, width_m=side, height_m=side)
    return scene.moved_to(
        math.floor(bounds[0] / SCENE_ORIGIN_STEP_M) * SCENE_ORIGIN_STEP_M,
        math.floor(bounds[1] / SCENE_ORIGIN_STEP_M) * SCENE_ORIGIN_STEP_M,
    )


def read_points(paths: list[pathlib.Path]) -> dict[str, np.ndarray]:
    """x, y, z and classification of every point of the files (``pipeline.io.las``)."""
    from ..io.las import iter_point_chunks

    parts: dict[str, list[np.ndarray]] = {"x": [], "y": [], "z": [], "classification": []}
    for path in paths:
        for chunk in iter_point_chunks(path, 1_000_000):
            x, y, z = chunk.coordinates()
            parts["x"].append(x)
            parts["y"].append(y)
            parts["z"].append(z)
            parts["classification"].append(np.asarray(chunk.classification))
    return {key: np.concatenate(values) for key, values in parts.items()}


def file_crs(path: pathlib.Path) -> str:
    """The file's CRS as ``EPSG:<code>`` when it has one, else its WKT ("" without a CRS)."""
    import pyproj

    from ..io.las import read_header

    wkt = read_header(path).crs_wkt
    if not wkt:
        return ""
    code = pyproj.CRS.from_wkt(wkt).to_epsg()
    return f"EPSG:{code}" if code else wkt


def footprint_box(
    x: np.ndarray, y: np.ndarray, *, block_m: float = 5.0, min_fill: float = 0.9
) -> tuple[float, float, float, float]:
    """The largest box, shrunk from the points' bounding box, whose edge rows and columns of
    ``block_m`` blocks are at least ``min_fill`` occupied (drops ragged file edges)."""
    x0, y0 = float(np.min(x)), float(np.min(y))
    cols = np.floor((x - x0) / block_m).astype(np.int64)
    rows = np.floor((y - y0) / block_m).astype(np.int64)
    occupied = np.zeros((rows.max() + 1, cols.max() + 1), bool)
    occupied[rows, cols] = True
    r0, c0, r1, c1 = 0, 0, occupied.shape[0], occupied.shape[1]
    while r1 - r0 > 2 and c1 - c0 > 2:
        box = occupied[r0:r1, c0:c1]
        edges = [box[0].mean(), box[-1].mean(), box[:, 0].mean(), box[:, -1].mean()]
        worst = int(np.argmin(edges))
        if edges[worst] >= min_fill:
            break
        r0, r1, c0, c1 = r0 + (worst == 0), r1 - (worst == 1), c0 + (worst == 2), c1 - (worst == 3)
    # partly occupied outermost blocks: step in by one block where the box was shrunk
    x_min = x0 + c0 * block_m if c0 else x0
    y_min = y0 + r0 * block_m if r0 else y0
    x_max = x0 + c1 * block_m if c1 < occupied.shape[1] else float(np.max(x))
    y_max = y0 + r1 * block_m if r1 < occupied.shape[0] else float(np.max(y))
    return x_min, y_min, x_max, y_max
