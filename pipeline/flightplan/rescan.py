"""Re-scans of occlusions: lanes placed where the hole's ground is in the drone lidar's sight.

An occlusion is ground the survey's sensor could not see behind a taller object (a
wall, a tree). A drone lane sees a hole pixel when the ray from the pixel's ground to
the lidar, at the moment its scan plane (across the track) passes over the pixel,
clears the surface model and lies within the lidar's half field of view
(``fov_deg / 2`` from the vertical). The rays are cast by
:func:`pipeline.sensor.sight.sight_classes`, the test the survey's own lines were
classified with; here the "track" is a lane flown at its planned height.

Candidates are lanes parallel to the pattern's lanes (the hole's long axis, or an
imposed azimuth), spread across the hole and half a swath beyond it on each side, one
every ``altitude_agl_m x tan(CANDIDATE_ANGLE_STEP_DEG)``. Each candidate's visible
pixels are cast alone; lanes are then chosen greedily, the one that sees most of what
is not yet seen first, while a lane adds at least ``min_gain_m2`` of newly visible
ground (the smallest hole worth a flight, ``flightplan.min_area_m2``) or sees all the
rest the candidates can see; a lane the later ones made redundant is dropped. The regular
pattern laid over the hole is kept when it sees as much with no more lanes; a pattern that also
covers holes of other causes keeps its lanes (their spacing and side overlap) and only gains lanes.

Pure: numpy arrays and shapely geometries in, frozen dataclasses out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely

from ..sensor.sight import SEEN, ground_targets, sight_classes
from .altitude import AffineLike, Surface, lane_with_turns
from .coverage import CoverageParams, CoveragePattern, Lane

__all__ = ["CANDIDATE_ANGLE_STEP_DEG", "Placement", "SightParams", "place_pattern"]

#: Neighbouring candidate lanes differ in their view of a pixel below them by about this
#: angle: the shadow a 10 m wall casts moves by under 1 m (one or two DSM pixels) from one
#: candidate to the next, so a finer grid finds no view the grid misses.
CANDIDATE_ANGLE_STEP_DEG = 5.0


@dataclass(frozen=True)
class SightParams:
    """What the visibility of a hole from lanes depends on (from ``[flightplan]`` and ``[holes]``)."""

    coverage: CoverageParams
    max_climb_gradient: float = 0.15
    terrain_step_m: float = 5.0
    #: The height jump (``holes.jump_threshold_m``) that tells a wall from the ground beside it,
    #: for the ground height in a hole (:func:`pipeline.sensor.sight.ground_targets`).
    ground_step_m: float = 2.5
    #: A lane is added only when it sees this much more ground (``flightplan.min_area_m2``).
    min_gain_m2: float = 25.0


@dataclass(frozen=True)
class Placement:
    """A pattern's lanes and the share of each of its holes' pixels visible from them."""

    pattern: CoveragePattern
    shares: dict[int, float]
    placed: bool = False


@dataclass(frozen=True)
class _Window:
    """The DSM around one pattern: the blocking surface, the ground at the hole pixels, which hole each is."""

    surface: np.ndarray
    targets: np.ndarray
    labels: np.ndarray
    x_left: float
    y_top: float
    pixel: float

    def cells(self) -> tuple[np.ndarray, np.ndarray]:
        rows, cols = np.nonzero(self.labels)
        return rows, cols


def place_pattern(
    pattern: CoveragePattern,
    holes: list[shapely.Geometry],
    dsm: Surface,
    transform: AffineLike,
    *,
    params: SightParams,
    rescan: bool,
    keep_lanes: bool = False,
) -> Placement:
    """The share of each hole visible from ``pattern``; with ``rescan``, the lanes that see most.

    Parameters
    ----------
    holes : list of geometries
        The pattern's holes, in the order of ``pattern.hole_ids``.
    dsm : ndarray
        The (repaired) surface heights on a north-up grid of square pixels; ``transform`` its affine.
    rescan : bool
        Choose the lanes by the visible share (an occlusion); else only measure the pattern's.
    keep_lanes : bool
        Keep the pattern's lanes and only add lanes to them (the pattern also covers holes of
        other causes, whose lanes keep their spacing and side overlap).

    Returns
    -------
    Placement
        Shares NaN where the DSM grid is not north-up with square pixels, or holds none of the holes' pixels.
    """
    if abs(abs(transform.a) - abs(transform.e)) > 1e-9 * abs(transform.a) or transform.b or transform.d:
        return Placement(pattern, {h: math.nan for h in pattern.hole_ids})  # rays are cast on north-up square pixels
    cover = params.coverage
    reach = cover.swath_m + cover.run_in_m + cover.turnaround_m
    window = _window(pattern, holes, dsm, transform, reach=reach, ground_step_m=params.ground_step_m)
    if window is None:
        return Placement(pattern, {h: math.nan for h in pattern.hole_ids})
    seen = np.logical_or.reduce([_seen(window, _track(lane, dsm, transform, params), cover) for lane in pattern.lanes])
    if not rescan:
        return Placement(pattern, _shares(window, seen, pattern.hole_ids))
    frame = _Frame.of(pattern)
    offsets = frame.candidate_offsets(pattern, cover)
    views = np.array([_seen(window, _track(frame.lane(v, pattern), dsm, transform, params), cover) for v in offsets])
    base = seen if keep_lanes else np.zeros_like(seen)
    chosen = _greedy(views, base, min_gain=params.min_gain_m2 / window.pixel**2)
    union = (base | np.logical_or.reduce(views[chosen])) if chosen else base
    kept = [frame.offset(lane) for lane in pattern.lanes] if keep_lanes else []
    count = len(kept) + len(chosen)
    if union.sum() > seen.sum() or (union.sum() == seen.sum() and count < len(pattern.lanes)):
        placed = frame.pattern(pattern, sorted(kept + [offsets[i] for i in chosen]))
        return Placement(placed, _shares(window, union, pattern.hole_ids), placed=True)
    return Placement(pattern, _shares(window, seen, pattern.hole_ids))


@dataclass(frozen=True)
class _Frame:
    """Along- and across-track unit vectors of a pattern and its lanes' along-track extent."""

    along: np.ndarray
    across: np.ndarray
    u0: float
    u1: float

    @classmethod
    def of(cls, pattern: CoveragePattern) -> _Frame:
        a = math.radians(pattern.azimuth_deg)
        along = np.array([math.sin(a), math.cos(a)])
        across = np.array([along[1], -along[0]])
        ends = np.array([p for lane in pattern.lanes for p in (lane.start, lane.end)]) @ along
        return cls(along, across, float(ends.min()), float(ends.max()))

    def candidate_offsets(self, pattern: CoveragePattern, cover: CoverageParams) -> list[float]:
        """Across-track positions from half a swath before the rectangle to half a swath beyond, nearest the middle first."""
        v = np.asarray(pattern.rectangle.exterior.coords) @ self.across
        step = cover.altitude_agl_m * math.tan(math.radians(CANDIDATE_ANGLE_STEP_DEG))
        low, high = v.min() - cover.swath_m / 2, v.max() + cover.swath_m / 2
        count = int(math.floor((high - low) / step)) + 1
        middle = (low + high) / 2
        grid = middle + (np.arange(count) - (count - 1) / 2) * step
        return [float(g) for g in sorted(grid, key=lambda g: (abs(g - middle), g))]

    def offset(self, lane: Lane) -> float:
        """A lane's across-track position."""
        return float(np.asarray(lane.start) @ self.across)

    def lane(self, v: float, pattern: CoveragePattern, index: int = 0) -> Lane:
        start = self.u0 * self.along + v * self.across
        end = self.u1 * self.along + v * self.across
        return Lane(index, (float(start[0]), float(start[1])), (float(end[0]), float(end[1])))

    def pattern(self, pattern: CoveragePattern, offsets: list[float]) -> CoveragePattern:
        """``pattern`` with lanes at ``offsets`` (ascending); its spacing the mean gap, for the turns' length."""
        lanes = tuple(self.lane(v, pattern, i) for i, v in enumerate(offsets))
        spacing = (offsets[-1] - offsets[0]) / (len(offsets) - 1) if len(offsets) > 1 else pattern.spacing_m
        return CoveragePattern(
            pattern_id=pattern.pattern_id,
            hole_ids=pattern.hole_ids,
            area=pattern.area,
            rectangle=pattern.rectangle,
            azimuth_deg=pattern.azimuth_deg,
            spacing_m=spacing,
            lanes=lanes,
            turnaround_m=pattern.turnaround_m,
        )


def _greedy(views: np.ndarray, covered: np.ndarray, *, min_gain: float) -> list[int]:
    """Candidates in the order chosen: most newly seen pixels first, while worth a lane (module docstring).

    ``covered``: the pixels the lanes kept already see.
    """
    chosen: list[int] = []
    if views.size == 0:
        return chosen
    base = covered.copy()
    covered = covered.copy()
    reachable = np.logical_or.reduce(views) & ~base
    while True:
        gains = (views & ~covered).sum(axis=1)
        best = int(np.argmax(gains))  # ties: the first, nearest the middle
        rest = int((reachable & ~covered).sum())
        if gains[best] == 0 or gains[best] < min(min_gain, rest):
            break
        chosen.append(best)
        covered |= views[best]
    for lane in list(chosen):  # an early pick that the later ones made redundant (a compromise): dropped
        others = [k for k in chosen if k != lane]
        if others and not (covered & ~(base | np.logical_or.reduce(views[others]))).any():
            chosen = others
    return chosen


def _track(lane: Lane, dsm: Surface, transform: AffineLike, params: SightParams) -> np.ndarray | None:
    """The lidar's path along ``lane`` (x, y, height), as :mod:`.mission` flies it: one straight line with its turns.

    None where no DSM lies under the lane's swath (off the survey): its height, and so its clearance, is unknown.
    """
    length, turnaround_m = lane.length_m, params.coverage.turnaround_m
    try:
        _, _, first, last = lane_with_turns(
            lane,
            turnaround_m,
            dsm,
            transform,
            params.coverage,
            max_gradient=params.max_climb_gradient,
            slope_gain_m=params.terrain_step_m,
        )
    except ValueError:
        return None
    total = 2 * turnaround_m + length
    z_start = first + (last - first) * turnaround_m / total
    z_end = first + (last - first) * (turnaround_m + length) / total
    return np.array([[lane.start[0], lane.start[1], z_start], [lane.end[0], lane.end[1], z_end]])


def _seen(window: _Window, track: np.ndarray | None, cover: CoverageParams) -> np.ndarray:
    """Per hole pixel of the window (in :meth:`_Window.cells` order): seen from the lane ``track`` (None: nothing)."""
    candidates = window.labels > 0
    if track is None:
        return np.zeros(int(candidates.sum()), bool)
    classes = sight_classes(
        candidates,
        window.surface,
        window.targets,
        np.broadcast_to(candidates, (1, *candidates.shape)),
        [track],
        origin_xy=(window.x_left, window.y_top),
        pixel_size=window.pixel,
        reach=math.inf,  # the window holds the lanes: a ray that leaves it proves nothing, and is not seen
        max_scan_angles=[cover.fov_deg / 2],
    )
    rows, cols = window.cells()
    return np.asarray(classes[rows, cols] == SEEN)


def _shares(window: _Window, seen: np.ndarray, hole_ids: tuple[int, ...]) -> dict[int, float]:
    rows, cols = window.cells()
    labels = window.labels[rows, cols]
    out = {}
    for k, hole_id in enumerate(hole_ids, start=1):
        mine = labels == k
        out[hole_id] = float(seen[mine].mean()) if mine.any() else math.nan
    return out


def _window(
    pattern: CoveragePattern,
    holes: list[shapely.Geometry],
    dsm: Surface,
    transform: AffineLike,
    *,
    reach: float,
    ground_step_m: float,
) -> _Window | None:
    """The DSM within ``reach`` of the pattern's rectangle, its hole pixels labelled; None: no hole pixel on the grid."""
    pixel = abs(transform.a)
    x0, y0, x1, y1 = pattern.rectangle.buffer(reach + 2 * pixel).bounds
    c0, c1 = max(0, int((x0 - transform.c) / pixel)), min(dsm.shape[1], int(math.ceil((x1 - transform.c) / pixel)))
    r0 = max(0, int((transform.f - y1) / pixel))
    r1 = min(dsm.shape[0], int(math.ceil((transform.f - y0) / pixel)))
    if c0 >= c1 or r0 >= r1:
        return None
    surface = np.array(dsm[r0:r1, c0:c1], dtype=np.float64)
    x_left, y_top = transform.c + c0 * pixel, transform.f - r0 * pixel
    labels = np.zeros(surface.shape, np.int32)
    for k, hole in enumerate(holes, start=1):
        # only the pixels of the hole's box can have their centre in it (the same labels; prepared,
        # 17.8 s -> see docs/performance.md for the 1 B point survey's 115 patterns)
        hx0, hy0, hx1, hy1 = hole.bounds
        b0, b1 = max(int((y_top - hy1) / pixel) - 1, 0), min(int(math.ceil((y_top - hy0) / pixel)) + 1, r1 - r0)
        d0, d1 = max(int((hx0 - x_left) / pixel) - 1, 0), min(int(math.ceil((hx1 - x_left) / pixel)) + 1, c1 - c0)
        if b0 >= b1 or d0 >= d1:
            continue
        rr, cc = np.ogrid[b0:b1, d0:d1]  # a column and a row: the centres broadcast, not a grid of each
        shapely.prepare(hole)
        inside_hole = shapely.contains_xy(hole, x_left + (cc + 0.5) * pixel, y_top - (rr + 0.5) * pixel)
        box = labels[b0:b1, d0:d1]
        box[(box == 0) & inside_hole] = k
    inside = labels > 0
    if not inside.any():
        return None
    # the ground at a hole pixel: the fill, or the lowest surface beside it where lower (a fill
    # that leans on a wall is no ground); a lower target only makes a seen ray less likely
    measured = np.isfinite(surface) & ~inside
    # NaN but at the hole pixels, where it is set in place: no window-sized temporaries (a 10 km strip's)
    targets = ground_targets(surface, measured, inside, step=ground_step_m, pixel_size=pixel)
    targets[inside] = np.fmin(surface[inside], targets[inside])
    floor = np.nanmin(surface[measured]) if measured.any() else np.nan
    targets[inside & np.isnan(targets)] = floor
    surface[inside] = np.nan  # the hole's own fill is a guess, and ground blocks no ray rising from ground
    return _Window(surface, targets, labels, x_left, y_top, pixel)
