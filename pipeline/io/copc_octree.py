"""A COPC file's hierarchy: the octree's nodes holding points, where their chunks are (no point decoded).

Read with the file's header (:func:`pipeline.io.las.read_header`), so the plan can split
a large file among tasks by its nodes (:mod:`pipeline.reads`); the nodes are decoded by
:func:`pipeline.io.copc.iter_copc_nodes`. Uses laspy's COPC hierarchy parser.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from laspy.copc import CopcReader, load_octree_for_query

from ..errors import InputDataError

__all__ = ["NODE_DTYPE", "CopcOctree", "read_copc_octree"]

#: One hierarchy entry, as the COPC specification lays it out (32 bytes, little-endian).
NODE_DTYPE = np.dtype(
    [
        ("level", "<i4"),
        ("x", "<i4"),
        ("y", "<i4"),
        ("z", "<i4"),
        ("offset", "<u8"),
        ("byte_size", "<i4"),
        ("point_count", "<i4"),
    ]
)


@dataclass(frozen=True, eq=False)
class CopcOctree:
    """The nodes of a COPC file that hold points, from its hierarchy pages (no point is decoded).

    Attributes
    ----------
    center : tuple of float
        Centre of the root cube, in the file's (scaled) coordinates.
    halfsize : float
        Half the side of the root cube.
    nodes : ndarray of NODE_DTYPE
        Every node with points, sorted by byte offset.
    """

    center: tuple[float, float, float]
    halfsize: float
    nodes: np.ndarray

    def node_bounds(self, nodes: np.ndarray | None = None) -> np.ndarray:
        """``(n, 4)`` array of each node's cube in x/y: minx, miny, maxx, maxy."""
        nodes = self.nodes if nodes is None else nodes
        side = 2.0 * self.halfsize / np.exp2(nodes["level"].astype(np.float64))
        minx = self.center[0] - self.halfsize + nodes["x"] * side
        miny = self.center[1] - self.halfsize + nodes["y"] * side
        return np.column_stack([minx, miny, minx + side, miny + side])


def read_copc_octree(path: str | os.PathLike) -> CopcOctree:
    """Read every hierarchy page of a COPC file: the nodes holding points and where their chunks are.

    Raises
    ------
    InputDataError
        The COPC info or hierarchy cannot be read (the file is then not a usable COPC).
    """
    try:
        with open(path, "rb") as fh, CopcReader(fh, close_fd=False) as reader:
            info = reader.copc_info
            found = load_octree_for_query(reader.source, info, reader.root_page)
    except Exception as e:
        raise InputDataError(Path(path), f"COPC hierarchy cannot be read: {e}") from None
    rows = [
        (n.key.level, n.key.x, n.key.y, n.key.z, n.offset, n.byte_size, n.point_count)
        for n in found
        if n.point_count > 0
    ]
    nodes = np.array(rows, dtype=NODE_DTYPE)
    nodes.sort(order="offset")
    center = (float(info.center[0]), float(info.center[1]), float(info.center[2]))
    return CopcOctree(center=center, halfsize=float(info.halfsize), nodes=nodes)
