"""``natural``: natural-neighbour interpolation of a hole from its rim band (Laplace coordinates).

Natural-neighbour interpolation weighs the data points whose Voronoi cells the query
point's own cell would touch if it were inserted into the diagram. With the *Laplace*
(non-Sibsonian) coordinates of Belikov, Ivanov, Kontorovich, Korytnik and Semenov
(1997) and Sugihara (1999), the weight of neighbour ``s`` is the length of the Voronoi
edge the query would share with it over their distance::

    w_s = |e_s| / |p - s|,      z(p) = sum_s w_s z_s / sum_s w_s

The interpolant is local (only the natural neighbours speak), reproduces planes exactly,
stays within its neighbours' range (no overshoot at a roof's edge), is continuous, and
follows the data's own spacing where a raster method follows the pixel lattice. It is the
``laplace`` of startinpy (Ledoux), one of the standard fills of the fill benchmark.

Per query: the Delaunay triangles whose circumcircle holds it (its *conflict* triangles,
found from the triangle that contains it by walking to neighbours: Bowyer-Watson) bound a
star-shaped cavity; each cavity edge ``(a, b)`` becomes the triangle ``(p, a, b)`` of the
new triangulation, whose circumcentre is a vertex of the query's Voronoi cell, and the edge
shared with ``s`` joins the circumcentres of its two new triangles. The data are the
component's rim band (the rim plus the ``mls_k`` nearest measured neighbours of each rim
pixel: the support of ``linear`` and ``spline``), triangulated by scipy (qhull) with the
fixed 1e-6 px jitter of ``linear`` (pixel centres are co-circular by the thousand). A query
outside the triangulation's hull (a hole open to the window's edge) takes the nearest height.

Pure: arrays in, arrays out, one component at a time.
"""

from __future__ import annotations

import numba
import numpy as np
from scipy.spatial import Delaunay, QhullError

from ._problem import Problem
from .scattered import fill_triangulated
from .settings import ComponentFill

__all__ = ["fill_natural", "laplace_interpolate"]


def laplace_interpolate(points: np.ndarray, z: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Natural-neighbour heights (Laplace coordinates) at ``queries`` from ``points`` (N x 2) with heights ``z``.

    NaN where a query lies outside the points' convex hull, and everywhere when the points
    do not span a plane (fewer than 3, or all on a line).
    """
    out = np.full(len(queries), np.nan)
    if len(points) < 3 or np.linalg.matrix_rank(points - points.mean(axis=0)) < 2:
        return out
    try:
        tri = Delaunay(points)
    except QhullError:
        return out
    start = tri.find_simplex(queries)
    _laplace(
        np.ascontiguousarray(tri.points, np.float64),
        np.ascontiguousarray(tri.simplices, np.int64),
        np.ascontiguousarray(tri.neighbors, np.int64),
        np.ascontiguousarray(z, np.float64),
        np.ascontiguousarray(queries, np.float64),
        np.ascontiguousarray(start, np.int64),
        out,
    )
    return out


@numba.njit(cache=True)
def _circumcentre(ax, ay, bx, by, cx, cy):  # pragma: no cover - compiled
    d = 2.0 * (ax * (by - cy) + bx * (cy - ay) + cx * (ay - by))
    a2, b2, c2 = ax * ax + ay * ay, bx * bx + by * by, cx * cx + cy * cy
    ux = (a2 * (by - cy) + b2 * (cy - ay) + c2 * (ay - by)) / d
    uy = (a2 * (cx - bx) + b2 * (ax - cx) + c2 * (bx - ax)) / d
    return ux, uy


@numba.njit(cache=True)
def _in_circle(pts, tri, px, py):  # pragma: no cover - compiled
    """Whether (px, py) lies strictly inside the circumcircle of triangle ``tri`` (any orientation)."""
    ax, ay = pts[tri[0], 0] - px, pts[tri[0], 1] - py
    bx, by = pts[tri[1], 0] - px, pts[tri[1], 1] - py
    cx, cy = pts[tri[2], 0] - px, pts[tri[2], 1] - py
    det = (
        (ax * ax + ay * ay) * (bx * cy - cx * by)
        - (bx * bx + by * by) * (ax * cy - cx * ay)
        + (cx * cx + cy * cy) * (ax * by - bx * ay)
    )
    orient = (pts[tri[1], 0] - pts[tri[0], 0]) * (pts[tri[2], 1] - pts[tri[0], 1]) - (
        pts[tri[1], 1] - pts[tri[0], 1]
    ) * (pts[tri[2], 0] - pts[tri[0], 0])
    return det * orient > 0.0


@numba.njit(cache=True)
def _laplace(pts, simplices, neighbors, z, queries, start, out):  # pragma: no cover - compiled
    n_tri = len(simplices)
    mark = np.full(n_tri, -1, np.int64)  # the query that last found a triangle in conflict
    stack = np.empty(n_tri, np.int64)
    conflict = np.empty(n_tri, np.int64)
    # per cavity vertex: the circumcentre of the new triangle where it starts an edge, and where it ends one
    slot = np.full(len(pts), -1, np.int64)
    verts = np.empty(len(pts), np.int64)
    c_start = np.empty((len(pts), 2))
    c_end = np.empty((len(pts), 2))
    for q in range(len(queries)):
        first = start[q]
        if first < 0:
            continue
        px, py = queries[q, 0], queries[q, 1]
        # the conflict triangles: those whose circumcircle holds the query, connected to the first
        n_conf, top = 0, 0
        stack[top] = first
        top += 1
        mark[first] = q
        while top > 0:
            top -= 1
            t = stack[top]
            conflict[n_conf] = t
            n_conf += 1
            for e in range(3):
                nb = neighbors[t, e]
                if nb >= 0 and mark[nb] != q and _in_circle(pts, simplices[nb], px, py):
                    mark[nb] = q
                    stack[top] = nb
                    top += 1
        # the cavity's edges: those of conflict triangles facing a non-conflict triangle (or none)
        n_verts = 0
        exact = -1
        for i in range(n_conf):
            t = conflict[i]
            tri = simplices[t]
            orient = (pts[tri[1], 0] - pts[tri[0], 0]) * (pts[tri[2], 1] - pts[tri[0], 1]) - (
                pts[tri[1], 1] - pts[tri[0], 1]
            ) * (pts[tri[2], 0] - pts[tri[0], 0])
            for e in range(3):
                nb = neighbors[t, e]
                if nb >= 0 and mark[nb] == q:
                    continue
                # the edge opposite vertex e, taken counter-clockwise
                a, b = tri[(e + 1) % 3], tri[(e + 2) % 3]
                if orient < 0.0:
                    a, b = b, a
                ux, uy = _circumcentre(px, py, pts[a, 0], pts[a, 1], pts[b, 0], pts[b, 1])
                for v in (a, b):
                    if slot[v] < 0:
                        slot[v] = n_verts
                        verts[n_verts] = v
                        n_verts += 1
                    if (pts[v, 0] - px) ** 2 + (pts[v, 1] - py) ** 2 < 1e-18:
                        exact = v
                c_start[slot[a], 0], c_start[slot[a], 1] = ux, uy
                c_end[slot[b], 0], c_end[slot[b], 1] = ux, uy
        if exact >= 0:
            out[q] = z[exact]
        else:
            total, weights = 0.0, 0.0
            for i in range(n_verts):
                v = verts[i]
                edge = np.sqrt((c_start[i, 0] - c_end[i, 0]) ** 2 + (c_start[i, 1] - c_end[i, 1]) ** 2)
                w = edge / np.sqrt((pts[v, 0] - px) ** 2 + (pts[v, 1] - py) ** 2)
                total += w * z[v]
                weights += w
            if weights > 0.0:
                out[q] = total / weights
        for i in range(n_verts):
            slot[verts[i]] = -1


def fill_natural(problem: Problem, labels: np.ndarray, out: np.ndarray) -> list[ComponentFill]:
    """Fill the components ``labels`` by natural-neighbour interpolation (Laplace coordinates) of their rim band."""
    return fill_triangulated(problem, labels, out, laplace_interpolate, "natural")
