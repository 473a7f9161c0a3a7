"""Hydro-flattening of rivers: water surfaces flat across, stepping down along the course (pure).

A lake is one level (:func:`~pipeline.fill.causes.rim_level`). A river's water falls
along its course, so one level floods its lower end or leaves its upper end below the
banks. For each water hole this module finds the course, measures the bank level
along it and fits a surface that is flat across the river and never rises downstream:

1. **Course.** The two ends are the farthest pair found by a double sweep of geodesic
   distance through the hole (8-connected pixel graph). An open end (the hole cut by the
   survey edge) puts them in its corners, so each end is moved to the middle of the
   pixels within a mean width of it. The course is the path between them that keeps to
   the middle of the channel (edge costs divided by the squared distance to the bank, so
   the path follows the ridge of the distance transform: the medial axis).
2. **Cross-sections.** The pixel path is smoothed (Gaussian, sigma half the mean width,
   at least 2 pixels) so that its normals are the river's cross-sections. Every water
   pixel, and every rim pixel, is projected on the smoothed course (nearest segment); its
   *chainage* is the arc length of the course up to there. Sigma is cut from each end of
   the smoothed course (bent by the smoothing) and points past an end are placed along
   its straight continuation. Pixels of one cross-section share one chainage, so one height.
3. **Stations.** The course is cut into stations twice the mean width long (at least 4
   pixels); a station's bank level is the ``percentile`` of its rim heights (the water's
   edge: banks carry vegetation and walls, nothing below the water).
4. **Monotone.** The station levels are fitted by isotonic regression (pool adjacent
   violators, weighted by rim pixels), once non-increasing and once non-decreasing along
   the chainage; the better fit says which end is upstream. Pooled stations make steps.
   The levels are then measured again with the fitted fall within each station taken
   out of its rim heights (else a low percentile leans to the station's lower end) and
   fitted again; a last fit keeps the slope from changing between stations except beside
   a gap where the stations measure a step (a weir), so that each station's noise does not
   pass into the surface.
5. **Surface.** Each pixel gets the fitted level interpolated linearly at its chainage
   between station centres, and beyond the end stations along the end slopes: monotone
   along the course, flat across it.

A hole is a *river* when its course is at least ``min_elongation`` times as long as its
mean width (``length**2 / area``; a disc gives 1.27) and the fitted levels drop by at
least ``min_drop`` from one end to the other; otherwise it is a lake and keeps the flat
fill (the caller's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.ndimage as ndi
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from .water_level import MIN_WATER_PX, edge_level

__all__ = ["RiverFit", "WaterEdge", "river_surfaces"]

#: 8-neighbour steps (half of them: the graph is undirected) and their lengths in pixels.
_STEPS = ((0, 1, 1.0), (1, 0, 1.0), (1, 1, math.sqrt(2.0)), (1, -1, math.sqrt(2.0)))
#: Holes with fewer pixels are never rivers (too small to have a course).
MIN_RIVER_PX = 16
#: Rounds of re-measuring the stations with the fitted fall within each taken out.
REFITS = 3
#: A fall between two stations beyond the reach's slope by this many times its noise is a step (a
#: weir, :func:`_measured_steps`): normal noise goes that far about once in 30,000 gaps.
STEP_SIGMAS = 4.0


@dataclass(frozen=True)
class RiverFit:
    """What the course of one water hole says.

    Attributes
    ----------
    label : int
    is_river : bool
        Elongated enough and dropping enough (see the module).
    length_px : float
        Length of the course (pixels).
    elongation : float
        ``length_px**2 / area_px``.
    drop : float
        Fitted level at the upstream end minus the downstream end (z units, >= 0).
    stations : int
        Stations with a measured bank.
    spread : float
        The error of the level (z units): the median spread of the edge heights of a
        station, combined with the robust scatter of the station levels about the fit
        (1.4826 x their median absolute residual).
    """

    label: int
    is_river: bool
    length_px: float
    elongation: float
    drop: float
    stations: int
    spread: float = math.nan


@dataclass(frozen=True)
class WaterEdge:
    """How a water hole's level is read from its edge (:mod:`pipeline.fill.water_level`), in pixels and z units.

    Attributes
    ----------
    tolerance : float
        Heights of one level agree within this (z units): the lidar's vertical noise.
    min_share : float
        Share of a ring (or a station's ring) the level needs.
    max_slope : float
        Steepest fall of a water surface along its course (z units per pixel).
    """

    tolerance: float
    min_share: float
    max_slope: float


def river_surfaces(
    ring_heights: np.ndarray,
    labels: np.ndarray,
    *,
    edge: WaterEdge,
    min_drop: float,
    min_elongation: float = 4.0,
    water_heights: np.ndarray | None = None,
    water_labels: np.ndarray | None = None,
) -> tuple[np.ndarray, list[RiverFit]]:
    """Fit a river surface to every labelled water hole.

    Parameters
    ----------
    ring_heights : ndarray (M, N)
        Heights of measured pixels (the lowest return per pixel: the water's edge), NaN elsewhere.
    labels : ndarray of int (M, N)
        One label > 0 per water hole, 0 elsewhere.
    edge : WaterEdge
        How a station's level is read from its edge, and the steepest fall allowed.
    min_drop : float
        Smallest fall from one end to the other (z units) for a river.
    min_elongation : float
        Smallest ``length**2 / area`` for a river.
    water_heights, water_labels : ndarray (M, N), optional
        The lowest return of pixels holding water returns, and the hole each belongs to
        (:func:`~pipeline.fill.water_level.water_edge_heights`); where a station has
        enough of them they give its level.

    Returns
    -------
    surface : ndarray of float64 (M, N)
        The river surface on the pixels of holes judged rivers, NaN elsewhere.
    fits : list of RiverFit
        One per label present, in label order.
    """
    heights = np.asarray(ring_heights, np.float64)
    labels = np.asarray(labels)
    if water_heights is None or water_labels is None:
        water_heights, water_labels = np.full(heights.shape, np.nan), np.zeros(labels.shape, np.int64)
    surface = np.full(heights.shape, np.nan)
    fits = []
    reach = np.nonzero(np.asarray(water_labels) > 0)
    for index, box in enumerate(ndi.find_objects(labels.astype(np.int64)), start=1):
        if box is None:
            continue
        grown = _grown_box(box, labels.shape, reach, np.asarray(water_labels) == index)
        hole = labels[grown] == index
        water = np.where(water_labels[grown] == index, water_heights[grown], np.nan)
        fit, local = _fit_one(heights[grown], water, hole, index, edge, min_drop, min_elongation)
        fits.append(fit)
        if fit.is_river:
            view = surface[grown]
            view[hole] = local[hole]
    return surface, fits


def _grown_box(
    box: tuple[slice, slice], shape: tuple[int, ...], reach: tuple[np.ndarray, ...], mine: np.ndarray
) -> tuple[slice, slice]:
    """The hole's box with one pixel of margin (the rim), grown to hold its water-return pixels."""
    r0, r1 = box[0].start - 1, box[0].stop + 1
    c0, c1 = box[1].start - 1, box[1].stop + 1
    rows, cols = reach
    if len(rows):
        own = mine[rows, cols]
        if own.any():
            r0, r1 = min(r0, int(rows[own].min())), max(r1, int(rows[own].max()) + 1)
            c0, c1 = min(c0, int(cols[own].min())), max(c1, int(cols[own].max()) + 1)
    return slice(max(r0, 0), min(r1, shape[0])), slice(max(c0, 0), min(c1, shape[1]))


def _fit_one(
    heights: np.ndarray,
    water: np.ndarray,
    hole: np.ndarray,
    label: int,
    edge: WaterEdge,
    min_drop: float,
    min_elongation: float,
) -> tuple[RiverFit, np.ndarray]:
    """The river fit of one hole in its box (rim and water returns included); the surface over the box."""
    area = int(hole.sum())
    none = RiverFit(label, False, 0.0, 0.0, 0.0, 0)
    if area < MIN_RIVER_PX:
        return none, np.empty(0)
    has_water = np.isfinite(water)
    chainage, length = _chainage(hole, has_water)
    elongation = length**2 / area
    if elongation < min_elongation:
        return RiverFit(label, False, length, elongation, 0.0, 0), np.empty(0)
    rim = _rim(hole) & np.isfinite(heights) & ~has_water
    station_px = max(2.0 * area / max(length, 1.0), 4.0)
    evidence = _Evidence(chainage[rim], heights[rim], chainage[has_water], water[has_water])
    centres, levels, weights, _ = evidence.stations(station_px, edge, None)
    if len(levels) < 2:
        return RiverFit(label, False, length, elongation, 0.0, len(levels)), np.empty(0)
    fitted = _monotone(centres, levels, weights, edge)
    # again with the fall within each station taken out, so its level no longer leans to its lower
    # end; a station falling more than the edge tolerance needs a few rounds to settle
    for _ in range(REFITS):
        centres, levels, weights, spreads = evidence.stations(station_px, edge, (centres, fitted))
        fitted = _monotone(centres, levels, weights, edge)
    # then with the slope kept from changing between stations but where they measure a step
    steps = _measured_steps(centres, fitted, spreads / np.sqrt(np.maximum(weights, 1.0)))
    fitted = _monotone(centres, levels, weights, edge, steps)
    drop = float(abs(fitted[0] - fitted[-1]))
    # the scatter of the edge heights about each station's level, and of the stations about the fit
    spread = math.hypot(float(np.median(spreads)), 1.4826 * float(np.median(np.abs(levels - fitted))))
    surface = _capped_surface(_interpolate(chainage, centres, fitted), hole, edge.max_slope)
    drop = min(drop, float(np.ptp(surface[hole])))
    fit = RiverFit(label, drop >= min_drop, length, elongation, drop, len(levels), spread)
    return fit, surface


def _capped_surface(surface: np.ndarray, hole: np.ndarray, max_slope: float) -> np.ndarray:
    """The surface with its fall scaled down about its mean where a step between neighbours exceeds the cap.

    The fit caps the fall per unit of chainage; the chainage of a pixel path is a little
    longer than the straight run (its smoothing leaves wiggles), so the fall between two
    neighbouring pixels can exceed the cap by a few per cent.
    """
    steepest = 0.0
    for axis in (0, 1):
        step = np.abs(np.diff(np.where(hole, surface, np.nan), axis=axis))
        if np.isfinite(step).any():
            steepest = max(steepest, float(np.nanmax(step)))
    if steepest <= max_slope:
        return surface
    mean = float(np.mean(surface[hole]))
    return mean + (surface - mean) * (max_slope / steepest)


def _interpolate(chainage: np.ndarray, centres: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """Levels between station centres, linear; beyond the end stations along the mean slope of the end reach.

    The rim of the last half station and of an open end is sparse, so one end station
    is a weak guide to the slope there; the slope over the last stations covering a
    quarter of the course (at least two) keeps the surface monotone and follows the water.
    """
    surface = np.interp(chainage, centres, levels)
    if len(centres) < 2:
        return surface
    span = max(2, len(centres) // 4)
    for outside, a, b in ((chainage < centres[0], 0, span - 1), (chainage > centres[-1], -1, -span)):
        slope = (levels[b] - levels[a]) / (centres[b] - centres[a]) if centres[b] != centres[a] else 0.0
        surface[outside] = levels[a] + slope * (chainage[outside] - centres[a])
    return surface


def _rim(hole: np.ndarray) -> np.ndarray:
    """Pixels 4-adjacent to the hole, outside it."""
    return ndi.binary_dilation(hole, structure=ndi.generate_binary_structure(2, 1)) & ~hole


def _chainage(hole: np.ndarray, also: np.ndarray) -> tuple[np.ndarray, float]:
    """Arc length along the course of the nearest course pixel, for every pixel of the box; the course length."""
    rows, cols = np.nonzero(hole)
    node = np.full(hole.shape, -1, np.int64)
    node[rows, cols] = np.arange(len(rows))
    depth = ndi.distance_transform_edt(np.pad(hole, 1))[1:-1, 1:-1]  # distance to the bank (pixels)
    src, dst, step = _edges(hole, node)
    n = len(rows)
    plain = coo_matrix((step, (src, dst)), shape=(n, n)).tocsr()
    # double sweep: the farthest pixel from anywhere is one end, the farthest from it the other
    start = _farthest(dijkstra(plain, directed=False, indices=0))
    from_start = dijkstra(plain, directed=False, indices=start)
    end = _farthest(from_start)
    from_end = dijkstra(plain, directed=False, indices=end)
    width = n / max(from_start[end], 1.0)
    # an open end is a cut across the channel: start and end in the middle of those cuts, not in a corner
    start = _middle(rows, cols, from_end >= from_end[start] - width)
    end = _middle(rows, cols, from_start >= from_start[end] - width)
    medial = step / (0.5 * (depth[rows[src], cols[src]] + depth[rows[dst], cols[dst]])) ** 2
    graph = coo_matrix((medial, (src, dst)), shape=(n, n)).tocsr()
    _, previous = dijkstra(graph, directed=False, indices=start, return_predecessors=True)
    path = [end]
    while path[-1] != start and previous[path[-1]] >= 0:
        path.append(int(previous[path[-1]]))
    path.reverse()
    # the pixel path is a staircase: smoothed over about half the width, its normals are the cross-sections
    sigma = max(0.5 * width, 2.0)
    pr = ndi.gaussian_filter1d(rows[path].astype(np.float64), sigma, mode="nearest")
    pc = ndi.gaussian_filter1d(cols[path].astype(np.float64), sigma, mode="nearest")
    near = _rim(hole) | hole | also
    chainage = np.zeros(hole.shape)
    chainage[near] = _project(np.column_stack([pr, pc]), np.column_stack(np.nonzero(near)), trim=sigma, back=sigma)
    return chainage, float(np.sum(np.hypot(np.diff(pr), np.diff(pc))))


def _project(course: np.ndarray, points: np.ndarray, *, trim: float, back: float) -> np.ndarray:
    """Chainage of each point: arc length to its nearest course vertex, along the end tangents beyond the ends.

    The ends of a double-sweep path run into the corners of the hole's open ends; ``trim``
    pixels of arc are cut from each end first, and the points past an end are placed along
    the straight continuation of the course there, so their sections stay perpendicular.
    """
    along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(course, axis=0), axis=1))])
    keep = (along >= min(trim, along[-1] / 4)) & (along <= along[-1] - min(trim, along[-1] / 4))
    if keep.sum() >= 2:
        course, along = course[keep], along[keep]
    _, nearest = cKDTree(course).query(points)
    chainage = _on_segments(course, along, points, nearest)
    back = min(len(course) - 1, max(1, int(back)))
    for end, inner, sign in ((0, back, -1.0), (len(course) - 1, len(course) - 1 - back, 1.0)):
        tangent = course[end] - course[inner]
        length = np.linalg.norm(tangent)
        at_end = nearest == end
        if length > 0 and at_end.any():
            beyond = (points[at_end] - course[end]) @ (tangent / length)
            chainage[at_end] = along[end] + sign * np.maximum(beyond, 0.0)
    return chainage


def _on_segments(course: np.ndarray, along: np.ndarray, points: np.ndarray, nearest: np.ndarray) -> np.ndarray:
    """Arc length of each point projected on the nearer of the two segments at its nearest vertex."""
    best = along[nearest].copy()
    best_distance = np.linalg.norm(points - course[nearest], axis=1)
    for step in (-1, 1):
        other = nearest + step
        ok = (other >= 0) & (other < len(course))
        a, b = course[nearest[ok]], course[other[ok]]
        direction = b - a
        length = np.linalg.norm(direction, axis=1)
        t = np.einsum("ij,ij->i", points[ok] - a, direction) / np.maximum(length, 1e-12) ** 2
        t = np.clip(t, 0.0, 1.0)
        foot = a + t[:, None] * direction
        distance = np.linalg.norm(points[ok] - foot, axis=1)
        closer = distance < best_distance[ok]
        rows = np.nonzero(ok)[0][closer]
        best[rows] = along[nearest[rows]] + step * t[closer] * length[closer]
        best_distance[rows] = distance[closer]
    return best


def _farthest(distance: np.ndarray) -> int:
    """The node farthest from a sweep's source among those it reached."""
    return int(np.argmax(np.where(np.isfinite(distance), distance, -1.0)))


def _middle(rows: np.ndarray, cols: np.ndarray, cap: np.ndarray) -> int:
    """The node of ``cap`` nearest to its centroid."""
    r, c = rows[cap], cols[cap]
    nodes = np.nonzero(cap)[0]
    return int(nodes[np.argmin((r - r.mean()) ** 2 + (c - c.mean()) ** 2)])


def _edges(hole: np.ndarray, node: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """8-connected edges between hole pixels: source, target, length (pixels)."""
    h, w = hole.shape
    src, dst, step = [], [], []
    for dr, dc, length in _STEPS:
        r0, r1 = max(0, -dr), h - max(0, dr)
        c0, c1 = max(0, -dc), w - max(0, dc)
        a = node[r0:r1, c0:c1]
        b = node[r0 + dr : r1 + dr, c0 + dc : c1 + dc]
        both = (a >= 0) & (b >= 0)
        src.append(a[both])
        dst.append(b[both])
        step.append(np.full(int(both.sum()), length))
    return np.concatenate(src), np.concatenate(dst), np.concatenate(step)


@dataclass(frozen=True)
class _Evidence:
    """A river's edge heights by chainage: its ring's lowest returns, and its water returns."""

    ring_along: np.ndarray
    ring: np.ndarray
    water_along: np.ndarray
    water: np.ndarray

    def stations(
        self, station_px: float, edge: WaterEdge, fitted: tuple[np.ndarray, np.ndarray] | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per station with evidence: centre chainage, edge level, heights that agree on it, their spread.

        With ``fitted`` (station centres and levels), the fitted fall between each
        height and the centre of its station is taken out of it first.
        """
        # the water's own returns are its level; the ring of a walled channel is the quay top
        use_ring = len(self.water) < MIN_WATER_PX
        along = np.concatenate([self.ring_along if use_ring else self.ring_along[:0], self.water_along])
        heights = np.concatenate([self.ring if use_ring else self.ring[:0], self.water])
        is_water = np.arange(len(along)) >= len(along) - len(self.water)
        station = np.floor(along / station_px).astype(np.int64)
        centres, levels, weights, spreads = [], [], [], []
        for k in np.unique(station):
            here = station == k
            h, at = heights[here], along[here]
            if fitted is not None:
                h = h - (_interpolate(at, *fitted) - _interpolate(np.array([at.mean()]), *fitted))
            water = is_water[here]
            found = edge_level(h[~water], h[water], tolerance=edge.tolerance, min_share=edge.min_share)
            if math.isfinite(found.level):
                centres.append(float(np.mean(at[water] if found.source == "water returns" else at[~water])))
                levels.append(found.level)
                weights.append(float(found.count))
                spreads.append(found.spread)
        return np.array(centres), np.array(levels), np.array(weights), np.array(spreads)


def _measured_steps(centres: np.ndarray, fitted: np.ndarray, errors: np.ndarray) -> np.ndarray:
    """Per gap between stations: whether the fitted levels step there (a weir, a fall), not slope.

    A gap is a step where its fall exceeds the reach's median slope over the gap by more
    than :data:`STEP_SIGMAS` times the larger of two noise measures: the standard error
    of the two stations' level difference (``errors``: each station's spread over the
    square root of its count of heights), and the robust scatter of every gap's excess
    fall (1.4826 x their median absolute value). The second holds where the first is too
    small: one station's level off by its noise makes the gap before it fall more and the
    gap after it less (excesses of 4 to 5 standard errors in pairs on the synthetic
    rivers, against 38 to 77 for 0.3 m and 1 m weirs).
    """
    gaps = np.diff(centres)
    if not len(gaps):
        return np.zeros(0, bool)
    falls = np.abs(np.diff(fitted))
    excess = falls - float(np.median(falls / np.maximum(gaps, 1e-9))) * gaps
    scatter = 1.4826 * float(np.median(np.abs(excess)))
    return excess > STEP_SIGMAS * np.maximum(np.hypot(errors[:-1], errors[1:]), scatter)


def _monotone(
    centres: np.ndarray,
    levels: np.ndarray,
    weights: np.ndarray,
    edge: WaterEdge,
    steps: np.ndarray | None = None,
) -> np.ndarray:
    """The better of the falling and rising fits, each monotone with its slope capped at ``edge.max_slope``.

    A robust (soft L1, scale ``edge.tolerance``) weighted least-squares fit of the
    station levels under ``0 <= fall between stations <= max_slope * distance``: a
    station whose edge is a bridge or a quay top stands out and pulls little. With
    ``steps`` (per gap between stations, :func:`_measured_steps`), a change of slope
    between neighbouring gaps costs as much as a station's misfit of the level it makes
    over one station spacing, except beside a gap the stations measure as a step: a
    river's slope changes gradually along a reach, and the noise of each station's
    level (its few water returns) otherwise passes into the surface as wobbles.
    """
    best, best_cost = levels, math.inf
    for sign in (1.0, -1.0):
        fit, cost = _capped_fit(centres, sign * levels, weights, edge, steps)
        if cost < best_cost:
            best, best_cost = sign * fit, cost
    return best


def _capped_fit(
    centres: np.ndarray,
    levels: np.ndarray,
    weights: np.ndarray,
    edge: WaterEdge,
    steps: np.ndarray | None = None,
) -> tuple[np.ndarray, float]:
    """Non-increasing levels, falling at most ``max_slope`` per pixel of chainage; the fit and its cost.

    ``steps``: see :func:`_monotone` (no slope term without it).
    """
    n = len(levels)
    spacing = np.diff(centres)
    gaps = spacing * edge.max_slope
    # unknowns: the first level and the n - 1 falls; level i = first - sum of the falls before it
    design = np.zeros((n, n))
    design[:, 0] = 1.0
    design[1:, 1:] = -np.tril(np.ones((n - 1, n - 1)))
    root = np.sqrt(weights / weights.max())
    # the change of slope between gaps j and j + 1 (fall over spacing), over one mean spacing
    bends = np.zeros((0, n))
    if steps is not None and n >= 3:
        smooth = [j for j in range(n - 2) if not (steps[j] or steps[j + 1])]
        bends = np.zeros((len(smooth), n))
        for row, j in enumerate(smooth):
            bends[row, j + 1] = -np.mean(spacing) / max(spacing[j], 1e-9)
            bends[row, j + 2] = np.mean(spacing) / max(spacing[j + 1], 1e-9)
    start = np.concatenate([[float(np.max(levels))], np.zeros(n - 1)])
    lower = np.concatenate([[-np.inf], np.zeros(n - 1)])
    upper = np.concatenate([[np.inf], gaps + 1e-12])
    # the residuals are linear in the unknowns: their Jacobian is one constant matrix
    jacobian = np.vstack([root[:, None] * design, bends])
    # imported here, where a river is fitted: scipy.optimize brings linprog and HiGHS with it (0.6 s),
    # which every process importing the fill (the client, each worker) paid at its start
    from scipy.optimize import least_squares

    found = least_squares(
        lambda x: np.concatenate([root * (design @ x - levels), bends @ x]),
        np.clip(start, lower, upper),
        jac=lambda x: jacobian,
        bounds=(lower, upper),
        loss="soft_l1",
        f_scale=max(edge.tolerance, 1e-6),
    )
    return design @ found.x, float(found.cost)
