"""The sensor's trajectory and swath of every flight line, fitted from the survey's sums (pure).

A flight line is a ``point_source_id`` flown once: the bins of one id are cut into
passes where the swath's middle jumps (the same id flown again, or one id for the
whole survey). Per time bin the sensor's position comes from the best evidence the
bin holds (:mod:`pipeline.sensor.sums`): the rays of pulses with several returns,
else the scan angles, else the swath's middle at a flying height that the swath's
width and a nominal field of view imply (``FlightLine.method`` says which, and the
run reports an assumed height as assumed). A running median over
``SMOOTHING_BINS`` bins removes the odd bin's noise: an aircraft's path is smooth
over seconds.

The swath of a line is the ground its scanner swept: on both sides of the ground
track, out to the median half-width of its bins (the extent of each bin's points
across track, from their hull), so that a lake or a dark roof at the swath's edge,
which returns nothing, still lies inside it; each bin's own hull is added, so every
returned point lies in its line's swath.

A swath the survey's edge cuts off says nothing of the scanner's reach: where a bin's
farthest return on one side lies on the boundary of the data (the union of the tiles'
extents, within a few point spacings), that side is *cropped* and left out of the
half-widths. Without rays or scan angles the ground track itself is found from the
edges (a scanner sweeps symmetrically about it): the middle between a bin's two edges,
or one edge less the line's half-width where the other is cropped; the middle of a
cropped bin's returns lies off the track, towards the data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely

from .sums import _INDEX, BIN_SECONDS, SUPPORT_DIRECTIONS

__all__ = ["FlightLine", "fit_flight_lines", "swath_polygon"]

#: Pulse pairs a bin needs before its rays place the sensor (lidR's ``track_sensor`` asks for 50
#: pulses per bin; fewer rays at a metre or more of separation already place it within metres).
MIN_PAIRS = 30
#: Returns with a scan angle a bin needs before their regression places the sensor.
MIN_SCAN_ANGLE_POINTS = 30
#: The scan angles of a bin must spread by this much (degrees, standard deviation of the angle's
#: tangent in degrees): a scanner sweeping its field of view does; a file writing one constant does not.
MIN_SCAN_ANGLE_SPREAD_DEG = 2.0
#: Points a bin needs to count in a line's swath width.
MIN_BIN_POINTS = 20
#: Bins over which the sensor's path is smoothed (running median): 2.5 s of flight.
SMOOTHING_BINS = 5
#: A sensor this close above the mean of its bin's returns is no airborne sensor (a failed fit).
MIN_FLYING_HEIGHT_M = 10.0
#: A sample's own height more than this many median absolute deviations from the line's median
#: height is an outlier ...
OUTLIER_MADS = 5.0
#: ... and never closer than this (an aircraft's altitude wanders by metres along a line).
OUTLIER_MIN_M = 15.0
#: One id's bins are one pass while the swath's middle moves on within this share of the swath
#: width from where steady flight would take it.
PASS_BREAK_SHARE = 0.5
#: A bin's farthest return on one side within this many of its point spacings (the square root
#: of its hull's area per return) of the data's boundary marks that side as cut off by the
#: survey's edge: returns are dense enough that the edge return of a cut swath lies on the boundary.
CROPPED_SPACINGS = 3.0
#: The edges' measured angle may exceed a recorded largest angle by this much (degrees: a whole-degree
#: rank's half degree, and the spread of the edges' angle over a line's bins) before the recorded
#: one is taken for something other than the scan angle.
RECORDED_ANGLE_SLACK_DEG = 2.0
#: A whole-degree rank ``r`` records an angle in ``[r - 0.5, r + 0.5]``; the edges' measured angle refines
#: it to the nearest angle there when it lies within this much of ``r``: half a degree beyond the rank's
#: own, for the measurement's scatter (a line's edges measured 0.01-0.18 degrees below the scanner's
#: angle in simulated scans). Farther off, the swath is cropped by the survey's edge and the rank stands.
RANK_MEASURED_DEG = 1.0


@dataclass(frozen=True)
class FlightLine:
    """One pass of the sensor: its trajectory and the swath it scanned.

    Attributes
    ----------
    line : int
        The ``point_source_id`` of its returns.
    part : int
        0, or the pass number where one id was flown several times.
    times : ndarray, shape (K,)
        GPS time of each trajectory sample.
    sensor : ndarray, shape (K, 3)
        The sensor's world position (x, y, z) at each sample.
    ground_z : ndarray, shape (K,)
        Mean height of the returns of each sample's bin (the ground the swath swept, roughly).
    half_width_left, half_width_right : float
        The swath's extent on each side of the ground track (world units), across track;
        left is to the left of the direction of flight.
    hulls : ndarray, shape (K, 16, 2)
        Each bin's hull of returns (the vertices of its support polygon), world x, y.
    method : str
        ``"multiple_returns"``, ``"scan_angle"`` or ``"nominal"`` (most of the samples).
    points : int
        Returns of the line.
    max_scan_angle_deg : float
        The largest scan angle of its returns (NaN where the file has none).
    """

    line: int
    part: int
    times: np.ndarray
    sensor: np.ndarray
    ground_z: np.ndarray
    half_width_left: float
    half_width_right: float
    hulls: np.ndarray
    method: str
    points: int
    max_scan_angle_deg: float

    @property
    def heading(self) -> np.ndarray:
        """Unit (dx, dy) of flight, from the first sample to the last."""
        d = self.sensor[-1, :2] - self.sensor[0, :2]
        return d / max(float(np.hypot(*d)), 1e-9)

    @property
    def azimuth_deg(self) -> float:
        """Direction of flight, degrees clockwise from north."""
        dx, dy = self.heading
        return math.degrees(math.atan2(dx, dy)) % 360.0

    @property
    def flying_height(self) -> float:
        """Median height of the sensor above the returns of its bins."""
        return float(np.median(self.sensor[:, 2] - self.ground_z))


def fit_flight_lines(
    lines: np.ndarray,
    bins: np.ndarray,
    values: np.ndarray,
    *,
    origin: tuple[float, float, float],
    nominal_fov_deg: float,
    extent: shapely.Geometry | None = None,
    bin_seconds: float = BIN_SECONDS,
) -> list[FlightLine]:
    """Every flight line's trajectory and swath from the merged sums (:func:`pipeline.sensor.sums.merge_sums`).

    ``nominal_fov_deg`` is the scanner's full field of view assumed where a bin has neither
    pulses with several returns nor scan angles. ``extent`` is where the survey holds data
    (world units; the union of the tiles' extents): a swath side reaching its boundary is
    cropped (module docstring); None: no side is. Lines with fewer than two usable bins are
    left out (a handful of stray returns has no direction).

    A line whose every bin is cropped on one side or the other has no half-width of its own;
    it takes the median of the other assumed-height lines' (one scanner, one flying height
    over a survey block), else its uncropped side's.
    """
    boundary = None if extent is None or extent.is_empty else shapely.boundary(extent)
    passes = []
    for line in np.unique(lines):
        rows = np.flatnonzero(lines == line)
        rows = rows[values[rows, _INDEX["n"]] >= 1]
        rows = rows[np.argsort(bins[rows], kind="stable")]
        for part, pass_rows in enumerate(_passes(bins[rows], values[rows], bin_seconds, origin)):
            passes.append((int(line), part, bins[rows][pass_rows], values[rows][pass_rows]))
    settings = (origin, nominal_fov_deg, boundary, bin_seconds)
    fitted = [_fit_pass(line, part, b, v, *settings) for line, part, b, v in passes]
    known = [f.half_width for f in fitted if f is not None and f.line.method == "nominal" and f.half_width is not None]
    fallback = float(np.median(known)) if known else None
    out: list[FlightLine] = []
    for (line, part, b, v), fit in zip(passes, fitted, strict=True):
        if fit is not None and fit.line.method == "nominal" and fit.half_width is None and fallback is not None:
            fit = _fit_pass(line, part, b, v, *settings, half_width=fallback)
        if fit is not None:
            out.append(fit.line)
    return out


@dataclass(frozen=True)
class _Fit:
    line: FlightLine
    half_width: float | None  # the line's own half-width across both edges (None: every bin cropped on a side)


def _centroids(values: np.ndarray, origin: tuple[float, float, float]) -> np.ndarray:
    n = values[:, _INDEX["n"]]
    return np.stack(
        [values[:, _INDEX[c]] / n + o for c, o in (("sx", origin[0]), ("sy", origin[1]), ("sz", origin[2]))], axis=1
    )


def _passes(bins: np.ndarray, values: np.ndarray, bin_seconds: float, origin) -> list[np.ndarray]:
    """The rows of one id cut where the swath's middle leaves the course of steady flight."""
    if len(bins) < 2:
        return [np.arange(len(bins))]
    middle = _centroids(values, origin)[:, :2]
    width = _hull_widths(values, origin)
    steps = np.diff(middle, axis=0)
    dt = np.diff(bins).astype(np.float64) * bin_seconds
    adjacent = dt <= 2 * bin_seconds
    speed = np.hypot(*steps[adjacent].T) / dt[adjacent] if adjacent.any() else np.array([])
    breaks = []
    for i in range(len(steps)):
        if adjacent[i]:
            continue
        before = slice(max(0, i - 4), i + 1)
        direction = middle[i] - middle[before][0]
        norm = float(np.hypot(*direction))
        v = float(np.median(speed)) if len(speed) else 0.0
        predicted = middle[i] + (direction / norm * v * dt[i] if norm > 0 else 0.0)
        if np.hypot(*(middle[i + 1] - predicted)) > PASS_BREAK_SHARE * max(float(np.median(width)), 1.0):
            breaks.append(i + 1)
    return np.split(np.arange(len(bins)), breaks)


def _hull_vertices(values: np.ndarray, origin) -> np.ndarray:
    """Each row's hull: the points that reach the support function's maxima, in angular order (world x, y).

    They are returns, so the polygon lies inside the returns' convex hull (never beyond it), and
    around a scan line's end, straight across the track, it reaches the end exactly.
    """
    x = values[:, _INDEX["x0"] : _INDEX["x0"] + SUPPORT_DIRECTIONS] + origin[0]
    y = values[:, _INDEX["y0"] : _INDEX["y0"] + SUPPORT_DIRECTIONS] + origin[1]
    return np.stack([x, y], axis=2)


def _hull_widths(values: np.ndarray, origin) -> np.ndarray:
    """The largest extent of each row's hull (its diameter across the 16 directions)."""
    h = values[:, _INDEX["h0"] : _INDEX["h0"] + SUPPORT_DIRECTIONS]
    half = SUPPORT_DIRECTIONS // 2
    return np.max(h[:, :half] + h[:, half:], axis=1)


def _fit_pass(
    line: int,
    part: int,
    bins: np.ndarray,
    values: np.ndarray,
    origin: tuple[float, float, float],
    nominal_fov_deg: float,
    boundary: shapely.Geometry | None,
    bin_seconds: float,
    half_width: float | None = None,
) -> _Fit | None:
    enough = values[:, _INDEX["n"]] >= MIN_BIN_POINTS
    if enough.sum() < 2:
        return None
    bins, values = bins[enough], values[enough]
    times, sensor, methods = _positions(bins, values, origin, bin_seconds)
    order = np.argsort(times, kind="stable")
    times, sensor, methods, values = times[order], sensor[order], methods[order], values[order]
    middle = _centroids(values, origin)
    hulls = _hull_vertices(values, origin)
    evidence = _consistent(sensor)
    methods[~evidence] = 0
    if evidence.sum() >= 2:
        track = _along_time(times, times[evidence], sensor[evidence, :2])
    else:
        track = _along_time(times, times, middle[:, :2])
    heading = _heading(track)
    left = np.array([-heading[1], heading[0]])
    across = np.einsum("kvd,d->kv", hulls - track[:, None, :], left)
    along = np.einsum("kvd,d->kv", hulls - track[:, None, :], heading)
    cropped = _cropped_sides(values, hulls, across, along, boundary)
    own_half_width, bin_widths = None, None
    if evidence.sum() < 2:
        track, own_half_width, bin_widths = _track_from_edges(
            times, track, left, across, _edge_heights(values, across), cropped,
            ground_z=middle[:, 2], tan_nominal=math.tan(math.radians(nominal_fov_deg) / 2.0), half_width=half_width,
        )  # fmt: skip
        across = np.einsum("kvd,d->kv", hulls - track[:, None, :], left)
    half_left = _side_median(across.max(axis=1), cropped[:, 0])
    half_right = _side_median(-across.min(axis=1), cropped[:, 1])
    width = own_half_width if half_width is None else half_width
    if evidence.sum() < 2 and width is not None and cropped.all():
        half_left = half_right = width
    # a side the survey's edge cuts everywhere reaches as far as the other (a symmetric scanner)
    if cropped[:, 0].all() and not cropped[:, 1].all():
        half_left = half_right
    elif cropped[:, 1].all() and not cropped[:, 0].all():
        half_right = half_left
    if evidence.sum() >= 2:
        height = np.interp(times, times[evidence], sensor[evidence, 2])
    else:
        tan_half = math.tan(math.radians(nominal_fov_deg) / 2.0)
        if bin_widths is None:
            bin_widths = np.full(len(times), (max(half_left, 0.0) + max(half_right, 0.0)) / 2.0)
        height = middle[:, 2] + bin_widths / tan_half
    sensor = _running_median(np.column_stack([track, np.where(evidence, sensor[:, 2], height)]), SMOOTHING_BINS)
    recorded = _recorded_max_angle(values)
    measured = _edge_angle(values, across, sensor, cropped)
    method = ("nominal", "scan_angle", "multiple_returns")[int(np.bincount(methods, minlength=3).argmax())]
    flight_line = FlightLine(
        line=line,
        part=part,
        times=times,
        sensor=sensor,
        ground_z=middle[:, 2],
        half_width_left=max(half_left, 0.0),
        half_width_right=max(half_right, 0.0),
        hulls=hulls,
        method=method,
        points=int(values[:, _INDEX["n"]].sum()),
        max_scan_angle_deg=_largest_angle(recorded, measured),
    )
    return _Fit(flight_line, own_half_width)


def _positions(
    bins: np.ndarray, values: np.ndarray, origin: tuple[float, float, float], bin_seconds: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per bin: its time, the sensor's position where the bin's rays or scan angles place it (NaN
    where neither does) and the evidence used (0 none, 1 scan angles, 2 pulses with several returns)."""
    middle = _centroids(values, origin)
    sensor = np.full((len(bins), 3), np.nan)
    times = bins * bin_seconds + values[:, _INDEX["st"]] / values[:, _INDEX["n"]]
    methods = np.zeros(len(bins), np.int8)
    for i, row in enumerate(values):
        position = _from_pulse_pairs(row, origin)
        if position is not None and position[2] - middle[i, 2] >= MIN_FLYING_HEIGHT_M:
            sensor[i], methods[i] = position, 2
            times[i] = bins[i] * bin_seconds + row[_INDEX["pair_t"]] / row[_INDEX["pair_w"]]
            continue
        position = _from_scan_angles(row, origin)
        if position is not None and position[2] - middle[i, 2] >= MIN_FLYING_HEIGHT_M:
            sensor[i], methods[i] = position, 1
            times[i] = bins[i] * bin_seconds + row[_INDEX["sa_t"]] / row[_INDEX["sa_n"]]
    return times, sensor, methods


def _cropped_sides(
    values: np.ndarray, hulls: np.ndarray, across: np.ndarray, along: np.ndarray, boundary: shapely.Geometry | None
) -> np.ndarray:
    """Per bin, whether its left and right sides (columns 0, 1) are cut off by the survey's edge.

    A side is cut where a vertex of the bin's hull at its outer end lies on the data's boundary
    (within ``CROPPED_SPACINGS`` point spacings): the farthest vertex across the track, or one
    within the bin's length along the track of it. A boundary crossing the swath at a slant cuts
    the side along a line that drifts across the track by up to the bin's length; its farthest
    point across lies off the boundary (2 m, six spacings, in a simulated Delft scan) while the
    cut's own vertices lie on it.
    """
    out = np.zeros((len(values), 2), bool)
    if boundary is None:
        return out
    local = hulls - hulls.mean(axis=1, keepdims=True)
    x, y = local[..., 0], local[..., 1]
    area = 0.5 * np.abs(np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1))  # shoelace
    spacing = np.sqrt(np.maximum(area, 0.0) / np.maximum(values[:, _INDEX["n"]], 1.0))
    on_boundary = shapely.distance(shapely.points(hulls), boundary) <= CROPPED_SPACINGS * spacing[:, None]
    length = (along.max(axis=1) - along.min(axis=1))[:, None]
    for column, side in enumerate((across, -across)):
        outer = side >= side.max(axis=1, keepdims=True) - length
        out[:, column] = (on_boundary & outer).any(axis=1)
    return out


def _edge_heights(values: np.ndarray, across: np.ndarray) -> np.ndarray:
    """Per bin, the heights of the returns farthest left and right across the track (K, 2)."""
    heights = values[:, _INDEX["e0"] : _INDEX["e0"] + SUPPORT_DIRECTIONS]
    rows = np.arange(len(values))
    return np.column_stack([heights[rows, across.argmax(axis=1)], heights[rows, across.argmin(axis=1)]])


def _side_median(extents: np.ndarray, cropped: np.ndarray) -> float:
    """The median of a side's extents over the bins the survey's edge does not cut (all bins where it cuts every one)."""
    return float(np.median(extents[~cropped] if (~cropped).any() else extents))


def _track_from_edges(
    times: np.ndarray,
    track: np.ndarray,
    left: np.ndarray,
    across: np.ndarray,
    edge_z: np.ndarray,
    cropped: np.ndarray,
    *,
    ground_z: np.ndarray,
    tan_nominal: float,
    half_width: float | None,
) -> tuple[np.ndarray, float | None, np.ndarray | None]:
    """The ground track of a line without rays or scan angles, from its swath's edges.

    A scanner sweeps symmetrically about its track: its outermost pulses leave at the same
    angle on both sides, so an edge return ``d`` across and ``z`` high satisfies
    ``d = (H - z) tan(a)``. The sensor's height ``H`` is each bin's ground plus its half-width
    over ``tan_nominal``; ``tan(a)`` the median over bins with both edges of
    ``(L + R) / ((H - z_L) + (H - z_R))``, which no offset of the track changes. Where both
    edges of a bin stand, the track lies where the two angles agree; where one is cropped,
    ``(H - z) tan(a)`` in from the other. ``track`` is the returns' middle per bin, ``across``
    the hull's vertices' distances left of it and ``edge_z`` (K, 2) the heights of each bin's
    left and right edge returns. ``half_width`` replaces the line's own (the median of
    ``(L + R) / 2`` over its whole bins) where given. Bins with no edge of their own take the
    positions of the others, interpolated in time (a straight line beyond them). Returns the
    track, the line's own half-width (None where no bin has both edges) and each bin's
    half-width (its own where both edges stand, else interpolated; None where unknown).
    """
    left_edge, right_edge = across.max(axis=1), -across.min(axis=1)
    whole = ~cropped[:, 0] & ~cropped[:, 1]
    halves = (left_edge + right_edge) / 2.0
    own = float(np.median(halves[whole])) if whole.any() else None
    if whole.any():  # each bin's own, interpolated in time where an edge is cut (an aircraft climbs, turns)
        widths = np.interp(times, times[whole], halves[whole])
    elif half_width is not None:
        widths = np.full(len(times), half_width)
    else:
        return track, own, None
    height = ground_z + widths / tan_nominal
    rise_left = np.maximum(height - edge_z[:, 0], MIN_FLYING_HEIGHT_M)
    rise_right = np.maximum(height - edge_z[:, 1], MIN_FLYING_HEIGHT_M)
    if whole.any():
        tan_edge = float(np.median(((left_edge + right_edge) / (rise_left + rise_right))[whole]))
    else:
        tan_edge = tan_nominal
    shift = np.full(len(times), np.nan)
    shift[whole] = ((left_edge * rise_right - right_edge * rise_left) / (rise_left + rise_right))[whole]
    only_left = ~cropped[:, 0] & cropped[:, 1]
    only_right = cropped[:, 0] & ~cropped[:, 1]
    shift[only_left] = (left_edge - rise_left * tan_edge)[only_left]
    shift[only_right] = (rise_right * tan_edge - right_edge)[only_right]
    known = np.isfinite(shift)
    if not known.any():
        return track, own, widths
    placed = track[known] + shift[known, None] * left
    return _along_time(times, times[known], placed), own, widths


def _recorded_max_angle(values: np.ndarray) -> float:
    """The largest scan angle the returns record (NaN where none, or where every angle is 0)."""
    angles = values[:, _INDEX["sa_max"]]
    if not np.isfinite(angles).any() or float(angles.max()) <= 0.0:
        return math.nan
    return float(angles.max())


def _edge_angle(values: np.ndarray, across: np.ndarray, sensor: np.ndarray, cropped: np.ndarray) -> float:
    """The scanner's largest angle measured on the swath's edges: the mean of the two sides' medians over bins.

    For each bin, the hull's point farthest across track on each side (a return), its distance
    from the track and its height; the angle from the vertical at the sensor. Sides the survey's
    edge crops (``cropped``, per bin left and right) are left out (every side is used where the
    edge crops them all), and so are sides whose farthest return lies across the track; a side
    without a bin of its own gives way to the other.
    The mean of the sides cancels an offset of the track; a median of each bin's wider side
    would not (it measured a 21.1 degree scanner 1 degree wide).
    """
    edge_z = _edge_heights(values, across)
    distances = np.column_stack([across.max(axis=1), -across.min(axis=1)])
    use = ~cropped if (~cropped).any() else np.ones_like(cropped)
    sides = []
    for column in range(2):
        rise = sensor[:, 2] - edge_z[:, column]
        # a side whose farthest return lies across the track holds no return of its own: cut off
        # (a line entering the survey at a slant: -48 m in a simulated scan, which made 19.5 degrees 3.9)
        valid = use[:, column] & (rise > 0) & (distances[:, column] > 0)
        angles = np.degrees(np.arctan2(distances[valid, column], rise[valid]))
        sides.append(float(np.median(angles)) if len(angles) else math.nan)
    known = [a for a in sides if math.isfinite(a)]
    return float(np.mean(known)) if known else math.nan


def _largest_angle(recorded: float, measured: float) -> float:
    """The line's largest scan angle: as recorded, to the precision it is recorded with.

    LAS 1.0-1.3 record whole degrees (a rank): the true largest angle lies within half a degree
    of the largest rank, at the nearest angle there to the edge's geometry when that lies within
    ``RANK_MEASURED_DEG`` of the rank (a swath cropped by the survey's edge measures low: the rank
    then stands). Without recorded angles, the edge's
    geometry alone; NaN where neither is known.

    A recorded angle that the line's own returns exceed by more than ``RECORDED_ANGLE_SLACK_DEG``
    is not the scanner's: its swath would leave out the returns it scanned. Seen in an IGN LiDAR
    HD extract (`ign_lidarprod_870000_6618000`: five values 0-4.0 degrees, none negative, over a
    swath 110 m wide), where it made every cut void beyond 10 m of the track a coverage gap.
    The edges' angle is taken instead.
    """
    if math.isnan(recorded):
        return measured
    if not math.isnan(measured) and measured > recorded + RECORDED_ANGLE_SLACK_DEG:
        return measured  # the returns lie beyond the recorded angle: the field holds something else
    if float(recorded).is_integer() and not math.isnan(measured) and abs(measured - recorded) <= RANK_MEASURED_DEG:
        # the nearest angle the rank allows: a scanner of 22.59 degrees records rank 23, and its
        # edges measured 22.42 degrees in a simulated forest scan (the rank alone put its swath's
        # edge 1.3 m too far out at 155 m above the canopy)
        return min(max(measured, recorded - 0.5), recorded + 0.5)
    return recorded  # a measurement the rank contradicts (a swath cropped by the survey's edge) is no refinement


def _consistent(sensor: np.ndarray) -> np.ndarray:
    """The samples with a position of their own whose height agrees with the line's others.

    An aircraft holds its altitude within metres over a line; a bin at the swath's end
    with a few skewed rays can put the sensor hundreds of metres off. Kept: within
    ``OUTLIER_MADS`` median absolute deviations of the median height (at least ``OUTLIER_MIN_M``).
    """
    known = ~np.isnan(sensor[:, 2])
    if known.sum() < 3:
        return known
    z = sensor[known, 2]
    median = float(np.median(z))
    spread = max(OUTLIER_MADS * float(np.median(np.abs(z - median))), OUTLIER_MIN_M)
    return known & (np.abs(np.nan_to_num(sensor[:, 2], nan=np.inf) - median) <= spread)


def _along_time(times: np.ndarray, known_times: np.ndarray, known_xy: np.ndarray) -> np.ndarray:
    """Positions at ``times``: interpolated between known samples, a straight line fitted to them beyond."""
    out = np.column_stack([np.interp(times, known_times, known_xy[:, d]) for d in range(2)])
    outside = (times < known_times[0]) | (times > known_times[-1])
    if outside.any():
        design = np.column_stack([np.ones_like(known_times), known_times - known_times[0]])
        coefficients = np.linalg.lstsq(design, known_xy, rcond=None)[0]
        fitted = np.column_stack([np.ones_like(times), times - known_times[0]]) @ coefficients
        out[outside] = fitted[outside]
    return out


def _heading(track: np.ndarray) -> np.ndarray:
    """Unit direction of the principal axis of the track, pointing from its first sample to its last."""
    centred = track - track.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    d = vt[0]
    if np.dot(track[-1] - track[0], d) < 0:
        d = -d
    return d / np.hypot(*d)


def _from_pulse_pairs(row: np.ndarray, origin) -> np.ndarray | None:
    """The point nearest to a bin's rays in least squares (Roussel et al. 2020), or None."""
    if row[_INDEX["pair_n"]] < MIN_PAIRS:
        return None
    a = np.array(
        [
            [row[_INDEX["a_xx"]], row[_INDEX["a_xy"]], row[_INDEX["a_xz"]]],
            [row[_INDEX["a_xy"]], row[_INDEX["a_yy"]], row[_INDEX["a_yz"]]],
            [row[_INDEX["a_xz"]], row[_INDEX["a_yz"]], row[_INDEX["a_zz"]]],
        ]
    )
    eig = np.linalg.eigvalsh(a)
    if eig[0] <= 1e-4 * eig[-1]:  # the rays are (nearly) parallel: no crossing point
        return None
    b = np.array([row[_INDEX["b_x"]], row[_INDEX["b_y"]], row[_INDEX["b_z"]]])
    return np.linalg.solve(a, b) + np.asarray(origin)


def _from_scan_angles(row: np.ndarray, origin) -> np.ndarray | None:
    """Ground track and height from the regression of x, y on tan(scan angle), or None.

    A return at angle ``a`` lies at ``s + c (z_s - z) tan a`` (``c`` the unit vector across
    track): in the basis ``1, k, k (z - mean z)`` with ``k = tan a`` the coefficient of ``k``
    is ``c (z_s - mean z)``, well defined even on flat ground where the third column vanishes.
    """
    n = row[_INDEX["sa_n"]]
    if n < MIN_SCAN_ANGLE_POINTS:
        return None
    mk = row[_INDEX["sa_k"]] / n
    if row[_INDEX["sa_kk"]] / n - mk * mk < math.tan(math.radians(MIN_SCAN_ANGLE_SPREAD_DEG)) ** 2:
        return None
    g = np.array(
        [
            [n, row[_INDEX["sa_k"]], row[_INDEX["sa_zk"]]],
            [row[_INDEX["sa_k"]], row[_INDEX["sa_kk"]], row[_INDEX["sa_zkk"]]],
            [row[_INDEX["sa_zk"]], row[_INDEX["sa_zkk"]], row[_INDEX["sa_zzkk"]]],
        ]
    )
    mz = row[_INDEX["sa_z"]] / n
    t = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -mz, 1.0]])  # to the basis 1, k, k (z - mean z)
    g_c = t @ g @ t.T
    coefficients = []
    for c in ("x", "y"):
        rhs = t @ np.array([row[_INDEX[f"sa_{c}"]], row[_INDEX[f"sa_{c}k"]], row[_INDEX[f"sa_{c}zk"]]])
        coefficients.append(np.linalg.lstsq(g_c, rhs, rcond=1e-9)[0])
    (x0, kx, _), (y0, ky, _) = coefficients
    height = math.hypot(kx, ky)
    return np.array([x0 + origin[0], y0 + origin[1], mz + origin[2] + height])


def _running_median(samples: np.ndarray, width: int) -> np.ndarray:
    """Running median of each column over ``width`` samples (shorter at the ends)."""
    if len(samples) < 3:
        return samples
    half = width // 2
    out = np.empty_like(samples)
    for i in range(len(samples)):
        out[i] = np.median(samples[max(0, i - half) : i + half + 1], axis=0)
    return out


def swath_polygon(line: FlightLine) -> shapely.Geometry:
    """The ground the line's scanner swept (world x, y): the track's strip out to the swath's half-widths, and every bin's hull.

    The strip's ends reach one and a half samples' spacing beyond the first and last sample:
    a sample is the middle of its bin (half a spacing to the bin's last scan line), and a line
    cut by the survey's edge flew on past its last return there (lakes and dark roofs at the
    edge return nothing: a simulated lake on a scene's edge fell between the last bin and the
    edge, 8-9 m, and read as missed coverage).
    """
    track = line.sensor[:, :2]
    heading = line.heading
    left = np.array([-heading[1], heading[0]])
    if len(track) > 1:
        step = 1.5 * float(np.median(np.hypot(*np.diff(track, axis=0).T)))
    else:
        step = 0.0
    start, end = track[0] - heading * step, track[-1] + heading * step
    path = np.vstack([start, track, end])
    lefts = path + left * line.half_width_left
    rights = path - left * line.half_width_right
    # every quad and hull made in one call each (a line has hundreds of bins)
    quads = shapely.buffer(shapely.polygons(np.stack([lefts[:-1], lefts[1:], rights[1:], rights[:-1]], axis=1)), 0)
    hulls = shapely.buffer(shapely.polygons(np.asarray(line.hulls, np.float64).reshape(-1, SUPPORT_DIRECTIONS, 2)), 0)
    parts = np.concatenate([quads, hulls])
    return shapely.union_all(parts[~shapely.is_empty(parts)])
