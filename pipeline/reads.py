"""Read tasks: what one stage-1 task decodes, a whole file or a group of a COPC file's octree nodes.

A LAS/LAZ file is decoded by one task. A COPC file spanning several cells can be
split (``rasterize.copc_split``): its octree nodes no larger than a cell are
grouped by the cell holding their centre, one task per group, and the nodes
above them (the octree's top levels: a thinned sample of the whole file) form
one more task. Every node with points belongs to exactly one task, so every
point is still decoded once; a task's bounds are its nodes' cubes clipped to the
file's header bounds, and the plan indexes cells by those bounds.

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
    from .survey import Survey, Tile

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
        The COPC chunks it decodes, in file order; empty: every point of the file.
    point_count : int
        Points it decodes (from the header or the hierarchy).
    """

    tile_index: int
    part: int
    parts: int
    bounds: tuple[float, float, float, float]
    nodes: tuple[Node, ...]
    point_count: int

    @property
    def is_whole_file(self) -> bool:
        return not self.nodes


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
    """A COPC file's nodes, grouped: the nodes no larger than a cell by the cell of their centre, the rest together."""
    octree = tile.header.copc
    assert octree is not None
    nodes = octree.nodes
    boxes = octree.node_bounds()
    cell_side = grid.cell_px * grid.resolution
    split_level = max(0, math.ceil(math.log2(2 * octree.halfsize / cell_side)))
    centre_x, centre_y = (boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2
    cell_x = np.floor(np.floor(centre_x / grid.resolution + grid.offset) / grid.cell_px).astype(np.int64)
    cell_y = np.floor(np.floor(centre_y / grid.resolution + grid.offset) / grid.cell_px).astype(np.int64)
    top = nodes["level"] < split_level
    groups: dict[tuple[int, int], list[int]] = defaultdict(list)
    for i in np.flatnonzero(~top):
        groups[(int(cell_y[i]), int(cell_x[i]))].append(int(i))
    ordered = ([list(np.flatnonzero(top))] if top.any() else []) + [
        groups[key] for key in sorted(groups, key=lambda k: (-k[0], k[1]))
    ]
    parts = []
    for part, members in enumerate(ordered):
        chosen = nodes[members]
        box = boxes[members]
        bounds = _clip(
            (float(box[:, 0].min()), float(box[:, 1].min()), float(box[:, 2].max()), float(box[:, 3].max())),
            tile.bounds,
        )
        chunks = tuple((int(n["offset"]), int(n["byte_size"]), int(n["point_count"])) for n in chosen)
        parts.append(ReadPart(tile.index, part, len(ordered), bounds, chunks, int(chosen["point_count"].sum())))
    return parts


def _clip(box: tuple[float, float, float, float], limit: tuple[float, float, float, float]):
    """``box`` inside ``limit`` (points outside the header bounds are never used)."""
    return (max(box[0], limit[0]), max(box[1], limit[1]), min(box[2], limit[2]), min(box[3], limit[3]))


__all__ = ["Node", "ReadPart", "plan_reads"]
