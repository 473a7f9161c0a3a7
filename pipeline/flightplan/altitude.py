"""Flying heights from the DSM, and the vertical reference they are written in.

A lane is flown at ``altitude_agl_m`` above the *highest* DSM surface under its
whole swath (not only under its centre line), so the lidar keeps at least that
range to anything it passes over. Where that surface changes by more than
``terrain_step_m`` along the lane, the lane is cut into sections flown at their
own heights (:func:`lane_sections`); a waypoint between two sections takes the
higher of the two, so the straight climb or descent between waypoints never
drops below either section's height.

Heights in the DSM are in its own vertical datum (usually a national
orthometric height, close to mean sea level). Converting them to ellipsoidal
heights needs a geoid grid; without it PROJ silently applies a "ballpark"
transformation that changes nothing. :func:`ellipsoid_transformer` refuses in
that case instead of letting wrong heights be written.

Pure functions: numpy arrays, an affine transform, shapely and pyproj.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import pyproj

from ..errors import ConfigError, CRSError
from .coverage import CoverageParams, Lane, Point2

__all__ = [
    "AffineLike",
    "LaneSection",
    "corridor_profile",
    "ellipsoid_transformer",
    "height_at",
    "lane_line",
    "lane_sections",
    "max_height_along",
]


class AffineLike(Protocol):
    """An affine pixel-to-world transform (``affine.Affine``): x = a col + b row + c, y = d col + e row + f."""

    @property
    def a(self) -> float: ...
    @property
    def b(self) -> float: ...
    @property
    def c(self) -> float: ...
    @property
    def d(self) -> float: ...
    @property
    def e(self) -> float: ...
    @property
    def f(self) -> float: ...


@dataclass(frozen=True)
class LaneSection:
    """A stretch of a lane flown at one height (metres in the DSM's datum)."""

    start: Point2
    end: Point2
    surface_max_m: float


class Surface(Protocol):
    """What the planner reads of a DSM or a ground grid: its shape and pixels by index, window or
    index arrays, as of a float64 array with NaN for no data (an array; the DSM read block by block
    on request, :class:`pipeline.io.flightplan_files.DsmWindows`; the ground grids' ``BoxGrid``)."""

    @property
    def shape(self) -> tuple[int, ...]: ...

    def __getitem__(self, key: Any) -> Any: ...


def corridor_profile(
    dsm: Surface,
    transform: AffineLike,
    start: Point2,
    end: Point2,
    *,
    half_width_m: float,
    step_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Highest DSM value in along-track bins of a corridor around a segment.

    A pixel counts when its centre is within ``half_width_m`` plus half a pixel
    diagonal of the segment (so every pixel the corridor touches is included).

    Parameters
    ----------
    dsm : ndarray of shape (M, N)
        Heights, NaN where there is no data (holes are ignored, not zero).
    transform : Affine
        Pixel-to-world transform of ``dsm``.

    Returns
    -------
    edges : ndarray of shape (K + 1,)
        Bin edges in metres along the segment, from 0 to its length.
    maxima : ndarray of shape (K,)
        Highest value per bin; NaN where the bin holds no data.
    """
    length = math.dist(start, end)
    n_bins = max(1, math.ceil(length / step_m))
    edges = np.linspace(0.0, length, n_bins + 1)
    maxima = np.full(n_bins, np.nan)
    bin_width = length / n_bins if length > 0 else 1.0
    for values, along in pixels_near_segment(dsm, transform, start, end, half_width_m):
        bins = np.minimum((along / bin_width).astype(int), n_bins - 1)
        np.fmax.at(maxima, bins, values)
    return edges, maxima


def pixels_near_segment(
    dsm: Surface, transform: AffineLike, start: Point2, end: Point2, radius_m: float
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """The DSM's measured pixels whose centre lies within ``radius_m`` (plus half a pixel's diagonal)
    of a segment: their values and their distance along it from ``start``, window by window (a
    long diagonal segment is read piece by piece, so the windows stay small)."""
    length = math.dist(start, end)
    pixel = math.hypot(transform.a, transform.d), math.hypot(transform.b, transform.e)
    reach = radius_m + 0.5 * math.hypot(*pixel)
    direction = (np.array([end[0] - start[0], end[1] - start[1]]) / length) if length > 0 else np.zeros(2)
    pieces = max(1, math.ceil(length / max(4 * reach, 50.0)))
    for k in range(pieces):
        a = (start[0] + direction[0] * length * k / pieces, start[1] + direction[1] * length * k / pieces)
        b = (start[0] + direction[0] * length * (k + 1) / pieces, start[1] + direction[1] * length * (k + 1) / pieces)
        rows, cols = _window(dsm.shape, transform, a, b, reach)
        if rows.size == 0:
            continue
        values = dsm[rows, cols].astype(float)
        x = transform.a * (cols + 0.5) + transform.b * (rows + 0.5) + transform.c
        y = transform.d * (cols + 0.5) + transform.e * (rows + 0.5) + transform.f
        dx, dy = x - start[0], y - start[1]
        along = np.clip(dx * direction[0] + dy * direction[1], 0.0, length)
        keep = (np.hypot(dx - along * direction[0], dy - along * direction[1]) <= reach) & np.isfinite(values)
        if keep.any():
            yield values[keep], along[keep]


def max_height_along(dsm: Surface, transform: AffineLike, start: Point2, end: Point2, *, half_width_m: float) -> float:
    """Highest DSM value within ``half_width_m`` of a segment; NaN if none."""
    pixel = max(math.hypot(transform.a, transform.d), math.hypot(transform.b, transform.e))
    _, maxima = corridor_profile(dsm, transform, start, end, half_width_m=half_width_m, step_m=max(pixel, 1.0) * 64)
    return float(np.nanmax(maxima)) if np.isfinite(maxima).any() else math.nan


def height_at(dsm: Surface, transform: AffineLike, point: Point2, *, search_m: float = 10.0) -> float:
    """DSM value at a point; if that pixel is empty, the median within ``search_m``; NaN if none."""
    inverse = _inverse(transform)
    col = inverse[0] * point[0] + inverse[1] * point[1] + inverse[2]
    row = inverse[3] * point[0] + inverse[4] * point[1] + inverse[5]
    r, c = int(math.floor(row)), int(math.floor(col))
    if 0 <= r < dsm.shape[0] and 0 <= c < dsm.shape[1] and np.isfinite(dsm[r, c]):
        return float(dsm[r, c])
    rows, cols = _window(dsm.shape, transform, point, point, search_m)
    values = dsm[rows, cols].astype(float) if rows.size else np.array([])
    values = values[np.isfinite(values)]
    return float(np.median(values)) if values.size else math.nan


def nearest_data_point(dsm: Surface, transform: AffineLike, point: Point2) -> Point2 | None:
    """The centre of the DSM pixel with data nearest to ``point`` (None when the DSM is empty)."""
    import scipy.ndimage as ndi

    empty = ~np.isfinite(dsm[:, :])  # the whole grid: a home nobody chose, in a hole or off the data
    if empty.all():
        return None
    inverse = _inverse(transform)
    col = inverse[0] * point[0] + inverse[1] * point[1] + inverse[2]
    row = inverse[3] * point[0] + inverse[4] * point[1] + inverse[5]
    r = min(max(int(math.floor(row)), 0), dsm.shape[0] - 1)
    c = min(max(int(math.floor(col)), 0), dsm.shape[1] - 1)
    _, (rows, cols) = ndi.distance_transform_edt(empty, return_indices=True)
    rr, cc = int(rows[r, c]) + 0.5, int(cols[r, c]) + 0.5
    t = transform
    return (t.a * cc + t.b * rr + t.c, t.d * cc + t.e * rr + t.f)


def lane_sections(
    dsm: Surface,
    transform: AffineLike,
    start: Point2,
    end: Point2,
    *,
    half_width_m: float,
    terrain_step_m: float,
    step_m: float | None = None,
) -> list[LaneSection]:
    """Cut a lane where the highest surface under its swath changes by more than ``terrain_step_m``.

    Bins without data take the highest value of the whole corridor (a hole
    under the lane says nothing about its height; the surroundings bound it).

    Raises
    ------
    ValueError
        If the corridor holds no DSM value at all.
    """
    pixel = max(math.hypot(transform.a, transform.d), math.hypot(transform.b, transform.e))
    step = step_m or max(pixel, terrain_step_m)
    edges, maxima = corridor_profile(dsm, transform, start, end, half_width_m=half_width_m, step_m=step)
    if not np.isfinite(maxima).any():
        raise ValueError(f"no DSM height within {half_width_m:.0f} m of the segment {start} -> {end}")
    maxima = np.where(np.isfinite(maxima), maxima, np.nanmax(maxima))
    length = edges[-1]
    direction = ((end[0] - start[0]) / (length or 1.0), (end[1] - start[1]) / (length or 1.0))

    def at(u: float) -> Point2:
        return (start[0] + direction[0] * u, start[1] + direction[1] * u)

    sections, first = [], 0
    low = high = maxima[0]
    for k in range(1, len(maxima) + 1):
        if k < len(maxima):
            new_low, new_high = min(low, maxima[k]), max(high, maxima[k])
            if new_high - new_low <= terrain_step_m:
                low, high = new_low, new_high
                continue
        sections.append(LaneSection(at(edges[first]), at(edges[k]), float(high)))
        if k < len(maxima):
            first, low, high = k, maxima[k], maxima[k]
    return sections


def lane_line(
    dsm: Surface,
    transform: AffineLike,
    start: Point2,
    end: Point2,
    *,
    half_width_m: float,
    altitude_agl_m: float,
    max_gradient: float,
    slope_gain_m: float,
) -> tuple[float, float]:
    """Heights (DSM datum) at the ends of a lane flown as one straight line, level or inclined.

    Level: the highest surface under the whole swath plus ``altitude_agl_m``. Inclined:
    the lowest straight line with a gradient of at most ``max_gradient`` that keeps
    ``altitude_agl_m`` above the highest surface of every along-track bin, chosen only
    when it lowers the lane's mean height by more than ``slope_gain_m`` (strongly
    sloping ground). Either way the lane is one straight segment: it never follows
    the canopy, and the lidar range changes smoothly.

    A lane over a void wider than its swath (a missed flight line's strip, the reason to fly
    it) has no DSM value under it: the corridor is widened, doubling, until it reaches the
    measured surface beside the void, whose highest value then stands for the whole lane (the
    surface under the void is unknown; what stands around it is the best guess of what may).

    Raises
    ------
    ValueError
        If no widening up to the DSM's own extent finds a DSM value.
    """
    pixel = max(math.hypot(transform.a, transform.d), math.hypot(transform.b, transform.e))
    extent = pixel * math.hypot(*dsm.shape)
    width = half_width_m
    edges, maxima = corridor_profile(dsm, transform, start, end, half_width_m=width, step_m=max(pixel, 1.0))
    while not np.isfinite(maxima).any() and width < extent:
        width *= 2.0
        edges, maxima = corridor_profile(dsm, transform, start, end, half_width_m=width, step_m=max(pixel, 1.0))
        maxima = np.full_like(maxima, np.nanmax(maxima)) if np.isfinite(maxima).any() else maxima
    if not np.isfinite(maxima).any():
        raise ValueError(f"no DSM height within {half_width_m:.0f} m of the lane {start} -> {end}")
    need = np.where(np.isfinite(maxima), maxima, np.nanmax(maxima)) + altitude_agl_m
    length = float(edges[-1])
    level = float(need.max())
    if max_gradient <= 0 or length <= 0:
        return level, level
    slopes = np.linspace(-max_gradient, max_gradient, 81)
    # the line c + s u stays above every bin's need over the whole bin (both edges)
    low_edge = np.minimum(slopes[:, None] * edges[None, :-1], slopes[:, None] * edges[None, 1:])
    intercepts = (need[None, :] - low_edge).max(axis=1)
    means = intercepts + slopes * length / 2.0
    best = int(np.argmin(means))
    if level - means[best] <= slope_gain_m:
        return level, level
    return float(intercepts[best]), float(intercepts[best] + slopes[best] * length)


def ellipsoid_transformer(
    vertical_crs: pyproj.CRS, *, probe: Point2, probe_height_m: float = 100.0
) -> Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """A function converting (x, y, DSM height) to WGS84 ellipsoidal heights, checked.

    Parameters
    ----------
    vertical_crs : pyproj.CRS
        The DSM's compound CRS (horizontal + vertical), e.g. ``EPSG:2154+5720``.
    probe : (x, y)
        A point of the survey where the conversion is tried: the geoid
        undulation there must be non-zero (it is tens of metres almost everywhere).

    Raises
    ------
    CRSError
        When the CRS has no vertical datum, or when PROJ lacks the geoid grid
        (its best transformation is unavailable and the fallback leaves the
        heights unchanged). The message names the missing grid.
    """
    if not vertical_crs.is_compound and not any(a.direction == "up" for a in vertical_crs.axis_info):
        raise CRSError(
            vertical_crs.name,
            "has no vertical datum; set flightplan.vertical_crs (e.g. 'EPSG:5720') to use ellipsoidal heights",
        )
    with warnings.catch_warnings():  # the missing grid is reported below, as an error
        warnings.simplefilter("ignore", UserWarning)
        group = pyproj.transformer.TransformerGroup(vertical_crs, "EPSG:4979", always_xy=True)
    missing = sorted(
        {g.short_name or g.full_name for op in group.unavailable_operations for g in op.grids if not g.available}
    )
    if not group.transformers:
        raise CRSError(vertical_crs.name, "PROJ has no transformation to WGS84 ellipsoidal heights")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        transformer = pyproj.Transformer.from_crs(vertical_crs, "EPSG:4979", always_xy=True)
    _, _, h = transformer.transform(probe[0], probe[1], probe_height_m)
    if not math.isfinite(h) or abs(h - probe_height_m) < 1e-3:
        grids = ", ".join(missing) if missing else "the geoid model"
        raise CRSError(
            vertical_crs.name,
            f"converting its heights to the WGS84 ellipsoid needs the geoid grid ({grids}), which PROJ "
            f"does not have here (the fallback leaves heights unchanged); install it into PROJ's data "
            f"directory ({pyproj.datadir.get_data_dir()}, e.g. `projsync --file {missing[0] if missing else 'GRID'}`), "
            "or use flightplan.altitude_reference = 'takeoff' or 'amsl', which need no grid",
        )

    def convert(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        return np.asarray(transformer.transform(x, y, z)[2], dtype=float)

    return convert


def vertical_crs_for(dsm_crs_wkt: str, vertical_crs: str) -> pyproj.CRS:
    """The compound CRS of the DSM heights: its own, or its horizontal CRS plus ``vertical_crs``.

    Raises
    ------
    ConfigError
        If ``vertical_crs`` is not a vertical CRS PROJ knows.
    """
    horizontal = pyproj.CRS.from_user_input(dsm_crs_wkt)
    if not vertical_crs:
        return horizontal
    try:
        vertical = pyproj.CRS.from_user_input(vertical_crs)
    except pyproj.exceptions.CRSError as e:
        raise ConfigError(f"flightplan.vertical_crs = {vertical_crs!r} is not a CRS PROJ knows: {e}") from None
    if not vertical.is_vertical:
        raise ConfigError(f"flightplan.vertical_crs = {vertical_crs!r} is not a vertical CRS (e.g. 'EPSG:5720')")
    if horizontal.is_compound:
        horizontal = horizontal.sub_crs_list[0]
    return pyproj.CRS.from_dict(
        {
            "$schema": "https://proj.org/schemas/v0.7/projjson.schema.json",
            "type": "CompoundCRS",
            "name": f"{horizontal.name} + {vertical.name}",
            "components": [horizontal.to_json_dict(), vertical.to_json_dict()],
        }
    )


def _inverse(t: AffineLike) -> tuple[float, float, float, float, float, float]:
    det = t.a * t.e - t.b * t.d
    if det == 0:
        raise ValueError("the DSM transform is not invertible")
    ia, ib, id_, ie = t.e / det, -t.b / det, -t.d / det, t.a / det
    return ia, ib, -(ia * t.c + ib * t.f), id_, ie, -(id_ * t.c + ie * t.f)


def _window(
    shape: tuple[int, ...], t: AffineLike, start: Point2, end: Point2, reach: float
) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices of every pixel in the box around a segment grown by ``reach``."""
    inverse = _inverse(t)
    xs = [min(start[0], end[0]) - reach, max(start[0], end[0]) + reach]
    ys = [min(start[1], end[1]) - reach, max(start[1], end[1]) + reach]
    cols, rows = [], []
    for x in xs:
        for y in ys:
            cols.append(inverse[0] * x + inverse[1] * y + inverse[2])
            rows.append(inverse[3] * x + inverse[4] * y + inverse[5])
    r0, r1 = max(0, int(math.floor(min(rows)))), min(shape[0], int(math.ceil(max(rows))) + 1)
    c0, c1 = max(0, int(math.floor(min(cols)))), min(shape[1], int(math.ceil(max(cols))) + 1)
    if r0 >= r1 or c0 >= c1:
        return np.array([], dtype=int), np.array([], dtype=int)
    rr, cc = np.meshgrid(np.arange(r0, r1), np.arange(c0, c1), indexing="ij")
    return rr.ravel(), cc.ravel()


def lane_with_turns(
    lane: Lane,
    turnaround_m: float,
    dsm: Surface,
    transform: AffineLike,
    coverage: CoverageParams,
    *,
    max_gradient: float,
    slope_gain_m: float,
) -> tuple[Point2, Point2, float, float]:
    """A lane extended by ``turnaround_m`` at both ends, flown as one straight line (:func:`lane_line`):
    the turn points before and after it and the heights there (DSM datum). Raises ``ValueError``
    where no DSM lies under the lane's swath."""
    length = lane.length_m
    dx, dy = (lane.end[0] - lane.start[0]) / length, (lane.end[1] - lane.start[1]) / length
    before = (lane.start[0] - dx * turnaround_m, lane.start[1] - dy * turnaround_m)
    after = (lane.end[0] + dx * turnaround_m, lane.end[1] + dy * turnaround_m)
    first, last = lane_line(
        dsm,
        transform,
        before,
        after,
        half_width_m=coverage.swath_m / 2,
        altitude_agl_m=coverage.altitude_agl_m,
        max_gradient=max_gradient,
        slope_gain_m=slope_gain_m,
    )
    return before, after, first, last
