"""Coverage patterns: boustrophedon lanes laid over holes.

The UAS paper ([UAS] section 4, ``seeds/hole-detection-and-reflight-uas.txt``)
encloses each hole in an axis-aligned box and flies lanes along its longer side.
Here the box is the hole's *minimum rotated rectangle* (after a safety margin),
so a thin diagonal strip gets a few long lanes instead of many short ones; a
caller may instead impose a lane azimuth (e.g. the direction of the original
flight lines, for a strip missed between two of them). Holes closer together than
one lane spacing share one pattern.

Lanes are straight segments at constant lidar recording; they extend by
``run_in_m`` beyond the rectangle on both ends so the sensor is steady over the
hole. Turns happen ``turnaround_m`` beyond the lane ends, without recording.

Coordinates are metres in a projected CRS; azimuths are degrees clockwise from
grid north, in [0, 180) for a lane direction.

Pure functions: shapely geometries and floats in, frozen dataclasses out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import LineString, Polygon

__all__ = [
    "CoverageParams",
    "CoveragePattern",
    "Lane",
    "cluster_holes",
    "lane_spacing",
    "plan_pattern",
    "swath_width",
]

Point2 = tuple[float, float]


@dataclass(frozen=True)
class CoverageParams:
    """What shapes a coverage pattern (from ``[flightplan]``, in metres and degrees)."""

    altitude_agl_m: float = 60.0
    fov_deg: float = 70.0
    side_overlap: float = 0.3
    run_in_m: float = 20.0
    turnaround_m: float = 10.0
    margin_m: float = 5.0

    @property
    def swath_m(self) -> float:
        """Full cross-track width of the lidar footprint on the highest surface."""
        return swath_width(self.altitude_agl_m, self.fov_deg)

    @property
    def spacing_m(self) -> float:
        """Distance between neighbouring lanes (the effective swath)."""
        return lane_spacing(self.altitude_agl_m, self.fov_deg, self.side_overlap)


@dataclass(frozen=True)
class Lane:
    """One scanning lane, flown from ``start`` to ``end`` with the lidar recording.

    ``start`` and ``end`` include the run-in on both sides of the hole rectangle.
    """

    index: int
    start: Point2
    end: Point2

    @property
    def length_m(self) -> float:
        return math.dist(self.start, self.end)

    @property
    def azimuth_deg(self) -> float:
        """Direction of flight, degrees clockwise from grid north in [0, 360)."""
        return _azimuth(self.start, self.end)

    def reversed(self) -> Lane:
        return Lane(self.index, self.end, self.start)

    def line(self) -> LineString:
        return LineString([self.start, self.end])


@dataclass(frozen=True)
class CoveragePattern:
    """The lanes that cover one hole, or several holes close together.

    Lanes are ordered across track and all point the same way (``azimuth_deg``);
    the route decides where to enter and which way to fly each one
    (:func:`pipeline.flightplan.route.pattern_variants`).
    """

    pattern_id: int
    hole_ids: tuple[int, ...]
    area: Polygon
    rectangle: Polygon
    azimuth_deg: float
    spacing_m: float
    lanes: tuple[Lane, ...]
    turnaround_m: float

    @property
    def scan_length_m(self) -> float:
        return sum(lane.length_m for lane in self.lanes)

    @property
    def turn_length_m(self) -> float:
        """Length flown between lanes (beyond the ends and across), lidar off."""
        turns = len(self.lanes) - 1
        return turns * (2 * self.turnaround_m + self.spacing_m) + 2 * self.turnaround_m


def swath_width(altitude_agl_m: float, fov_deg: float) -> float:
    """Cross-track width of the lidar footprint: ``2 h tan(fov / 2)``.

    Raises
    ------
    ValueError
        If the field of view is not in (0, 180) degrees.
    """
    if not 0 < fov_deg < 180:
        raise ValueError(f"fov_deg must be between 0 and 180 degrees, got {fov_deg}")
    return 2.0 * altitude_agl_m * math.tan(math.radians(fov_deg) / 2.0)


def lane_spacing(altitude_agl_m: float, fov_deg: float, side_overlap: float) -> float:
    """Distance between lanes: ``swath x (1 - side_overlap)``."""
    if not 0 <= side_overlap < 1:
        raise ValueError(f"side_overlap must be in [0, 1), got {side_overlap}")
    return swath_width(altitude_agl_m, fov_deg) * (1.0 - side_overlap)


def cluster_holes(polygons: list[shapely.Geometry], distance_m: float) -> list[list[int]]:
    """Group holes closer together than ``distance_m`` (transitively).

    Returns
    -------
    list of list of int
        Indices into ``polygons``; groups in order of their first member.
    """
    parent = list(range(len(polygons)))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    if polygons:
        tree = shapely.STRtree(polygons)
        left, right = tree.query(polygons, predicate="dwithin", distance=distance_m)
        for a, b in zip(left.tolist(), right.tolist()):
            # dwithin is inclusive; "closer than" one spacing means strictly less
            if a < b and shapely.distance(polygons[a], polygons[b]) < distance_m:
                parent[find(a)] = find(b)
    groups: dict[int, list[int]] = {}
    for i in range(len(polygons)):
        groups.setdefault(find(i), []).append(i)
    return sorted(groups.values(), key=lambda g: g[0])


def plan_pattern(
    area: shapely.Geometry,
    *,
    params: CoverageParams,
    pattern_id: int = 0,
    hole_ids: tuple[int, ...] = (),
    azimuth_deg: float | None = None,
) -> CoveragePattern:
    """Boustrophedon lanes covering ``area`` buffered by the margin.

    Parameters
    ----------
    area : Polygon or MultiPolygon
        The hole (or the union of close holes), projected metres.
    azimuth_deg : float, optional
        Lane direction imposed by the caller (e.g. the original flight lines);
        default: the long side of the minimum rotated rectangle.

    Returns
    -------
    CoveragePattern
        ``n = ceil(width / spacing)`` lanes centred across the rectangle, so the
        lanes buffered by half the spacing cover the rectangle and thus the hole.
    """
    buffered = area.buffer(params.margin_m) if params.margin_m > 0 else area
    if buffered.is_empty:
        raise ValueError(f"pattern {pattern_id}: the hole geometry is empty")
    if azimuth_deg is None:
        azimuth_deg = _long_side_azimuth(shapely.minimum_rotated_rectangle(buffered))
    azimuth_deg = azimuth_deg % 180.0
    along = np.array([math.sin(math.radians(azimuth_deg)), math.cos(math.radians(azimuth_deg))])
    across = np.array([along[1], -along[0]])
    coords = _exterior_coords(buffered)
    u, v = coords @ along, coords @ across
    u_min, u_max, v_min, v_max = u.min(), u.max(), v.min(), v.max()
    rectangle = Polygon(
        [tuple(uu * along + vv * across) for uu, vv in ((u_min, v_min), (u_max, v_min), (u_max, v_max), (u_min, v_max))]
    )
    spacing = params.spacing_m
    n_lanes = max(1, math.ceil((v_max - v_min) / spacing - 1e-9))
    v_centre = (v_min + v_max) / 2.0
    lanes = []
    for i in range(n_lanes):
        v_i = v_centre + (i - (n_lanes - 1) / 2.0) * spacing
        start = (u_min - params.run_in_m) * along + v_i * across
        end = (u_max + params.run_in_m) * along + v_i * across
        lanes.append(Lane(i, (float(start[0]), float(start[1])), (float(end[0]), float(end[1]))))
    return CoveragePattern(
        pattern_id=pattern_id,
        hole_ids=tuple(hole_ids),
        area=buffered,
        rectangle=rectangle,
        azimuth_deg=float(azimuth_deg),
        spacing_m=spacing,
        lanes=tuple(lanes),
        turnaround_m=params.turnaround_m,
    )


def split_pattern(pattern: CoveragePattern, parts: int) -> list[CoveragePattern]:
    """Cut a pattern's lanes into ``parts`` groups of neighbouring lanes.

    Used when one pattern alone does not fit in a sortie; each part keeps the
    pattern id and is flown as a pattern of its own.
    """
    chunks = np.array_split(np.arange(len(pattern.lanes)), parts)
    out = []
    for chunk in chunks:
        if len(chunk) == 0:
            continue
        lanes = tuple(pattern.lanes[i] for i in chunk)
        out.append(
            CoveragePattern(
                pattern_id=pattern.pattern_id,
                hole_ids=pattern.hole_ids,
                area=pattern.area,
                rectangle=pattern.rectangle,
                azimuth_deg=pattern.azimuth_deg,
                spacing_m=pattern.spacing_m,
                lanes=lanes,
                turnaround_m=pattern.turnaround_m,
            )
        )
    return out


def _long_side_azimuth(rectangle: shapely.Geometry) -> float:
    """Azimuth in [0, 180) of the longer side of a (rotated) rectangle."""
    coords = np.asarray(rectangle.exterior.coords) if isinstance(rectangle, Polygon) else np.asarray(rectangle.coords)
    if len(coords) < 3:  # a point or a segment: its own direction (or north)
        if len(coords) < 2 or math.dist(coords[0], coords[-1]) == 0:
            return 0.0
        return _azimuth(tuple(coords[0]), tuple(coords[-1])) % 180.0
    side_a = (tuple(coords[0]), tuple(coords[1]))
    side_b = (tuple(coords[1]), tuple(coords[2]))
    longer = side_a if math.dist(*side_a) >= math.dist(*side_b) else side_b
    return _azimuth(*longer) % 180.0


def _azimuth(start: Point2, end: Point2) -> float:
    return math.degrees(math.atan2(end[0] - start[0], end[1] - start[1])) % 360.0


def _exterior_coords(geometry: shapely.Geometry) -> np.ndarray:
    hull = geometry.convex_hull
    if isinstance(hull, Polygon):
        return np.asarray(hull.exterior.coords)
    return np.asarray(shapely.get_coordinates(hull))
