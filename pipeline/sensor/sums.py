"""Mergeable sums, per flight line and time bin, from which the sensor's trajectory is fitted (pure).

Stage 1 sees every point once. For each (``point_source_id``, ``floor(gps_time /
bin_seconds)``) it adds to one row of sums; rows of the same key from different tiles
or chunks add up exactly (maxima take the maximum), so the trajectory fitted from them
(:mod:`pipeline.sensor.trajectory`) does not depend on how the survey is cut. Three
kinds of evidence, each used where the data has it:

- **Pulses with several returns** (Gatziolis and McGaughey 2019; Roussel et al. 2020,
  lidR's ``track_sensor``): the first and the last return of one pulse lie on the
  laser's ray, so the line through them passes through the sensor. The point closest
  to all the rays of a time bin, in least squares, is the sensor's position: it solves
  ``A s = b`` with ``A = sum w (I - u u^T)`` and ``b = sum w (I - u u^T) p``, sums that
  add across tiles. A ray's angular error is the ranging noise over the returns'
  separation, so the weight is the squared separation (capped), and pairs closer than
  ``MIN_PAIR_SEPARATION_M`` are not used.
- **Scan angles**: a return at scan angle ``a`` lies ``(z_s - z) tan a`` across track
  from the sensor's ground track. The regression of the returns' x and y on
  ``tan a`` (and ``z tan a``) per bin gives the ground track and the flying height.
- **The swath itself**: the points' centroid and their convex hull, kept as the
  support function in ``SUPPORT_DIRECTIONS`` directions (a maximum per direction,
  mergeable): where nothing else is known, the ground track is the swath's middle,
  and the hull tells how wide the swath is.

Coordinates are relative to a survey origin (``origin``) so that the sums keep their
precision in float64.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

__all__ = [
    "BIN_SECONDS",
    "COLUMNS",
    "SUPPORT_DIRECTIONS",
    "TrajectorySums",
    "empty_sums",
    "merge_sums",
    "trajectory_sums",
]

#: Length of a time bin. An aircraft at 50-70 m/s flies 25-35 m in it: a short piece of a
#: straight line, holding thousands of pulses at today's rates (lidR's default is 0.5 s too).
BIN_SECONDS = 0.5
#: Directions of the support function of each bin's points (every 22.5 degrees).
SUPPORT_DIRECTIONS = 16
#: Returns of one pulse closer than this give no usable direction: a few centimetres of
#: ranging noise over a metre is already a degree of error (Gatziolis and McGaughey 2019).
MIN_PAIR_SEPARATION_M = 1.0
#: Separations above this count no more (a misplaced return far down the ray must not dominate).
MAX_PAIR_WEIGHT_SEPARATION_M = 30.0
#: A ray more than this far from the vertical is no laser ray of an airborne scanner.
MAX_RAY_ZENITH_DEG = 75.0

_SCALARS = (
    "n", "sx", "sy", "sz", "st",  # points: count, coordinate sums, time (from the bin's start) sum
    "pair_n", "pair_w", "pair_t",  # pulse pairs: count, weight sum, weighted time sum
    "a_xx", "a_xy", "a_xz", "a_yy", "a_yz", "a_zz", "b_x", "b_y", "b_z",  # sum w (I - uu^T), sum w (I - uu^T) p
    "sa_n", "sa_k", "sa_kk", "sa_z", "sa_zk", "sa_zkk", "sa_zzkk",  # scan angles: k = tan(angle)
    "sa_x", "sa_xk", "sa_xzk", "sa_y", "sa_yk", "sa_yzk", "sa_t",
    "sa_max",  # largest |scan angle| in degrees (merged by maximum)
)  # fmt: skip
#: Column names of a sums row: the scalars, then ``h0..h15``, the support function (maximum of
#: ``x cos(phi) + y sin(phi)``, merged by maximum), then ``x0..x15``, ``y0..y15`` and ``e0..e15``,
#: the point that reaches each maximum (merged with it): the swath's edge and the surface it lies on.
#: ``x cos(phi) + y sin(phi)``, ``phi = k * 22.5`` degrees), merged by maximum.
COLUMNS = _SCALARS + tuple(f"{c}{k}" for c in ("h", "x", "y", "e") for k in range(SUPPORT_DIRECTIONS))
#: The columns carried with each direction's maximum.
_CARRIED = ("x", "y", "e")
_MAX_COLUMNS = ("sa_max",) + tuple(f"h{k}" for k in range(SUPPORT_DIRECTIONS))
_INDEX = {name: i for i, name in enumerate(COLUMNS)}
_N_COLUMNS = len(COLUMNS)
_MAX_MASK = np.array([name in _MAX_COLUMNS for name in COLUMNS])


#: tan(scan angle) looked up in the LAS 1.4 angle steps (0.006 degrees; a whole-degree rank falls within
#: 0.003 degrees of a step): a table lookup instead of a tangent per point.
_STEPS_PER_DEGREE = 1.0 / 0.006
_TAN_OFFSET = 15_000  # 90 degrees
_TANGENTS = np.tan(np.radians((np.arange(2 * _TAN_OFFSET + 1) - _TAN_OFFSET) / _STEPS_PER_DEGREE))


def empty_sums() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(lines, bins, values)`` with no row: line ids (int64), bin indices (int64), sums (float64, N x columns)."""
    return np.empty(0, np.int64), np.empty(0, np.int64), np.empty((0, _N_COLUMNS), np.float64)


def trajectory_sums(
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    line: np.ndarray,
    gps_time: np.ndarray,
    return_number: np.ndarray,
    number_of_returns: np.ndarray,
    scan_angle_deg: np.ndarray,
    keep: np.ndarray,
    *,
    origin: tuple[float, float, float],
    bin_seconds: float = BIN_SECONDS,
    scales: tuple[float, float, float] = (1.0, 1.0, 1.0),
    offsets: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sums of one chunk of points, one row per (line, time bin) present.

    The Python face of the numba kernel :func:`_accumulate`: it finds each point's row
    and forwards the point columns, one array each (numba takes no records), so it is
    exempt from the ten-parameter rule.

    Parameters
    ----------
    x, y, z : ndarray
        Coordinates: float64 world coordinates, or a LAS record's integers with their
        ``scales`` and ``offsets`` (the kernel scales them itself, as the rasterizer does).
    line : ndarray of int
        ``point_source_id``.
    gps_time, return_number, number_of_returns, scan_angle_deg : ndarray
        :class:`pipeline.io.las.PulseFields`; points whose time is 0 (virtual or synthetic
        points, formats without time) are left out.
    keep : ndarray of bool
        The points that count (noise and withheld points are left out).
    origin : (float, float, float)
        Subtracted from the coordinates before summing.

    Returns
    -------
    lines, bins, values : ndarray
        Line id and bin index per row, sorted by (bin, line), and the sums (columns ``COLUMNS``).
    """
    slots, keys = _slots(line, gps_time, keep, bin_seconds)
    if len(keys) == 0:
        return empty_sums()
    values = np.zeros((len(keys), _N_COLUMNS), np.float64)
    values[:, _MAX_MASK] = -np.inf
    scales_, shifts = np.array(scales, np.float64), np.array(offsets, np.float64) - np.array(origin, np.float64)
    apart = _accumulate(
        values, slots, x, y, z, gps_time, bin_seconds, return_number, number_of_returns, scan_angle_deg, line,
        scales_, shifts, _TANGENTS,
    )  # fmt: skip
    if apart:
        min_up = math.cos(math.radians(MAX_RAY_ZENITH_DEG))
        _pair_by_time(
            values, slots, x, y, z, gps_time, return_number, number_of_returns, line, scales_, shifts,
            1.0 / bin_seconds, bin_seconds, min_up,
        )  # fmt: skip
    order = np.argsort(keys, kind="stable")
    keys = keys[order]
    return keys % 65536, keys // 65536, values[order]


@numba.njit(cache=True, nogil=True, inline="always")
def _floor(value):
    """floor() as an int64 (an adjusted GPS time before 2011 is negative), without libm's call."""
    whole = np.int64(value)
    return whole - 1 if value < whole else whole


@numba.njit(cache=True, nogil=True)
def _slots(line, gps_time, keep, bin_seconds):
    """A row per (bin, line) present and each point's row (-1: not used), in one pass.

    Points of a line come in time order in most files, so the key changes rarely; on a
    change the few keys seen so far are searched, newest first.
    """
    n = len(line)
    per_bin = 1.0 / bin_seconds
    slots = np.empty(n, np.int64)
    keys = np.empty(n, np.int64)  # room for every point's own key: never grown (a growing array slows the loop 4x)
    count = 0
    last_key = np.int64(-1)
    last_slot = -1
    for i in range(n):
        t = gps_time[i]
        if not keep[i] or t == 0.0:
            slots[i] = -1
            continue
        key = _floor(t * per_bin) * 65536 + np.int64(line[i])
        if key != last_key:
            last_slot = -1
            for j in range(count - 1, -1, -1):
                if keys[j] == key:
                    last_slot = j
                    break
            if last_slot < 0:
                keys[count] = key
                last_slot = count
                count += 1
            last_key = key
        slots[i] = last_slot
    return slots, keys[:count].copy()


@numba.njit(cache=True, nogil=True)
def _accumulate(
    values, slots, xs, ys, zs, gps_time, bin_seconds, return_number, number_of_returns, angles, line, scales, shifts,
    tangents,
):  # fmt: skip
    n = len(slots)
    per_bin = 1.0 / bin_seconds
    cos_k = np.empty(16)
    sin_k = np.empty(16)
    for k in range(16):
        cos_k[k] = math.cos(k * math.pi / 8.0)
        sin_k[k] = math.sin(k * math.pi / 8.0)
    min_up = math.cos(math.radians(75.0))
    firsts = np.empty(n, np.int64)  # first returns of pulses with several, in point order
    count = 0
    for i in range(n):
        s = slots[i]
        if s < 0:
            continue
        t = gps_time[i]
        row = values[s]
        xi = xs[i] * scales[0] + shifts[0]
        yi = ys[i] * scales[1] + shifts[1]
        zi = zs[i] * scales[2] + shifts[2]
        tb = t * per_bin
        ti = (tb - _floor(tb)) * bin_seconds
        row[0] += 1.0
        row[1] += xi
        row[2] += yi
        row[3] += zi
        row[4] += ti
        a = np.float64(angles[i])
        if a == a and abs(a) < 89.0:  # not NaN
            k = tangents[int(round(a * _STEPS_PER_DEGREE)) + _TAN_OFFSET]
            row[17] += 1.0
            row[18] += k
            row[19] += k * k
            row[20] += zi
            row[21] += zi * k
            row[22] += zi * k * k
            row[23] += zi * zi * k * k
            row[24] += xi
            row[25] += xi * k
            row[26] += xi * zi * k
            row[27] += yi
            row[28] += yi * k
            row[29] += yi * zi * k
            row[30] += ti
            if abs(a) > row[31]:
                row[31] = abs(a)
        for d in range(8):  # directions d and d + 8 are opposite: one product serves both
            h = xi * cos_k[d] + yi * sin_k[d]
            if h > row[32 + d]:
                row[32 + d] = h
                row[48 + d] = xi
                row[64 + d] = yi
                row[80 + d] = zi
            if -h > row[40 + d]:
                row[40 + d] = -h
                row[56 + d] = xi
                row[72 + d] = yi
                row[88 + d] = zi
        if return_number[i] == 1 and number_of_returns[i] > 1:
            firsts[count] = i
            count += 1
    # the first return of a pulse with several: its last return is the one stored last (loops of
    # their own: in the loop above, their body slowed every point by 4 ns)
    lasts = np.full(count, -1, np.int64)
    adjacent = 0
    for f in range(count):
        i = firsts[f]
        m = number_of_returns[i]
        j = i + m - 1
        if j < n and slots[j] == slots[i] and gps_time[j] == gps_time[i] and return_number[j] == m:
            if line[j] == line[i]:
                lasts[f] = j
                adjacent += 1
    if 2 * adjacent < count:
        return True  # stored apart: the caller pairs them by time (:func:`_pair_by_time`)
    for f in range(count):
        if lasts[f] >= 0:
            i, j = firsts[f], lasts[f]
            _add_pair(values[slots[i]], i, j, xs, ys, zs, gps_time, scales, shifts, per_bin, bin_seconds, min_up)
    return False


@numba.njit(cache=True, nogil=True)
def _pair_by_time(
    values, slots, xs, ys, zs, gps_time, return_number, number_of_returns, line, scales, shifts, per_bin, bin_seconds,
    min_up,
):  # fmt: skip
    """The pairs of a chunk whose pulses' returns are not stored one after the other, found by their time.

    A file sorted in space (IGN's ``ign_bat``: 15 of 20,915 pulses' returns adjacent) or read by
    octree node (COPC) keeps a pulse's returns apart. Its first and last returns share the
    pulse's GPS time and line: sorted by (time, line), they meet. The pairs are added in the
    order of their first returns, as the adjacent ones are, so the sums do not depend on the sort.
    Used for a chunk where fewer than half of the first returns have their last beside them (a
    file in acquisition order: 92-99 %), which keeps the sort off the common path.
    """
    n = len(slots)
    ends = np.empty(n, np.int64)  # first and last returns of pulses with several
    count = 0
    for i in range(n):
        m = number_of_returns[i]
        if slots[i] >= 0 and m > 1 and (return_number[i] == 1 or return_number[i] == m):
            ends[count] = i
            count += 1
    ends = ends[:count]
    times = gps_time[ends]
    order = np.argsort(times, kind="mergesort")
    pairs_first = np.empty(count, np.int64)
    pairs_last = np.empty(count, np.int64)
    found = 0
    start = 0
    while start < count:  # a run of one time: match each first return to the last return of its line
        stop = start + 1
        while stop < count and times[order[stop]] == times[order[start]]:
            stop += 1
        for a in range(start, stop):
            i = ends[order[a]]
            if return_number[i] != 1:
                continue
            m = number_of_returns[i]
            for b in range(start, stop):
                j = ends[order[b]]
                if j != i and return_number[j] == m and number_of_returns[j] == m and line[j] == line[i]:
                    pairs_first[found] = i
                    pairs_last[found] = j
                    found += 1
                    break
        start = stop
    by_first = np.argsort(pairs_first[:found], kind="mergesort")
    for k in by_first:
        i, j = pairs_first[k], pairs_last[k]
        _add_pair(values[slots[i]], i, j, xs, ys, zs, gps_time, scales, shifts, per_bin, bin_seconds, min_up)


@numba.njit(cache=True, nogil=True, inline="always")
def _add_pair(row, i, j, xs, ys, zs, gps_time, scales, shifts, per_bin, bin_seconds, min_up):
    """Add the ray through first return ``i`` and last return ``j`` of one pulse to its bin's row."""
    xi = xs[i] * scales[0] + shifts[0]
    yi = ys[i] * scales[1] + shifts[1]
    zi = zs[i] * scales[2] + shifts[2]
    tb = gps_time[i] * per_bin
    ti = (tb - _floor(tb)) * bin_seconds
    dx = xi - (xs[j] * scales[0] + shifts[0])
    dy = yi - (ys[j] * scales[1] + shifts[1])
    dz = zi - (zs[j] * scales[2] + shifts[2])
    sep = math.sqrt(dx * dx + dy * dy + dz * dz)
    if sep >= 1.0 and dz > min_up * sep:
        ux, uy, uz = dx / sep, dy / sep, dz / sep
        w = min(sep, 30.0) ** 2
        axx, axy, axz = w * (1 - ux * ux), -w * ux * uy, -w * ux * uz
        ayy, ayz, azz = w * (1 - uy * uy), -w * uy * uz, w * (1 - uz * uz)
        row[5] += 1.0
        row[6] += w
        row[7] += w * ti
        row[8] += axx
        row[9] += axy
        row[10] += axz
        row[11] += ayy
        row[12] += ayz
        row[13] += azz
        row[14] += axx * xi + axy * yi + axz * zi
        row[15] += axy * xi + ayy * yi + ayz * zi
        row[16] += axz * xi + ayz * yi + azz * zi


def merge_sums(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Add the rows of the same (line, bin) from many chunks or tiles (maxima: the maximum)."""
    parts = [p for p in parts if len(p[0])]
    if not parts:
        return empty_sums()
    lines = np.concatenate([p[0] for p in parts])
    bins = np.concatenate([p[1] for p in parts])
    values = np.concatenate([p[2] for p in parts])
    keys = bins * 65536 + lines
    unique_keys, index = np.unique(keys, return_inverse=True)
    out = np.zeros((len(unique_keys), _N_COLUMNS), np.float64)
    np.add.at(out, index, np.where(_MAX_MASK, 0.0, values))
    out[:, _MAX_MASK] = -np.inf
    maxima = np.full((len(unique_keys), int(_MAX_MASK.sum())), -np.inf)
    np.maximum.at(maxima, index, values[:, _MAX_MASK])
    out[:, _MAX_MASK] = maxima
    # each direction's extreme point: from the row that reaches the merged maximum (the last such, on ties)
    h0 = _INDEX["h0"]
    for k in range(SUPPORT_DIRECTIONS):
        reaches = np.flatnonzero(values[:, h0 + k] == out[index, h0 + k])
        for name in _CARRIED:
            column = _INDEX[f"{name}{k}"]
            out[index[reaches], column] = values[reaches, column]
    order = np.lexsort((unique_keys // 65536, unique_keys % 65536))
    return (unique_keys % 65536)[order], (unique_keys // 65536)[order], out[order]


@dataclass(frozen=True, eq=False)
class TrajectorySums:
    """The sums of a tile, a file or the survey: rows keyed by (line, time bin); ``+`` merges."""

    lines: np.ndarray
    bins: np.ndarray
    values: np.ndarray

    def __eq__(self, other: object) -> bool:
        return isinstance(other, TrajectorySums) and all(
            np.array_equal(getattr(self, name), getattr(other, name)) for name in ("lines", "bins", "values")
        )

    __hash__ = None  # type: ignore[assignment]  # arrays: equal, not hashable

    @classmethod
    def empty(cls) -> TrajectorySums:
        return cls(*empty_sums())

    @classmethod
    def merged(cls, parts: list[TrajectorySums]) -> TrajectorySums:
        return cls(*merge_sums([(p.lines, p.bins, p.values) for p in parts]))

    def __add__(self, other: TrajectorySums) -> TrajectorySums:
        return TrajectorySums.merged([self, other])

    def __len__(self) -> int:
        return len(self.lines)

    @property
    def points(self) -> int:
        """Points summed (those with a GPS time)."""
        return int(self.values[:, _INDEX["n"]].sum())
