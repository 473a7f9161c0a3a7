"""A whole re-flight plan: which holes, their patterns, the route, sorties and waypoints.

:func:`plan_mission` is the one entry point; it chains the kernels of
:mod:`.coverage`, :mod:`.route` and :mod:`.altitude` and returns a frozen
:class:`FlightPlan` that the file writers (``pipeline.io.flightplan_files``)
only serialise.

Heights: every waypoint carries ``height_m``, its height in the DSM's vertical
datum, and ``altitude_m``, the same height in the plan's reference
(``"takeoff"``: minus the DSM height at home; ``"amsl"``: unchanged;
``"ellipsoid"``: converted with a checked geoid transformation).

Pure: numpy arrays, shapely geometries and pyproj in; dataclasses out.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import pyproj
import shapely

from ..grid import z_order
from .altitude import AffineLike, Surface, height_at, lane_with_turns, max_height_along, nearest_data_point
from .clearance import flight_time_s, leg_clearance
from .coverage import CoverageParams, CoveragePattern, Lane, Point2, cluster_holes, plan_pattern, split_pattern
from .rescan import SightParams, place_pattern
from .route import (
    PatternEnds,
    Visit,
    greedy_route,
    improve_route,
    pattern_ends,
    pattern_variants,
    route_length,
    sortie_duration,
    split_sorties,
)
from .takeoff import Takeoff, TakeoffParams, check_home
from .takeoff_search import AreaMask, GroundGrid, nearest_open_ground

__all__ = ["FlightParams", "FlightPlan", "HoleDecision", "HoleInput", "Sortie", "Waypoint", "plan_mission"]

REFERENCES = ("takeoff", "amsl", "ellipsoid")


@dataclass(frozen=True)
class FlightParams:
    """Everything :func:`plan_mission` needs from ``[flightplan]`` (SI units)."""

    coverage: CoverageParams = field(default_factory=CoverageParams)
    causes: tuple[str, ...] = ("missed_coverage",)
    min_area_m2: float = 25.0
    speed_m_s: float = 6.0
    transit_speed_m_s: float = 12.0
    max_flight_time_s: float = 1200.0
    setup_time_s: float = 90.0
    terrain_step_m: float = 5.0
    altitude_reference: str = "takeoff"
    max_climb_gradient: float = 0.15
    min_clearance_m: float = 20.0
    clearance_radius_m: float = 3.0
    acceleration_m_s2: float = 2.0
    takeoff: TakeoffParams = field(default_factory=TakeoffParams)
    #: The height jump that tells a wall from the ground beside it (``holes.jump_threshold_m``),
    #: for the ground in an occlusion hole (:mod:`.rescan`).
    ground_step_m: float = 2.5


@dataclass(frozen=True)
class HoleInput:
    """One hole as the caller knows it; ``azimuth_deg`` imposes the lane direction."""

    hole_id: int
    geometry: shapely.Geometry
    cause: str
    area_m2: float
    azimuth_deg: float | None = None


@dataclass(frozen=True)
class HoleDecision:
    """Whether a hole is flown, and why not when it is not."""

    hole_id: int
    cause: str
    area_m2: float
    planned: bool
    reason: str
    pattern_id: int | None = None
    geometry: shapely.Geometry | None = None
    #: Share of the hole's pixels whose ground its lanes see (:mod:`.rescan`); None: not planned.
    visible_share: float | None = None


@dataclass(frozen=True)
class Waypoint:
    """A point of a sortie; ``actions`` in order, e.g. ``("pattern_entry",)``, ``("lane_start",)``."""

    sortie: int
    sequence: int
    x: float
    y: float
    lon: float
    lat: float
    height_m: float
    altitude_m: float
    actions: tuple[str, ...]
    pattern_id: int | None = None
    lane_index: int | None = None


@dataclass(frozen=True)
class FlownLane:
    """A lane as flown: its sortie and direction."""

    sortie: int
    pattern_id: int
    hole_ids: tuple[int, ...]
    lane: Lane


@dataclass(frozen=True)
class Sortie:
    """One flight from home and back."""

    number: int
    waypoints: tuple[Waypoint, ...]
    lanes: tuple[FlownLane, ...]
    length_m: float
    duration_s: float
    least_clearance_m: float = math.inf


@dataclass(frozen=True)
class FlightPlan:
    """The result of :func:`plan_mission`."""

    decisions: tuple[HoleDecision, ...]
    patterns: tuple[CoveragePattern, ...]
    sorties: tuple[Sortie, ...]
    home: Point2
    home_lonlat: Point2
    home_ground_m: float
    altitude_reference: str
    crs_wkt: str
    params: FlightParams
    greedy_length_m: float
    improved_length_m: float
    home_source: str = "DSM (no ground points)"
    home_warning: str = ""

    @property
    def flown_length_m(self) -> float:
        return sum(s.length_m for s in self.sorties)


def plan_mission(
    holes: list[HoleInput],
    dsm: Surface,
    transform: AffineLike,
    *,
    crs_wkt: str,
    params: FlightParams,
    home: Point2 | None = None,
    to_ellipsoid: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None,
    snap_home: bool = False,
    ground: GroundGrid | None = None,
) -> FlightPlan:
    """Plan the re-flight of the holes a drone can re-scan.

    Home: the given one, its ground height from ``ground`` (a warning when it is on a
    roof or canopy); else, with ``ground``, the open ground nearest to the planned holes
    (:mod:`.takeoff`); else the centre of the holes, moved with ``snap_home`` (a home
    nobody chose) to the nearest pixel with data, its height from the DSM.

    Parameters
    ----------
    holes : list of HoleInput
        In the survey's projected CRS (metres).
    dsm : ndarray of shape (M, N)
        Surface heights, NaN for no data; ``transform`` is its affine transform.
    home : (x, y), optional
        Take-off and landing point; default: the open ground nearest to the planned holes.
    ground : GroundGrid, optional
        Ground-class points on the DSM's grid, for the take-off point and its height.
    to_ellipsoid : callable, optional
        ``(x, y, height) -> ellipsoidal height``, checked by
        :func:`~.altitude.ellipsoid_transformer`; required for ``"ellipsoid"``.

    Raises
    ------
    ValueError
        No DSM height at home, an unknown altitude reference, or a leg that does not
        clear the surface by ``min_clearance_m`` (the message names the sortie and leg).
    """
    if params.altitude_reference not in REFERENCES:
        raise ValueError(f"altitude_reference must be one of {REFERENCES}, got {params.altitude_reference!r}")
    if params.altitude_reference == "ellipsoid" and to_ellipsoid is None:
        raise ValueError("altitude_reference 'ellipsoid' needs a checked to_ellipsoid conversion")
    selected, decisions = _select(holes, params)
    patterns, shares = _placed_patterns(_patterns(selected, params.coverage), selected, dsm, transform, params)
    takeoff = _choose_home(home, patterns, holes, dsm, transform, ground=ground, snap=snap_home, params=params)
    home, home_ground = takeoff.xy, takeoff.ground_m
    units, unit_ends, unflyable = _flyable_units(patterns, home, params)
    decisions = _mark_unflyable(decisions, unflyable, patterns)
    decisions = [replace(d, visible_share=shares.get(d.hole_id)) if d.planned else d for d in decisions]
    greedy, improved, sortie_visits = _routes(unit_ends, home, params)
    if not math.isfinite(home_ground) and sortie_visits:
        raise ValueError(f"no DSM height within 10 m of home {home}; choose a home point on open ground with data")
    to_lonlat = pyproj.Transformer.from_crs(pyproj.CRS.from_user_input(crs_wkt), "EPSG:4326", always_xy=True)
    shared = _SortieContext(units, unit_ends, home, dsm, transform, params, to_lonlat, home_ground, to_ellipsoid)
    sorties = [_sortie(number, visits, shared) for number, visits in enumerate(sortie_visits, start=1)]
    home_lonlat = to_lonlat.transform(*home)
    return FlightPlan(
        decisions=tuple(decisions),
        patterns=tuple(patterns),
        sorties=tuple(sorties),
        home=(float(home[0]), float(home[1])),
        home_lonlat=(float(home_lonlat[0]), float(home_lonlat[1])),
        home_ground_m=home_ground,
        altitude_reference=params.altitude_reference,
        crs_wkt=crs_wkt,
        params=params,
        greedy_length_m=route_length(greedy, unit_ends, home),
        improved_length_m=route_length(improved, unit_ends, home),
        home_source=takeoff.source,
        home_warning=takeoff.warning,
    )


def _routes(
    unit_ends: list[PatternEnds], home: Point2, params: FlightParams
) -> tuple[list[Visit], list[Visit], list[list[Visit]]]:
    """The greedy route, its improvement, and that split into sorties (each improved on its own)."""
    greedy = greedy_route(unit_ends, home)
    improved = improve_route(greedy, unit_ends, home)
    sortie_visits = split_sorties(
        improved,
        unit_ends,
        home,
        lane_speed_m_s=params.speed_m_s,
        transit_speed_m_s=params.transit_speed_m_s,
        setup_time_s=params.setup_time_s,
        max_flight_time_s=params.max_flight_time_s,
        acceleration_m_s2=params.acceleration_m_s2,
    )
    return greedy, improved, [improve_route(v, unit_ends, home) for v in sortie_visits]


@dataclass(frozen=True)
class _SortieContext:
    """What every sortie of a plan shares: the flyable patterns and their ends, home, the DSM, the conversions."""

    units: list[CoveragePattern]
    unit_ends: list[PatternEnds]
    home: Point2
    dsm: Surface
    transform: AffineLike
    params: FlightParams
    to_lonlat: pyproj.Transformer
    home_ground: float
    to_ellipsoid: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None


def _sortie(number: int, visits: list[Visit], shared: _SortieContext) -> Sortie:
    """Sortie ``number``: its waypoints, the lanes it flies, its length and duration."""
    units, unit_ends, home, params = shared.units, shared.unit_ends, shared.home, shared.params
    raw = _sortie_points(visits, units, home, shared.dsm, shared.transform, params)
    least = _check_clearance(number, raw, shared.dsm, shared.transform, params)
    waypoints = _finish_waypoints(
        number, raw, shared.to_lonlat, shared.home_ground, params.altitude_reference, shared.to_ellipsoid
    )
    lanes = tuple(
        FlownLane(number, units[v.pattern].pattern_id, units[v.pattern].hole_ids, lane)
        for v in visits
        for lane in pattern_variants(units[v.pattern])[v.variant]
    )
    length = route_length(visits, unit_ends, home)
    return Sortie(number, waypoints, lanes, length, params.setup_time_s + _flight_time(raw, params), least)


def _leg_speeds(points: list[_Point], params: FlightParams) -> np.ndarray:
    """Transit speed on legs from take-off or a pattern's exit, lane speed on the others."""
    transit = [p.actions[0] in ("takeoff", "pattern_exit") for p in points[:-1]]
    return np.where(transit, params.transit_speed_m_s, params.speed_m_s).astype(float)


def _flight_time(points: list[_Point], params: FlightParams) -> float:
    """Seconds in the air between the take-off height and home: legs, turns and speed changes."""
    xyz = np.array([(p.xy[0], p.xy[1], p.height) for p in points], dtype=float)
    return flight_time_s(xyz, _leg_speeds(points, params), acceleration_m_s2=params.acceleration_m_s2)


def _check_clearance(sortie: int, points: list[_Point], dsm: Surface, transform, params: FlightParams) -> float:
    """The least clearance of a sortie's legs; refuses a leg below ``min_clearance_m``."""
    least = math.inf
    for leg, (a, b) in enumerate(zip(points[:-1], points[1:]), start=1):
        clearance = leg_clearance(dsm, transform, a.xy, b.xy, (a.height, b.height), radius_m=params.clearance_radius_m)
        if clearance < params.min_clearance_m:
            raise ValueError(
                f"sortie {sortie}, leg {leg} ({a.actions[0]} -> {b.actions[0]}, from {a.xy[0]:.1f}, {a.xy[1]:.1f} "
                f"to {b.xy[0]:.1f}, {b.xy[1]:.1f}) clears the highest surface within "
                f"{params.clearance_radius_m:g} m by {clearance:.1f} m < flightplan.min_clearance_m = "
                f"{params.min_clearance_m:g}; raise flightplan.altitude_agl_m or lower min_clearance_m"
            )
        least = min(least, clearance)
    return least


def _select(holes: list[HoleInput], params: FlightParams) -> tuple[list[HoleInput], list[HoleDecision]]:
    selected, decisions = [], []
    for hole in holes:
        if hole.cause not in params.causes:
            reason = f"cause '{hole.cause}' is not re-flown (flightplan.causes = {list(params.causes)})"
        elif hole.area_m2 < params.min_area_m2:
            reason = f"area {hole.area_m2:.1f} m2 < flightplan.min_area_m2 = {params.min_area_m2:g}"
        elif hole.geometry is None or hole.geometry.is_empty:
            reason = "empty geometry"
        else:
            selected.append(hole)
            decisions.append(HoleDecision(hole.hole_id, hole.cause, hole.area_m2, True, "", geometry=hole.geometry))
            continue
        decisions.append(HoleDecision(hole.hole_id, hole.cause, hole.area_m2, False, reason, geometry=hole.geometry))
    return selected, decisions


def _patterns(selected: list[HoleInput], coverage: CoverageParams) -> list[CoveragePattern]:
    groups = cluster_holes([h.geometry for h in selected], coverage.spacing_m)
    patterns = []
    for pattern_id, group in enumerate(groups, start=1):
        members = [selected[i] for i in group]
        oriented = [h for h in members if h.azimuth_deg is not None]
        azimuth = max(oriented, key=lambda h: h.area_m2).azimuth_deg if oriented else None
        area = shapely.union_all([h.geometry for h in members])
        patterns.append(
            plan_pattern(
                area,
                params=coverage,
                pattern_id=pattern_id,
                hole_ids=tuple(h.hole_id for h in members),
                azimuth_deg=azimuth,
            )
        )
    return patterns


def _placed_patterns(
    patterns: list[CoveragePattern],
    selected: list[HoleInput],
    dsm: Surface,
    transform: AffineLike,
    params: FlightParams,
) -> tuple[list[CoveragePattern], dict[int, float]]:
    """Each pattern with an occlusion hole re-placed where its ground is in sight, and every hole's visible share."""
    sight = SightParams(
        coverage=params.coverage,
        max_climb_gradient=params.max_climb_gradient,
        terrain_step_m=params.terrain_step_m,
        ground_step_m=params.ground_step_m,
        min_gain_m2=params.min_area_m2,
    )
    by_id = {h.hole_id: h for h in selected}
    placed: list[CoveragePattern | None] = [None] * len(patterns)
    shares = {}
    # placed in Z order of their centres, the results kept in the patterns' order: the DSM is read
    # in blocks kept while they fit in a cache, and patterns met neighbour after neighbour find
    # their blocks still there (each pattern's placement is its own; the order changes no result)
    for index in _z_order([p.area.centroid for p in patterns]):
        pattern = patterns[index]
        members = [by_id[i] for i in pattern.hole_ids]
        rescan = any(h.cause == "occlusion" for h in members)
        keep = any(h.cause != "occlusion" for h in members)  # their lanes keep their spacing and overlap
        geometries = [h.geometry for h in members]
        found = place_pattern(pattern, geometries, dsm, transform, params=sight, rescan=rescan, keep_lanes=keep)
        placed[index] = found.pattern
        shares.update(found.shares)
    return [p for p in placed if p is not None], shares


def _z_order(points: list) -> list[int]:
    """Indices of ``points`` (shapely points) along a Z-order curve over their bounding box (:func:`pipeline.grid.z_order`)."""
    if len(points) < 2:
        return list(range(len(points)))
    xy = np.array([(p.x, p.y) for p in points], dtype=np.float64)
    low, span = xy.min(axis=0), np.ptp(xy, axis=0)
    scaled = np.floor((xy - low) / np.where(span > 0, span, 1.0) * 65535).astype(np.int64)
    return [int(i) for i in z_order(scaled[:, 0], scaled[:, 1])]


def _choose_home(
    home: Point2 | None,
    patterns: list[CoveragePattern],
    holes: list[HoleInput],
    dsm: Surface,
    transform: AffineLike,
    *,
    ground: GroundGrid | None,
    snap: bool,
    params: FlightParams,
) -> Takeoff:
    """The take-off point and its ground height (the module docstring of :mod:`.takeoff`)."""
    if home is not None and ground is not None:
        ground.load_around(home, transform, 2 * params.takeoff.clear_radius_m)
        return check_home(dsm, ground.height, transform, home, params=params.takeoff)
    if home is None and ground is not None and patterns:
        areas = [p.area for p in patterns]
        targets = AreaMask(areas, dsm.shape, transform)  # held near the holes, not over the survey's span
        found = nearest_open_ground(dsm, transform, targets, ground, params.takeoff, within=targets.boxes)
        if found is not None:
            return found
    # warned only where a take-off was sought: with no hole to re-fly there is no flight to take off for
    sought = home is None and ground is not None and bool(patterns)
    warning = "no open ground with ground points near the holes" if sought else ""
    if home is None:
        home = _default_home(patterns, holes)
    if snap and not math.isfinite(height_at(dsm, transform, home)):
        # a home nobody chose, in a hole or off the data: the nearest point with a surface height
        home = nearest_data_point(dsm, transform, home) or home
    return Takeoff(home, height_at(dsm, transform, home), "DSM (no ground points)", warning)


def _default_home(patterns: list[CoveragePattern], holes: list[HoleInput]) -> Point2:
    geometries = [p.area for p in patterns] or [h.geometry for h in holes if h.geometry is not None]
    if not geometries:
        return (0.0, 0.0)
    centre = shapely.union_all(geometries).centroid
    return (float(centre.x), float(centre.y))


def _flyable_units(
    patterns: list[CoveragePattern], home: Point2, params: FlightParams
) -> tuple[list[CoveragePattern], list[PatternEnds], dict[int, str]]:
    """Patterns, each cut into parts of neighbouring lanes when it alone exceeds a sortie."""
    units, ends, unflyable = [], [], {}

    def alone(pattern: CoveragePattern) -> tuple[float, PatternEnds]:
        e = pattern_ends(pattern)
        best = min(
            sortie_duration(
                [Visit(0, v)],
                [e],
                home,
                params.speed_m_s,
                params.transit_speed_m_s,
                params.setup_time_s,
                acceleration_m_s2=params.acceleration_m_s2,
            )  # fmt: skip
            for v in range(len(e.entries))
        )
        return best, e

    for pattern in patterns:
        parts = 1
        while True:
            pieces = split_pattern(pattern, parts) if parts > 1 else [pattern]
            timed = [alone(p) for p in pieces]
            if all(t <= params.max_flight_time_s for t, _ in timed):
                units += pieces
                ends += [e for _, e in timed]
                break
            if parts >= len(pattern.lanes):
                worst = max(t for t, _ in timed)
                unflyable[pattern.pattern_id] = (
                    f"one lane of pattern {pattern.pattern_id} needs {worst:.0f} s from home and back "
                    f"> flightplan.max_flight_time_s = {params.max_flight_time_s:g}"
                )
                break
            parts += 1
    return units, ends, unflyable


def _mark_unflyable(
    decisions: list[HoleDecision], unflyable: dict[int, str], patterns: list[CoveragePattern]
) -> list[HoleDecision]:
    pattern_of = {h: p.pattern_id for p in patterns for h in p.hole_ids}
    out = []
    for d in decisions:
        if d.planned:
            pid = pattern_of[d.hole_id]
            if pid in unflyable:
                d = HoleDecision(d.hole_id, d.cause, d.area_m2, False, unflyable[pid], pid, d.geometry)
            else:
                d = HoleDecision(d.hole_id, d.cause, d.area_m2, True, "", pid, d.geometry)
        out.append(d)
    return out


@dataclass
class _Point:
    xy: Point2
    height: float
    actions: list[str]
    pattern_id: int | None = None
    lane_index: int | None = None


def _sortie_points(
    visits: list[Visit],
    units: list[CoveragePattern],
    home: Point2,
    dsm: Surface,
    transform: AffineLike,
    params: FlightParams,
) -> list[_Point]:
    """The points of one sortie with safe heights in the DSM's datum."""
    agl = params.coverage.altitude_agl_m
    points = [_Point(home, -math.inf, ["takeoff"])]
    for visit in visits:
        pattern = units[visit.pattern]
        lanes = pattern_variants(pattern)[visit.variant]
        for k, lane in enumerate(lanes):
            lane_points = _lane_points(lane, pattern, dsm, transform, params)
            lane_points[0].actions = ["pattern_entry"] if k == 0 else ["turn"]
            lane_points[-1].actions = ["pattern_exit"] if k == len(lanes) - 1 else ["turn"]
            if k > 0:  # both turn points of a turn fly at the higher of the two lanes
                high = max(points[-1].height, lane_points[0].height)
                points[-1].height = lane_points[0].height = high
            points += lane_points
    points.append(_Point(home, -math.inf, ["home"]))
    legs = [i for i, p in enumerate(points) if p.actions[0] in ("takeoff", "pattern_exit")]
    for i in legs:  # transit legs: above the highest surface along them
        a, b = points[i], points[i + 1]
        surface = max_height_along(dsm, transform, a.xy, b.xy, half_width_m=max(params.coverage.swath_m / 2, 20.0))
        if not math.isfinite(surface):
            surface = max(a.height, b.height) - agl
        high = surface + agl
        a.height, b.height = max(a.height, high), max(b.height, high)
    return _merge_coincident(points)


def _lane_points(
    lane: Lane, pattern: CoveragePattern, dsm: Surface, transform: AffineLike, params: FlightParams
) -> list[_Point]:
    """Turn point, lane start, lane end, turn point, on one straight line (:func:`.altitude.lane_line`)."""
    t = pattern.turnaround_m
    length = lane.length_m
    d = ((lane.end[0] - lane.start[0]) / length, (lane.end[1] - lane.start[1]) / length)
    before, _, first, last = lane_with_turns(
        lane,
        t,
        dsm,
        transform,
        params.coverage,
        max_gradient=params.max_climb_gradient,
        slope_gain_m=params.terrain_step_m,
    )
    total = 2 * t + length
    points = []
    for u, action in ((0.0, "turn"), (t, "lane_start"), (t + length, "lane_end"), (total, "turn")):
        xy = (before[0] + d[0] * u, before[1] + d[1] * u)
        height = first + (last - first) * (u / total if total > 0 else 0.0)
        points.append(_Point(xy, height, [action], pattern.pattern_id, lane.index))
    return points


def _merge_coincident(points: list[_Point]) -> list[_Point]:
    """Join consecutive points closer than 1 cm (e.g. a zero turnaround), keeping all actions."""
    merged = [points[0]]
    for p in points[1:]:
        last = merged[-1]
        if math.dist(last.xy, p.xy) < 0.01 and last.actions[0] != "takeoff" and p.actions[0] != "home":
            last.actions += p.actions
            last.height = max(last.height, p.height)
            last.pattern_id = last.pattern_id if last.pattern_id is not None else p.pattern_id
            last.lane_index = p.lane_index if p.lane_index is not None else last.lane_index
        else:
            merged.append(p)
    return merged


def _finish_waypoints(
    sortie: int,
    points: list[_Point],
    to_lonlat: pyproj.Transformer,
    home_ground: float,
    reference: str,
    to_ellipsoid: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None,
) -> tuple[Waypoint, ...]:
    x = np.array([p.xy[0] for p in points])
    y = np.array([p.xy[1] for p in points])
    heights = np.array([p.height for p in points])
    lon, lat = to_lonlat.transform(x, y)
    if reference == "takeoff":
        altitude = heights - home_ground
    elif reference == "amsl":
        altitude = heights
    else:
        assert to_ellipsoid is not None, "plan_mission checks that 'ellipsoid' comes with a conversion"
        altitude = to_ellipsoid(x, y, heights)
    return tuple(
        Waypoint(
            sortie,
            i,
            float(x[i]),
            float(y[i]),
            float(lon[i]),
            float(lat[i]),
            float(heights[i]),
            float(altitude[i]),
            tuple(p.actions),
            p.pattern_id,
            p.lane_index,
        )
        for i, p in enumerate(points)
    )
