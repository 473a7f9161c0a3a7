"""Walls: straight height steps found in the height-jump pixels and fitted precisely.

Airborne lidar sees few points on walls; a wall shows in the height map as a band
of height-jump pixels ([UAS] eq. 1, :func:`pipeline.holes.height_jumps`) between a
low side (ground) and a high side (roof). Following Lesparre and Gorte, "Finding and
fitting wall planes in airborne point cloud data" ([WALL], ``seeds/wall-planes-
airborne.txt``), the wall's position is not taken from the jump pixels themselves
but from a least-squares fit of a smooth step (an S-curve) to the heights on
either side, which locates it to a fraction of a pixel.

Two steps, both pure functions:

1. :func:`wall_segments` groups jump pixels into straight segments: 8-connected jump
   pixels whose uphill directions (the gradient of ``zmax``) agree, so that the
   two walls of a building corner become two segments.
2. :func:`fit_wall` fits, to the pixels within a few pixels of a segment,

   ``h(d) = low + (high - low) / (1 + exp(-d / width))``

   where ``d`` is the signed distance to the wall line ``x cos(phi) + y sin(phi) =
   rho`` (positive on the high side); ``phi``, ``rho``, ``low``, ``high`` and
   ``width`` are the unknowns (bounded least squares, then a soft-L1 polish).
   A pixel is a square, not a point: its ``zmax`` is the highest point anywhere in
   it, so it is modelled as ``h(d + r)`` and its ``zmin`` as ``h(d - r)``, ``r``
   being the pixel's half-extent along the wall normal (``(|cos phi| + |sin
   phi|) / 2``). This makes the fitted line unbiased on max/min rasters. Empty
   pixels next to the wall (a scan shadow) count as "not roof": roofs are seen
   from the air, so a pixel the roof reached would hold points.

:func:`find_walls` runs both and returns :class:`Wall` records in world coordinates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np
import scipy.ndimage as ndi
from affine import Affine

from ..quantiles import linear_quantiles
from .masks import height_jumps
from .wall_step import LOGISTIC_NODES, bounded_least_squares, soft_l1_cost

__all__ = ["Wall", "WallParams", "WallSegment", "find_walls", "fit_wall", "wall_segments"]


@dataclass(frozen=True)
class WallSegment:
    """Jump pixels of one straight wall candidate.

    Attributes
    ----------
    rows, cols : ndarray of int64
        The jump pixels (array indices).
    normal : tuple of float
        Unit vector (d_col, d_row) across the wall, pointing uphill.
    """

    rows: np.ndarray
    cols: np.ndarray
    normal: tuple[float, float]

    @property
    def n_pixels(self) -> int:
        return len(self.rows)


@dataclass(frozen=True)
class Wall:
    """A fitted wall line.

    Attributes
    ----------
    x0, y0, x1, y1 : float
        End points in world coordinates (through ``transform``).
    bottom, top : float
        Fitted heights of the low and the high side (z units).
    rms : float
        Root mean square of the height residuals of the measured pixels (z units).
    width_px : float
        Fitted width of the S-curve, in pixels (small for a sharp wall).
    n_support : int
        Pixels used in the fit.
    n_jump_px : int
        Jump pixels of the segment.
    line_px : tuple of float
        End points in pixel coordinates of the input arrays, (col0, row0, col1,
        row1); pixel (r, c) covers [c, c + 1) x [r, r + 1).
    normal_px : tuple of float
        Unit normal (d_col, d_row) pointing to the high side, in pixel coordinates.
    offset_px : float
        The line is ``col * normal_px[0] + row * normal_px[1] == offset_px``.
    """

    x0: float
    y0: float
    x1: float
    y1: float
    bottom: float
    top: float
    rms: float
    width_px: float
    n_support: int
    n_jump_px: int
    line_px: tuple[float, float, float, float]
    normal_px: tuple[float, float]
    offset_px: float

    @property
    def height(self) -> float:
        return self.top - self.bottom

    @property
    def length(self) -> float:
        """Length in world units."""
        return math.hypot(self.x1 - self.x0, self.y1 - self.y0)


def wall_segments(
    jumps: np.ndarray,
    zmax: np.ndarray,
    *,
    min_pixels: int = 6,
    min_length_px: float = 4.0,
    angle_tolerance_deg: float = 20.0,
    max_thickness_px: float = 2.0,
) -> list[WallSegment]:
    """Group height-jump pixels into straight wall segments.

    Parameters
    ----------
    jumps : ndarray of bool, shape (M, N)
        Height-jump pixels (e.g. :func:`pipeline.holes.height_jumps`).
    zmax : ndarray of float, shape (M, N)
        Highest point per pixel, NaN where empty.
    min_pixels : int
        Smaller groups are dropped.
    min_length_px : float
        Shorter groups are dropped.
    angle_tolerance_deg : float
        Neighbouring jump pixels join when their uphill directions differ by less.
    max_thickness_px : float
        Groups thicker than this (standard deviation across their main axis,
        e.g. vegetation) are dropped.

    Returns
    -------
    list of WallSegment
        Longest first.
    """
    jumps = np.asarray(jumps, dtype=bool)
    if jumps.shape != np.shape(zmax) or jumps.ndim != 2:
        raise ValueError(f"jumps {jumps.shape} and zmax {np.shape(zmax)} must be 2-D arrays of one shape")
    if not jumps.any():
        return []
    gx, gy = _uphill(np.asarray(zmax, dtype=np.float64))
    rows, cols = np.nonzero(jumps)
    gxs, gys = gx[rows, cols], gy[rows, cols]
    tol = math.radians(angle_tolerance_deg)
    n_groups, group = _group_jump_pixels(jumps, rows, cols, gxs, gys, tol)
    normals = _straight_groups(
        group, n_groups, rows, cols, gxs, gys, tol,
        min_pixels=min_pixels, min_length_px=min_length_px, max_thickness_px=max_thickness_px,
    )  # fmt: skip
    order = np.argsort(group, kind="stable")
    bounds = np.searchsorted(group[order], np.arange(n_groups + 1))
    segments = []
    for g in np.flatnonzero(np.isfinite(normals[:, 0])):
        members = order[bounds[g] : bounds[g + 1]]
        normal = (float(normals[g, 0]), float(normals[g, 1]))
        segments.append(WallSegment(rows[members].astype(np.int64), cols[members].astype(np.int64), normal))
    segments.sort(key=lambda s: -s.n_pixels)
    return segments


def _group_jump_pixels(
    jumps: np.ndarray, rows: np.ndarray, cols: np.ndarray, gxs: np.ndarray, gys: np.ndarray, tol: float
) -> tuple[int, np.ndarray]:
    """Connected groups of 8-adjacent jump pixels whose uphill directions differ by less than ``tol``."""
    index = np.full(jumps.shape, -1, np.int64)
    index[rows, cols] = np.arange(len(rows))
    angle = np.mod(np.arctan2(gys, gxs), np.pi)  # undirected: a wall's two sides agree
    strong = np.hypot(gxs, gys) > 0
    return _joined_groups(index, rows, cols, angle, strong, tol)


@numba.njit(cache=True, nogil=True)
def _root(parent, i):  # pragma: no cover - compiled
    while parent[i] != i:
        parent[i] = parent[parent[i]]  # path halving
        i = parent[i]
    return i


@numba.njit(cache=True, nogil=True)
def _joined_groups(index, rows, cols, angle, strong, tol):  # pragma: no cover - compiled
    """Union-find over the pixels' east, south, south-east and south-west neighbours that agree.

    Groups are numbered by their lowest pixel, as ``scipy.sparse.csgraph.connected_components``
    numbers them (it built and sorted a sparse graph of the pairs first: 0.6 of a 211 M-point
    survey's 1.6 s of grouping).
    """
    height, width = index.shape
    n = len(rows)
    parent = np.arange(n)
    for i in range(n):
        if not strong[i]:
            continue
        for step in range(4):
            r2 = rows[i] + (0 if step == 0 else 1)
            c2 = cols[i] + (1 if step == 0 else (0 if step == 1 else (1 if step == 2 else -1)))
            if r2 < 0 or r2 >= height or c2 < 0 or c2 >= width:
                continue
            j = index[r2, c2]
            if j < 0 or not strong[j]:
                continue
            diff = abs(angle[i] - angle[j])
            if min(diff, math.pi - diff) < tol:
                a, b = _root(parent, i), _root(parent, j)
                if a != b:
                    parent[max(a, b)] = min(a, b)
    group = np.empty(n, np.int64)
    number = np.full(n, -1, np.int64)
    count = 0
    for v in range(n):
        r = _root(parent, v)
        if number[r] < 0:
            number[r] = count
            count += 1
        group[v] = number[r]
    return count, group


#: Lengths and thicknesses of a group within this of a limit meet it (floating-point rounding of exact ties).
_ROUNDING_PX = 1e-9


def _straight_groups(
    group: np.ndarray,
    n_groups: int,
    rows: np.ndarray,
    cols: np.ndarray,
    gxs: np.ndarray,
    gys: np.ndarray,
    tol: float,
    *,
    min_pixels: int,
    min_length_px: float,
    max_thickness_px: float,
) -> np.ndarray:
    """Each group's uphill unit normal (NaN where it is no wall segment), for all groups at once.

    A group is a segment when it has ``min_pixels``, its pixel centres' spread across their
    main axis (the smaller eigenvalue of their covariance, in closed form for 2 x 2) is at most
    ``max_thickness_px``, its length (``sqrt(12 x`` the larger eigenvalue``)``, a uniform run's)
    at least ``min_length_px``, and its pixels' uphill directions agree (their mean unit
    vector at least ``cos(tol)`` long) and cross the main axis (within ``tol`` of its normal).
    """
    size = np.bincount(group, minlength=n_groups).astype(np.float64)
    x, y = cols + 0.5, rows + 0.5
    mean_x = np.bincount(group, x, minlength=n_groups) / size
    mean_y = np.bincount(group, y, minlength=n_groups) / size
    dx, dy = x - mean_x[group], y - mean_y[group]
    cxx = np.bincount(group, dx * dx, minlength=n_groups) / size
    cxy = np.bincount(group, dx * dy, minlength=n_groups) / size
    cyy = np.bincount(group, dy * dy, minlength=n_groups) / size
    half_sum, half_diff = (cxx + cyy) / 2, (cxx - cyy) / 2
    radius = np.hypot(half_diff, cxy)
    smaller, larger = half_sum - radius, half_sum + radius
    # the main axis: angle 0.5 atan2(2 cxy, cxx - cyy); its normal points across the group
    axis = 0.5 * np.arctan2(2 * cxy, cxx - cyy)
    normal = np.stack([-np.sin(axis), np.cos(axis)], axis=1)
    length = np.hypot(gxs, gys)
    with np.errstate(invalid="ignore", divide="ignore"):  # a flat pixel (no uphill) joins no group of two
        ux = np.bincount(group, gxs / length, minlength=n_groups) / size
        uy = np.bincount(group, gys / length, minlength=n_groups) / size
    uphill_norm = np.hypot(ux, uy)
    across = normal[:, 0] * ux + normal[:, 1] * uy
    # pixel centres make exact ties (a run of 4 x 2 pixels is 4 long): judged within rounding
    wall = (
        (size >= min_pixels)
        & (np.sqrt(np.maximum(smaller, 0.0)) <= max_thickness_px + _ROUNDING_PX)
        & (np.sqrt(12 * larger) >= min_length_px - _ROUNDING_PX)
        & (uphill_norm >= math.cos(tol))
        & (np.abs(across) >= math.cos(tol) * uphill_norm)
    )
    normal = np.where((across < 0)[:, None], -normal, normal)
    return np.where(wall[:, None], normal, np.nan)


def fit_wall(
    zmax: np.ndarray,
    zmin: np.ndarray | None,
    segment: WallSegment,
    *,
    count: np.ndarray | None = None,
    transform: Affine | None = None,
    support_px: float = 3.0,
    empty_is_low: bool = True,
    min_height: float = 0.0,
    pixel_values: str = "extremes",
    points_per_pixel: float = 8.0,
) -> Wall | None:
    """Fit the S-curve step of one wall segment ([WALL]).

    The surface across the wall is ``low + (high - low) * S(d)`` with ``S`` a
    logistic S-curve of width ``width`` and ``d`` the signed distance to the wall
    line. A pixel sees the surface over its whole square: the share of the square
    on the high side is ``a(d)``, the exact area fraction of a unit square cut by
    the line, smoothed by the S-curve. Then, for a pixel with ``k`` points spread
    over it, the expected highest point is ``low + (high - low) * (1 - (1 - a)^k)``
    and the expected lowest ``low + (high - low) * a^k`` (``pixel_values=
    "extremes"``, the stage-2 rasters); a mean or centre value is
    ``low + (high - low) * a`` (``"centre"``). Fitting expectations keeps the line
    unbiased whatever the point density.

    Parameters
    ----------
    zmax : ndarray of float, shape (M, N)
        Highest point per pixel (or the surface value, see ``pixel_values``), NaN where empty.
    zmin : ndarray of float, shape (M, N), optional
        Lowest point per pixel; a second observation of each pixel.
    segment : WallSegment
        From :func:`wall_segments`.
    count : ndarray of int, shape (M, N), optional
        Points per pixel (``k``); ``points_per_pixel`` where not given.
    transform : Affine, optional
        Pixel-to-world transform of the arrays (e.g. ``grid.window_transform(window)``);
        the identity by default.
    support_px : float
        Pixels whose centre lies within this distance of the initial line (and
        beside the segment's extent) take part in the fit.
    empty_is_low : bool
        Empty pixels in the support count as "not reached by the roof": roofs are
        seen from the air, so a pixel the roof covered would hold points.
    min_height : float
        Fits whose step is not higher are rejected (None).
    pixel_values : {"extremes", "centre"}
        What the pixel values are: the highest/lowest point of the square pixel
        (stage-2 ``zmax``/``zmin``), or the surface at the centre / its mean
        over the pixel (an interpolated or averaged DSM).
    points_per_pixel : float
        ``k`` when ``count`` is not given.

    Returns
    -------
    Wall or None
        None when the fit fails, has too little support on either side, or is too low.
    """
    if pixel_values not in ("extremes", "centre"):
        raise ValueError(f"pixel_values must be 'extremes' or 'centre', got {pixel_values!r}")
    n0, pts, rho0 = _initial_line(segment)
    observed = _observe(
        zmax, zmin, count, segment, n0, rho0, support_px=support_px, pixel_values=pixel_values,
        points_per_pixel=points_per_pixel, empty_is_low=empty_is_low,
    )  # fmt: skip
    if observed is None:
        return None
    observations, low0, high0, n_measured, n_support = observed
    fit = _fit_support(observations, n0, rho0, low0, high0, support_px=support_px)
    if fit is None or not fit.x[3] - fit.x[2] > min_height:
        return None
    return _wall(fit, segment, pts, n_measured=n_measured, n_support=n_support, transform=transform)


def _initial_line(segment: WallSegment) -> tuple[np.ndarray, np.ndarray, float]:
    """The segment's uphill normal, its pixel centres (x = column, y = row) and the line's offset along the normal."""
    n0 = np.asarray(segment.normal, dtype=np.float64)
    pts = np.stack([segment.cols + 0.5, segment.rows + 0.5], axis=1)
    rho0 = float((pts @ n0).mean())
    return n0, pts, rho0


#: Observation arrays of a fit, in the order :func:`.wall_step.step_residuals` takes them: the
#: highest points (x, y, points per pixel, height), the lowest points (likewise), the empty pixels (x, y).
_Observations = tuple[np.ndarray, ...]


def _observe(
    zmax: np.ndarray,
    zmin: np.ndarray | None,
    count: np.ndarray | None,
    segment: WallSegment,
    n0: np.ndarray,
    rho0: float,
    *,
    support_px: float,
    pixel_values: str,
    points_per_pixel: float,
    empty_is_low: bool,
) -> tuple[_Observations, float, float, int, int] | None:
    """The fit's observations: the pixels whose centre lies within ``support_px`` of the initial line, beside the segment.

    Returns the observations, the starting low and high levels (the 20th percentile of the low
    side's heights, the 80th of the high side's), the number of measured values (highest plus
    lowest points, which come first among the residuals) and of support pixels; None when
    there is too little support on either side, or no step.
    """
    zmax = np.asarray(zmax, dtype=np.float64)
    h, w = zmax.shape
    along0 = np.array([n0[1], -n0[0]])
    t = np.stack([segment.cols + 0.5, segment.rows + 0.5], axis=1) @ along0
    t_lo, t_hi = float(t.min()) + 1.0, float(t.max()) - 1.0  # keep clear of corners
    pad = int(math.ceil(support_px)) + 2
    r0, r1 = max(int(segment.rows.min()) - pad, 0), min(int(segment.rows.max()) + pad + 1, h)
    c0, c1 = max(int(segment.cols.min()) - pad, 0), min(int(segment.cols.max()) + pad + 1, w)
    no_values = np.empty((0, 0))
    zmin_arr = no_values if zmin is None else np.asarray(zmin, dtype=np.float64)
    if pixel_values == "centre":
        count_arr, k_fixed = no_values, 1.0
    elif count is not None:
        count_arr, k_fixed = np.asarray(count, dtype=np.float64), math.nan
    else:
        count_arr, k_fixed = no_values, float(points_per_pixel)
    found = _support_observations(
        zmax, zmin_arr, count_arr, k_fixed, r0, r1, c0, c1, float(n0[0]), float(n0[1]), rho0, t_lo, t_hi,
        float(support_px), empty_is_low,
    )  # fmt: skip
    low0, high0, n_measured, n_support = found[10:]
    if n_measured < 0 or not high0 > low0:
        return None
    return (*found[:10], LOGISTIC_NODES), low0, high0, n_measured, n_support


@numba.njit(cache=True, nogil=True)
def _support_observations(
    zmax, zmin, count, k_fixed, r0, r1, c0, c1, n0x, n0y, rho0, t_lo, t_hi, support_px, empty_is_low
):  # pragma: no cover - compiled
    """:func:`_observe`'s pixels and levels in one compiled pass over the segment's box.

    The box's pixels are visited row by row, as ``np.nonzero`` orders them; distances are
    computed in numpy's order of operations, so every value is the one the array version gave.
    ``zmin`` and ``count`` may be empty (0 x 0): no lowest points, ``k_fixed`` points per pixel.
    ``n_measured`` is -1 when a side has too little support.
    """
    size = (r1 - r0) * (c1 - c0)
    xc, yc, d0 = np.empty(size), np.empty(size), np.empty(size)
    zx, zn, k = np.empty(size), np.empty(size), np.empty(size)
    has_zmin, has_count = zmin.shape[0] > 0, count.shape[0] > 0
    ax, ay = n0y, -n0x
    n = 0
    for r in range(r0, r1):
        y = r + 0.5
        for c in range(c0, c1):
            x = c + 0.5
            d = x * n0x + y * n0y - rho0
            along = x * ax + y * ay
            if abs(d) <= support_px and along >= t_lo and along <= t_hi:
                xc[n], yc[n], d0[n] = x, y, d
                zx[n] = zmax[r, c]
                zn[n] = zmin[r, c] if has_zmin else np.nan
                k[n] = count[r, c] if has_count else k_fixed
                n += 1
    n_high = n_low = n_empty = n_below = n_above = n_lows = n_highs = 0
    for i in range(n):
        if np.isfinite(zx[i]):
            n_high += 1
            n_below += d0[i] < 0
            n_above += d0[i] > 0
            n_low += np.isfinite(zn[i])
            if d0[i] < -0.5:
                n_lows += 1 + np.isfinite(zn[i])
            elif d0[i] > 0.5:
                n_highs += 1
        else:
            n_empty += 1
    empty = np.empty(0)
    if n_high < 6 or n_below < 3 or n_above < 3:
        return empty, empty, empty, empty, empty, empty, empty, empty, empty, empty, 0.0, 0.0, -1, n
    lows, highs = np.empty(n_lows), np.empty(n_highs)
    x_high, y_high, k_high, z_high = np.empty(n_high), np.empty(n_high), np.empty(n_high), np.empty(n_high)
    x_low, y_low, k_low, z_low = np.empty(n_low), np.empty(n_low), np.empty(n_low), np.empty(n_low)
    n_empty = n_empty if empty_is_low else 0
    x_empty, y_empty = np.empty(n_empty), np.empty(n_empty)
    i_high = i_low = i_empty = i_lows = i_highs = 0
    for i in range(n):
        if np.isfinite(zx[i]):
            x_high[i_high], y_high[i_high], k_high[i_high], z_high[i_high] = xc[i], yc[i], max(k[i], 1.0), zx[i]
            i_high += 1
            if np.isfinite(zn[i]):
                x_low[i_low], y_low[i_low], k_low[i_low], z_low[i_low] = xc[i], yc[i], max(k[i], 1.0), zn[i]
                i_low += 1
            if d0[i] < -0.5:
                lows[i_lows] = zx[i]
                i_lows += 1
                if np.isfinite(zn[i]):
                    lows[i_lows] = zn[i]
                    i_lows += 1
            elif d0[i] > 0.5:
                highs[i_highs] = zx[i]
                i_highs += 1
        elif empty_is_low:
            x_empty[i_empty], y_empty[i_empty] = xc[i], yc[i]
            i_empty += 1
    # np.nanpercentile(lows, 20) and np.percentile(highs, 80), value for value
    low0 = _linear_quantile(lows, 0.2) if n_lows else np.min(z_high)
    high0 = _linear_quantile(highs, 0.8) if n_highs else np.max(z_high)
    return (
        x_high, y_high, k_high, z_high, x_low, y_low, k_low, z_low, x_empty, y_empty,
        low0, high0, n_high + n_low, n,
    )  # fmt: skip


@numba.njit(cache=True, nogil=True)
def _linear_quantile(values, q):  # pragma: no cover - compiled
    """:func:`pipeline.quantiles.linear_quantiles` of one quantile, compiled: numpy's linear method."""
    ordered = np.sort(values)
    last = len(ordered) - 1
    virtual = last * q
    if virtual >= last:
        return ordered[last]
    below = math.floor(virtual)
    a, b, t = ordered[below], ordered[below + 1], virtual - below
    step = b - a
    return b - step * (1 - t) if t >= 0.5 else a + step * t


def _fit_support(
    observations: _Observations, n0: np.ndarray, rho0: float, low0: float, high0: float, *, support_px: float
) -> _StepFit | None:
    """Fit the step to the observations, from a start at the initial line and levels; None when the fit fails."""
    step0 = high0 - low0
    phi0 = math.atan2(n0[1], n0[0])
    x0 = np.array([phi0, rho0, low0, high0, math.log(0.2)])
    lower = [phi0 - 0.6, rho0 - support_px, low0 - step0, low0, math.log(0.001)]
    upper = [phi0 + 0.6, rho0 + support_px, high0, high0 + step0, math.log(support_px)]
    return _fit_step(observations, x0, lower, upper, step0)


class _StepFit(NamedTuple):
    """A fitted step: its parameters, residuals, cost and how the search ended."""

    x: np.ndarray  # (phi, rho, low, high, log_width)
    fun: np.ndarray  # residuals at x
    cost: float  # 0.5 sum of squares, or of soft-L1 values (the loss it was fitted with)
    status: int  # 1 converged, 0 evaluation budget spent


def _fit_step(observations: tuple, x0: np.ndarray, lower: list, upper: list, step0: float) -> _StepFit | None:
    """Least squares of the S-curve step (a good basin), then a robust soft-L1 polish against outliers.

    Both are bounded Levenberg-Marquardt searches compiled in one call each
    (:func:`.wall_step.bounded_least_squares`); a wall costs about 0.5 ms instead of scipy's 3.7 ms,
    mostly interpreter overhead (the fits are at least as good as ``least_squares``'s,
    ``tests/test_walls.py``). Returns None when the fit fails.
    """
    lower_a, upper_a = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    scale = np.array([0.05, 0.1, 0.1 * step0, 0.1 * step0, 0.5])
    start = np.clip(np.asarray(x0, dtype=np.float64), lower_a, upper_a)
    # tolerances of 1e-6 (relative) are far below the 0.2-pixel accuracy a wall needs
    x, fun, cost, status = bounded_least_squares(start, lower_a, upper_a, scale, 0.0, 200, *observations)
    if status < 0:
        return None
    fit = _StepFit(x, fun, cost, status)
    f_scale = max(0.05 * step0, 1e-6)
    # the robust polish only changes a fit that has outliers (residuals beyond the soft-L1 knee)
    if np.max(np.abs(fun), initial=0.0) > 3.0 * f_scale:
        x, fun, cost, status = bounded_least_squares(fit.x, lower_a, upper_a, scale, f_scale, 100, *observations)
        if status >= 0 and cost <= soft_l1_cost(fit.fun, f_scale):
            fit = _StepFit(x, fun, cost, status)
    return fit


def _wall(
    fit, segment: WallSegment, pts: np.ndarray, *, n_measured: int, n_support: int, transform: Affine | None
) -> Wall:
    """The fitted line as a :class:`Wall`, its ends at the segment's extent."""
    phi, rho, low, high, log_w = fit.x
    normal = np.array([math.cos(phi), math.sin(phi)])
    along = np.array([normal[1], -normal[0]])
    foot = normal * rho
    proj = pts @ along
    ends = [foot + along * (proj.min() - 0.5), foot + along * (proj.max() + 0.5)]
    rms = float(np.sqrt(np.mean(fit.fun[:n_measured] ** 2)))
    transform = Affine.identity() if transform is None else transform
    (x0w, y0w), (x1w, y1w) = (transform @ (float(e[0]), float(e[1])) for e in ends)
    return Wall(
        x0=x0w,
        y0=y0w,
        x1=x1w,
        y1=y1w,
        bottom=float(low),
        top=float(high),
        rms=rms,
        width_px=float(math.exp(log_w)),
        n_support=int(n_support),
        n_jump_px=segment.n_pixels,
        line_px=(float(ends[0][0]), float(ends[0][1]), float(ends[1][0]), float(ends[1][1])),
        normal_px=(float(normal[0]), float(normal[1])),
        offset_px=float(rho),
    )


@dataclass(frozen=True)
class WallParams:
    """How :func:`find_walls` groups jump pixels into segments and fits them.

    Attributes
    ----------
    min_pixels, min_length_px, angle_tolerance_deg
        See :func:`wall_segments`.
    support_px, pixel_values
        See :func:`fit_wall`.
    """

    min_pixels: int = 6
    min_length_px: float = 4.0
    angle_tolerance_deg: float = 20.0
    support_px: float = 3.0
    pixel_values: str = "extremes"


_DEFAULT_WALLS = WallParams()


def find_walls(
    zmax: np.ndarray,
    zmin: np.ndarray | None,
    *,
    jump_threshold: float,
    count: np.ndarray | None = None,
    transform: Affine | None = None,
    params: WallParams = _DEFAULT_WALLS,
    region: tuple[slice, slice] | None = None,
    jumps: np.ndarray | None = None,
) -> list[Wall]:
    """Walls of a height map: jump pixels -> straight segments -> S-curve fits.

    Parameters
    ----------
    zmax, zmin : ndarray of float, shape (M, N)
        Highest and lowest point per pixel, NaN where empty (``zmin`` may be None).
    jump_threshold : float
        Height-jump threshold in z units ([UAS] eq. 1); also the least wall height.
    count : ndarray of int, shape (M, N), optional
        Points per pixel (see :func:`fit_wall`).
    transform : Affine, optional
        Pixel-to-world transform of the arrays.
    params : WallParams
        How segments are grouped and fitted (defaults: :class:`WallParams`).
    region : (slice, slice), optional
        Only segments whose centre pixel lies in these rows and columns are
        fitted (a cell's core inside its halo arrays: each wall is fitted once,
        by the cell that holds its middle, with the halo as context).

    Returns
    -------
    list of Wall
    """
    # float64 once for every wall's support (each fit would otherwise convert the whole arrays)
    zmax = np.asarray(zmax, dtype=np.float64)
    zmin = None if zmin is None else np.asarray(zmin, dtype=np.float64)
    count = None if count is None else np.asarray(count, dtype=np.float64)
    if jumps is None:
        jumps = height_jumps(zmax, zmax if zmin is None else zmin, jump_threshold=jump_threshold)
    segments = wall_segments(
        jumps,
        zmax,
        min_pixels=params.min_pixels,
        min_length_px=params.min_length_px,
        angle_tolerance_deg=params.angle_tolerance_deg,
    )
    walls = []
    for seg in segments:
        if region is not None:
            row, col = _median_index(seg.rows), _median_index(seg.cols)
            rows, cols = region
            if not (rows.start <= row < rows.stop and cols.start <= col < cols.stop):
                continue
        wall = fit_wall(
            zmax,
            zmin,
            seg,
            count=count,
            transform=transform,
            support_px=params.support_px,
            min_height=jump_threshold,
            pixel_values=params.pixel_values,
        )
        if wall is not None:
            walls.append(wall)
    return walls


def _median_index(indices: np.ndarray) -> int:
    """``int(np.median(indices))``, through :func:`~pipeline.quantiles.linear_quantiles`: without numpy's
    median set-up per call (0.3 s of a 42 M-point survey's 4,700 segments)."""
    return int(linear_quantiles(indices, (0.5,))[0])


def _uphill(zmax: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradient (d/dcol, d/drow) of ``zmax`` with empty pixels filled from the nearest data."""
    empty = ~np.isfinite(zmax)
    if empty.all():
        return np.zeros_like(zmax), np.zeros_like(zmax)
    if empty.any():
        idx = ndi.distance_transform_edt(empty, return_distances=False, return_indices=True)
        zmax = zmax[tuple(idx)]
    return ndi.sobel(zmax, axis=1), ndi.sobel(zmax, axis=0)
