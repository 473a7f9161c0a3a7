"""Read tasks: what one stage-1 task decodes, a whole file or a group of a COPC file's octree nodes.

A LAS/LAZ file is decoded by one task. A COPC file spanning several cells can be
split (``rasterize.copc_split``): its octree nodes no larger than a cell are
grouped by the cell holding their centre, one *cell task* per cell of the file;
the nodes above them (the octree's top levels: a thinned sample of the whole
file) are decoded by one *top task*, which bins nothing but hands each of its
points to the cell task of the cell holding it. Every node with points is
decompressed by exactly one task, so every point is still decoded once, and no
task's raster window spans the whole file: a cell task's bounds are its cell and
its nodes' cubes, clipped to the file's header bounds, and the plan indexes cells
by those bounds.

Pure: plans from the headers and the hierarchies read by the survey scan.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .grid import Grid

if TYPE_CHECKING:
    from .survey.scan import Survey, Tile

#: A COPC node as a read task carries it: byte offset, byte size and point count of its chunk.
Node = tuple[int, int, int]


@dataclass(frozen=True)
class ReadPart:
    """One read task: a whole file (``nodes`` empty) or some nodes of a COPC file.

    Attributes
    ----------
    tile_index : int
        The file (``survey.tiles`` index).
    part, parts : int
        This task's number among the file's tasks (``0`` of ``1`` for a whole file).
    bounds : tuple of float
        Where its points lie, in the survey CRS (the header bounds for a whole file).
    nodes : tuple of Node
        The COPC chunks it decodes, in file order; empty for a whole file (or a cell
        task of a cell holding only top points).
    point_count : int
        Points it decodes (from the header or the hierarchy).
    role : str
        ``"whole"`` (a whole file), ``"top"`` (the octree's top: decodes, hands its
        points to the cell tasks, bins nothing) or ``"cell"``.
    cell : tuple of int, optional
        A cell task's cell, ``(index_x, index_y)``.
    """

    tile_index: int
    part: int
    parts: int
    bounds: tuple[float, float, float, float]
    nodes: tuple[Node, ...]
    point_count: int
    role: str = "whole"
    cell: tuple[int, int] | None = None

    @property
    def is_whole_file(self) -> bool:
        return self.role == "whole"


def plan_reads(survey: Survey, grid: Grid, copc_split: bool | str) -> list[ReadPart]:
    """The read tasks of a survey, file by file in tile order (one per file unless a COPC file is split).

    ``copc_split``: ``True`` splits every COPC file, ``"auto"`` those whose bounds
    meet more than one cell, ``False`` none. A file reprojected while streaming is
    read whole (its node cubes are in another CRS than the cells).
    """
    reads: list[ReadPart] = []
    for tile in survey.tiles:
        octree = tile.header.copc
        split = octree is not None and len(octree.nodes) > 1 and tile.bounds == tile.header.bounds
        if split and copc_split == "auto":
            split = len(grid.cell_indices_under(grid.window_of_bounds(*tile.bounds))) > 1
        if split and copc_split is not False:
            reads.extend(_split_copc(tile, grid))
        else:
            reads.append(ReadPart(tile.index, 0, 1, tile.bounds, (), tile.header.point_count))
    return reads


def _split_copc(tile: Tile, grid: Grid) -> list[ReadPart]:
    """A COPC file's tasks: the top task (nodes larger than a cell), then one task per cell, north-west first."""
    octree = tile.header.copc
    assert octree is not None
    nodes, boxes = octree.nodes, octree.node_bounds()
    split_level = max(0, math.ceil(math.log2(2 * octree.halfsize / (grid.cell_px * grid.resolution))))
    top = nodes["level"] < split_level
    cell_x, cell_y = cell_of(grid, (boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2)
    groups: dict[tuple[int, int], list[int]] = defaultdict(list)
    for i in np.flatnonzero(~top):
        groups[(int(cell_x[i]), int(cell_y[i]))].append(int(i))
    if top.any():  # the top's points may lie in any cell of the file
        for key in grid.cell_indices_under(grid.window_of_bounds(*tile.bounds)):
            groups.setdefault(key, [])
    cells = sorted(groups, key=lambda k: (-k[1], k[0]))
    parts = len(cells) + int(top.any())
    reads = []
    if top.any():
        reads.append(ReadPart(tile.index, 0, parts, tile.bounds, _chunks(nodes[top]), _points(nodes[top]), "top"))
    for key in cells:
        members = groups[key]
        core = grid.window_bounds(grid.cell(*key).window)
        box = np.vstack([boxes[members], np.array([core])])
        bounds = _clip((box[:, 0].min(), box[:, 1].min(), box[:, 2].max(), box[:, 3].max()), tile.bounds)
        chosen = nodes[members]
        reads.append(ReadPart(tile.index, len(reads), parts, bounds, _chunks(chosen), _points(chosen), "cell", key))
    return reads


def cell_of(grid: Grid, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Absolute cell indices ``(index_x, index_y)`` of world points (the lattice formula of :mod:`pipeline.grid`)."""
    col = np.floor(np.asarray(x) / grid.resolution + grid.offset)
    row = np.floor(np.asarray(y) / grid.resolution + grid.offset)
    return np.floor(col / grid.cell_px).astype(np.int64), np.floor(row / grid.cell_px).astype(np.int64)


def _chunks(nodes: np.ndarray) -> tuple[Node, ...]:
    return tuple((int(n["offset"]), int(n["byte_size"]), int(n["point_count"])) for n in nodes)


def _points(nodes: np.ndarray) -> int:
    return int(nodes["point_count"].sum())


def _clip(box: tuple[float, float, float, float], limit: tuple[float, float, float, float]):
    """``box`` inside ``limit`` (points outside the header bounds are never used)."""
    return (
        max(float(box[0]), limit[0]),
        max(float(box[1]), limit[1]),
        min(float(box[2]), limit[2]),
        min(float(box[3]), limit[3]),
    )


__all__ = ["Node", "ReadPart", "cell_of", "plan_reads"]
