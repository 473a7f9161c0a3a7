"""Scattered-data fills from the measured pixels around a hole: ``spline`` and ``linear``.

``spline``: the regularized spline with tension (RST) of Mitasova and Mitas (1993), the
interpolator of GRASS ``v.surf.rst`` and of ``r.fillnulls method=rst``. The surface is

    z(x) = p(x) + sum_j a_j R(|x - x_j|),   R(r) = -[E1(rho) + ln(rho) + C_E],  rho = (phi r / 2)^2

(``E1`` the exponential integral, ``C_E`` Euler's constant) with ``p`` a linear
trend (1, x, y), so that planes are reproduced exactly, and the coefficients solve
``(K + s I) a + P c = z``, ``P^T a = 0``, where ``s`` is the smoothing. The tension
``phi`` moves the surface between a thin plate (low tension: curvature carried into the
hole) and a membrane (high tension: no overshoot); like GRASS, it is given for
coordinates normalised by ``dnorm`` (the square root of the support's box area here, one
segment holding all points), default 40 and smoothing 0.1, GRASS's defaults.
The support is the rim plus the ``mls_k`` nearest measured neighbours of every rim pixel
(the same band as MLS and IDW), thinned on a lattice to at most ``spline_max_points``
(a dense solve: its cost grows with the cube of the points).

``linear``: linear interpolation on the Delaunay triangulation of the same support
points' pixel centres (scipy), the "linear TIN" of GIS tools; pixels outside the
triangulation's hull (a hole open to the window's edge) take the nearest support height.

Both are pure: arrays in, arrays out, one component at a time.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy import linalg
from scipy.spatial import Delaunay, cKDTree
from scipy.special import exp1

from ._problem import Problem, rims_by_label, support_points
from .settings import ComponentFill

__all__ = ["fill_linear", "fill_spline", "fill_triangulated", "rst_basis", "rst_fit"]

_EULER = 0.5772156649015329


def rst_basis(r: np.ndarray, tension: float) -> np.ndarray:
    """The RST radial function ``R(r) = -[E1(rho) + ln(rho) + C_E]``, ``rho = (tension r / 2)^2``; ``R(0) = 0``."""
    rho = (0.5 * tension * np.asarray(r, np.float64)) ** 2
    out = np.zeros_like(rho)
    pos = rho > 0
    # for small rho, E1(rho) + ln(rho) + C_E = rho - rho^2/4 + ... (no cancellation trouble above 1e-8)
    out[pos] = -(exp1(rho[pos]) + np.log(rho[pos]) + _EULER)
    return out


def rst_fit(points: np.ndarray, z: np.ndarray, queries: np.ndarray, *, tension: float, smoothing: float) -> np.ndarray:
    """Heights at ``queries`` of the regularized spline with tension through ``points`` (N x 2) with heights ``z``.

    Coordinates are normalised by ``dnorm`` (square root of the points' box area, at
    least 1) before ``tension`` applies; the trend is linear. Returns NaN for every
    query when the system is singular (fewer than 3 points not on a line).
    """
    n = len(points)
    if n < 3:
        return np.full(len(queries), np.nan)
    lo, hi = points.min(axis=0), points.max(axis=0)
    dnorm = max(float(np.sqrt(np.prod(np.maximum(hi - lo, 1.0)))), 1.0)
    centre = 0.5 * (lo + hi)
    p = (points - centre) / dnorm
    q = (queries - centre) / dnorm
    z0 = float(np.mean(z))
    d = np.sqrt(((p[:, None, :] - p[None, :, :]) ** 2).sum(-1))
    a = np.zeros((n + 3, n + 3))
    a[:n, :n] = rst_basis(d, tension) + smoothing * np.eye(n)
    trend = np.column_stack([np.ones(n), p])
    a[:n, n:] = trend
    a[n:, :n] = trend.T
    rhs = np.concatenate([z - z0, np.zeros(3)])
    try:
        coef = linalg.solve(a, rhs, assume_a="sym")
    except (linalg.LinAlgError, ValueError):
        return np.full(len(queries), np.nan)
    if not np.all(np.isfinite(coef)):
        return np.full(len(queries), np.nan)
    out = np.empty(len(queries))
    step = max(1, 2_000_000 // max(n, 1))  # queries x points per block, bounded memory
    for s in range(0, len(q), step):
        qq = q[s : s + step]
        dq = np.sqrt(((qq[:, None, :] - p[None, :, :]) ** 2).sum(-1))
        out[s : s + step] = z0 + rst_basis(dq, tension) @ coef[:n] + coef[n] + qq @ coef[n + 1 :]
    return out


def _thin(flat: np.ndarray, w: int, rim: np.ndarray, max_points: int) -> np.ndarray:
    """At most about ``max_points`` of the support points: one per lattice cell, rim pixels first."""
    if len(flat) <= max_points:
        return flat
    ordered = np.concatenate([rim, np.setdiff1d(flat, rim)])
    r, c = np.divmod(ordered, w)
    step = 2
    while True:
        cell = (r // step) * (w // step + 1) + c // step
        _, first = np.unique(cell, return_index=True)
        if len(first) <= max_points:
            return ordered[np.sort(first)]
        step += 1


def _none(k: int, size: int) -> ComponentFill:
    return ComponentFill(label=k, n_pixels=size, method="none", filled=False)


def _component_points(problem: Problem, labels: np.ndarray):
    """Per component: (label, support flat indices, rim flat indices, hole rows, hole cols)."""
    st = problem.settings
    sizes, slices, rims = problem.sizes(), problem.slices(), rims_by_label(problem, labels)
    for k in labels:
        k = int(k)
        rim = rims[k]
        pts = support_points(problem, k, rim, st.mls_k) if len(rim) else rim
        sl = slices[k - 1]
        pr, pc = np.nonzero(problem.labels[sl] == k)
        yield k, int(sizes[k]), pts, rim, pr + sl[0].start, pc + sl[1].start


def fill_spline(problem: Problem, labels: np.ndarray, out: np.ndarray) -> list[ComponentFill]:
    """Fill the components ``labels`` with a regularized spline with tension on their rim band."""
    st = problem.settings
    w = problem.labels.shape[1]
    recs = []
    for k, size, pts, rim, pr, pc in _component_points(problem, labels):
        pts = _thin(pts, w, rim, st.spline_max_points)
        sr, sc = np.divmod(pts, w)
        values = rst_fit(
            np.column_stack([sr, sc]).astype(np.float64),
            problem.heights[sr, sc],
            np.column_stack([pr, pc]).astype(np.float64),
            tension=st.spline_tension,
            smoothing=st.spline_smoothing,
        )
        if not np.all(np.isfinite(values)):
            recs.append(_none(k, size))
            continue
        out[pr, pc] = values
        recs.append(ComponentFill(label=k, n_pixels=size, method="spline", filled=True, n_support=len(pts)))
    return recs


def fill_linear(problem: Problem, labels: np.ndarray, out: np.ndarray) -> list[ComponentFill]:
    """Fill the components ``labels`` by linear interpolation on the Delaunay triangulation of their rim band."""
    return fill_triangulated(problem, labels, out, _linear, "linear")


def _linear(points: np.ndarray, z: np.ndarray, queries: np.ndarray) -> np.ndarray:
    # imported where a hole is filled linearly: scipy.interpolate brings scipy.optimize with it, which
    # every process importing the fill (the client, each worker) paid at its start
    from scipy.interpolate import LinearNDInterpolator

    return LinearNDInterpolator(Delaunay(points), z)(queries)


def fill_triangulated(
    problem: Problem,
    labels: np.ndarray,
    out: np.ndarray,
    interpolate: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray],
    method: str,
) -> list[ComponentFill]:
    """Fill each component with ``interpolate(points, z, queries)`` (NaN outside the points' hull)
    of its rim band's pixel centres, then the nearest support height outside the hull (everywhere
    where the band's pixels lie on one line).

    The points are taken in the component's own frame (its support's corner at the origin: the
    same triangulation wherever the window around it starts, whatever the cell size) and moved by
    a fixed 1e-6 px jitter in their row-major order: pixel centres are co-circular by the thousand,
    and qhull's point location then walks for ever (0.5 s for a 700-pixel hole).
    """
    w = problem.labels.shape[1]
    recs = []
    for k, size, pts, _, pr, pc in _component_points(problem, labels):
        if len(pts) == 0:
            recs.append(_none(k, size))
            continue
        sr, sc = np.divmod(pts, w)
        corner = np.array([sr.min(), sc.min()], np.float64)
        xy = np.column_stack([sr, sc]).astype(np.float64) - corner
        zs = problem.heights[sr, sc]
        queries = np.column_stack([pr, pc]).astype(np.float64) - corner
        values = np.full(len(pr), np.nan)
        if len(pts) >= 3 and np.linalg.matrix_rank(xy - xy.mean(axis=0)) == 2:  # not all on a line
            jitter = np.random.default_rng(0).uniform(-1e-6, 1e-6, xy.shape)
            values = interpolate(xy + jitter, zs, queries)
        outside = ~np.isfinite(values)
        if outside.any():
            _, nn = cKDTree(xy).query(queries[outside])
            values[outside] = zs[nn]
        out[pr, pc] = values
        recs.append(ComponentFill(label=k, n_pixels=size, method=method, filled=True, n_support=len(pts)))
    return recs
