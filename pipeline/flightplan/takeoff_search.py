"""Where a re-flight takes off: the open ground nearest to the planned holes, searched where it can be.

:func:`nearest_open_ground` runs :func:`.takeoff.choose_takeoff` window by window, one per
cluster of holes (within ``TAKEOFF_MAX_M`` of them), over ground points read on request near the
place the DSM alone shows open (:class:`GroundGrid`, whose grids hold only the boxes read:
:class:`BoxGrid`), so that its cost follows the holes and not the span of the survey. The rules
of open ground are :mod:`.takeoff`'s; :func:`pipeline.flightplan.mission.plan_mission` calls this.

Pure: numpy arrays, shapely geometries and an affine transform in, a ``Takeoff`` out; the ground
points come through the caller's reader.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
import scipy.ndimage as ndi
import shapely
from affine import Affine

from .altitude import AffineLike, Surface
from .coverage import Point2
from .takeoff import Takeoff, TakeoffParams, choose_takeoff

__all__ = [
    "TAKEOFF_MAX_M",
    "TAKEOFF_SEARCH_M",
    "AreaMask",
    "WindowOf",
    "BoxGrid",
    "GroundGrid",
    "area_boxes",
    "merged_boxes",
    "nearest_open_ground",
    "rasterize_areas",
    "target_windows",
]


#: Where the take-off is sought first: the ground points within this distance of the flattest clear
#: place the DSM shows near the holes (a pilot walks there; the survey's points are not all decoded).
TAKEOFF_SEARCH_M = 150.0
#: The farthest from the planned holes a take-off is sought (a pilot keeps the drone in sight: a few
#: hundred metres); the DSM is read this far around them too (:func:`pipeline.flight_planning.plan_flights`).
TAKEOFF_MAX_M = 500.0


class BoxGrid:
    """A grid of ``shape`` that holds only the boxes written into it: ``fill`` everywhere else.

    Reads and writes by row and column slices (or a single pixel), as a numpy array's; what it
    holds follows the boxes written (the ground points read near a take-off), not the grid's span
    (a DSM window over holes 10 km apart: 100 M pixels, 800 MB as a float64 array).
    """

    def __init__(self, shape: tuple[int, int], fill: float) -> None:
        self.shape = shape
        self.fill = fill
        self._boxes: list[tuple[int, int, np.ndarray]] = []  # (row, column, values), later ones on top

    def __getitem__(self, key: tuple[slice | int, slice | int]) -> Any:
        single = all(isinstance(k, (int, np.integer)) for k in key)
        rows, cols = (slice(int(k), int(k) + 1) if isinstance(k, (int, np.integer)) else k for k in key)
        r0, r1, _ = rows.indices(self.shape[0])
        c0, c1, _ = cols.indices(self.shape[1])
        out = np.full((max(r1 - r0, 0), max(c1 - c0, 0)), self.fill)
        for br, bc, values in self._boxes:
            a0, a1 = max(r0, br), min(r1, br + values.shape[0])
            b0, b1 = max(c0, bc), min(c1, bc + values.shape[1])
            if a0 < a1 and b0 < b1:
                out[a0 - r0 : a1 - r0, b0 - c0 : b1 - c0] = values[a0 - br : a1 - br, b0 - bc : b1 - bc]
        return float(out[0, 0]) if single else out

    def __setitem__(self, key: tuple[slice, slice], values: np.ndarray) -> None:
        r0, r1, _ = key[0].indices(self.shape[0])
        c0, c1, _ = key[1].indices(self.shape[1])
        self._boxes.append((r0, c0, np.array(np.broadcast_to(values, (r1 - r0, c1 - c0)), dtype=np.float64)))


@dataclass(frozen=True)
class GroundGrid:
    """Ground-class points on the DSM's grid: mean height per pixel (NaN: none), water points per pixel.

    With a ``reader`` the grids start empty and :meth:`load` reads the points of a pixel box on
    request (rows ``r0:r1``, columns ``c0:c1``): the caller's I/O, handed in, so the kernels stay pure.
    """

    height: np.ndarray | BoxGrid
    water: np.ndarray | BoxGrid | None = None
    reader: Callable[[tuple[int, int, int, int]], tuple[np.ndarray, np.ndarray]] | None = None

    def load(self, box: tuple[int, int, int, int]) -> None:
        """Read the ground points of ``box`` (clipped to the grid) into the grids, where a reader is set."""
        if self.reader is None:
            return
        rows, cols = self.height.shape
        r0, c0, r1, c1 = max(box[0], 0), max(box[1], 0), min(box[2], rows), min(box[3], cols)
        if r1 <= r0 or c1 <= c0:
            return
        height, water = self.reader((r0, c0, r1, c1))
        self.height[r0:r1, c0:c1] = height
        if self.water is not None:
            self.water[r0:r1, c0:c1] = water

    def load_around(self, xy: Point2, transform: AffineLike, radius_m: float) -> tuple[int, int, int, int] | None:
        """Read the ground points within ``radius_m`` of ``xy``; the box read (clipped; None: off the grid)."""
        col, row = (xy[0] - transform.c) / transform.a, (xy[1] - transform.f) / transform.e  # north-up (open_dsm)
        r = int(math.ceil(radius_m / max(abs(transform.a), 1e-9)))
        rows, cols = self.height.shape
        box = (max(int(row) - r, 0), max(int(col) - r, 0), min(int(row) + r + 1, rows), min(int(col) + r + 1, cols))
        if box[2] <= box[0] or box[3] <= box[1]:
            return None
        self.load(box)
        return box


def nearest_open_ground(
    dsm: Surface,
    transform: AffineLike,
    targets: np.ndarray | AreaMask,
    ground: GroundGrid,
    params: TakeoffParams,
    *,
    within: list[tuple[int, int, int, int]],
) -> Takeoff | None:
    """:func:`.takeoff.choose_takeoff` within ``TAKEOFF_MAX_M`` of the planned holes, over ground points read where they can matter.

    The search runs window by window, one per cluster of holes (their pixels grown by
    ``TAKEOFF_MAX_M``, overlapping windows merged), so that its cost follows the holes and not the
    span of the survey (three clusters 10 km apart are three small windows, not one 20 km grid).
    In each window a grid read on request is read first within ``TAKEOFF_SEARCH_M`` of the place
    the DSM alone shows flat and clear nearest to the holes (open ground is flat and clear in the
    DSM too, so the DSM's choice is at least as near), and judged there alone; then the whole
    window. Of the windows' choices the one nearest to its holes wins (ties: nearest to the
    centre of all of them, then the first in row order), as one search over the whole grid would
    choose. ``targets``: the holes' pixels, a boolean array or an :class:`AreaMask` (which holds
    them near the holes alone); ``within``: boxes that hold every target pixel (:func:`target_windows`).
    """
    centre = _mean_pixel(targets, within)
    if centre is None:
        return None
    reach = int(math.ceil(TAKEOFF_MAX_M / max(abs(transform.a), 1e-9)))
    best: tuple[tuple[float, float, int, int], Takeoff] | None = None
    for r0, c0, r1, c1 in target_windows(targets, reach, within):
        window = _affine(transform) @ Affine.translation(c0, r0)
        local = (slice(r0, r1), slice(c0, c1))
        local_targets = targets[local]
        distance = rounded_distance(local_targets)
        surface = WindowOf(dsm, (r0, c0, r1, c1))  # read where the search looks, not the whole window
        found = _open_ground_in(surface, transform, local_targets, ground, (r0, c0), params, distance, centre)
        if found is None:
            continue
        r = int((found.xy[1] - window.f) / window.e)  # north-up (open_dsm refuses rotated rasters)
        c = int((found.xy[0] - window.c) / window.a)
        score = (float(np.round(distance[r, c])), math.hypot(r + r0 - centre[0], c + c0 - centre[1]), r + r0, c + c0)
        if best is None or score < best[0]:
            best = (score, found)
    return None if best is None else best[1]


def rounded_distance(targets: np.ndarray) -> np.ndarray:
    """Each pixel's Euclidean distance to the nearest target pixel, rounded to whole pixels (float32).

    What the take-off search ranks by (``choose_takeoff``'s ``rank``): the same values as
    ``np.round(scipy.ndimage.distance_transform_edt(~targets))``, without scipy's 40 bytes a
    pixel of temporaries (its feature transform, then its distances in float64): a window of 24 M
    pixels along a 10 km missed line took 950 MB there, 290 MB here (an int64 column pass, then
    the rows). Exact: the squared distances are integers (Felzenszwalb and Huttenlocher's lower
    envelope of parabolas), and the square root of an integer is never halfway between two.
    """
    targets = np.asarray(targets, dtype=bool)
    if targets.ndim != 2:
        raise ValueError(f"targets must be 2-dimensional, got shape {targets.shape}")
    if not targets.any():
        return np.full(targets.shape, np.inf, np.float32)
    return _rounded_distance(targets)


@numba.njit(cache=True)
def _rounded_distance(targets):  # pragma: no cover - compiled
    rows, cols = targets.shape
    far = np.int64(rows + cols) ** 2 + 1  # more than any squared distance inside the window
    column = np.empty((rows, cols), np.int64)  # squared distance to the nearest target in the column
    for c in range(cols):
        last = -1
        for r in range(rows):
            if targets[r, c]:
                last = r
            column[r, c] = far if last < 0 else (r - last) ** 2
        last = -1
        for r in range(rows - 1, -1, -1):
            if targets[r, c]:
                last = r
            if last >= 0 and (last - r) ** 2 < column[r, c]:
                column[r, c] = (last - r) ** 2
    out = np.empty((rows, cols), np.float32)
    sites = np.empty(cols, np.int64)
    bounds = np.empty(cols + 1, np.float64)
    for r in range(rows):
        f = column[r]
        k = -1
        for q in range(cols):  # the lower envelope of the parabolas f[q] + (x - q)^2
            if f[q] >= far:
                continue
            while k >= 0:
                p = sites[k]
                s = ((f[q] + q * q) - (f[p] + p * p)) / (2.0 * (q - p))
                if s <= bounds[k]:
                    k -= 1
                else:
                    break
            k += 1
            sites[k] = q
            bounds[k] = (
                -np.inf
                if k == 0
                else ((f[q] + q * q) - (f[sites[k - 1]] + sites[k - 1] ** 2)) / (2.0 * (q - sites[k - 1]))
            )
            bounds[k + 1] = np.inf
        if k < 0:
            for q in range(cols):
                out[r, q] = np.inf
            continue
        j = 0
        for q in range(cols):
            while bounds[j + 1] < q:
                j += 1
            p = sites[j]
            out[r, q] = np.round(np.sqrt(np.float64((q - p) ** 2 + f[p])))
    return out


def _open_ground_in(
    dsm: np.ndarray | WindowOf,
    transform: AffineLike,
    targets: np.ndarray,
    ground: GroundGrid,
    corner: tuple[int, int],
    params: TakeoffParams,
    distance: np.ndarray,
    centre: tuple[float, float],
) -> Takeoff | None:
    """:func:`.takeoff.choose_takeoff` in one window of the grid (``corner``: its first row and column;
    ``transform``: the whole grid's)."""
    r0, c0 = corner
    window = _affine(transform) @ Affine.translation(c0, r0)
    shape = dsm.shape
    local_centre = (centre[0] - r0, centre[1] - c0)

    def judged(box: tuple[int, int, int, int]) -> Takeoff | None:
        """Judged on the ground points of ``box`` (window pixels) alone."""
        b0, d0, b1, d1 = box
        sub = (slice(b0, b1), slice(d0, d1))
        height = ground.height[r0 + b0 : r0 + b1, c0 + d0 : c0 + d1]
        water = None if ground.water is None else ground.water[r0 + b0 : r0 + b1, c0 + d0 : c0 + d1]
        return choose_takeoff(
            dsm[sub], height, water, window @ Affine.translation(d0, b0), targets[sub], params=params,
            distance=distance[sub], centre=(local_centre[0] - b0, local_centre[1] - d0),
        )  # fmt: skip

    if ground.reader is not None:
        guess = choose_takeoff(dsm, dsm, None, window, targets, params=params, distance=distance, centre=local_centre)
        if guess is not None:
            box = ground.load_around(guess.xy, transform, TAKEOFF_SEARCH_M)
            if box is not None:
                b0, d0, b1, d1 = box
                inner = (max(b0 - r0, 0), max(d0 - c0, 0), min(b1 - r0, shape[0]), min(d1 - c0, shape[1]))
                if inner[2] > inner[0] and inner[3] > inner[1]:
                    found = judged(inner)
                    if found is not None:
                        return found
        ground.load((r0, c0, r0 + shape[0], c0 + shape[1]))
    return judged((0, 0, *shape))


def _affine(transform: AffineLike) -> Affine:
    return Affine(transform.a, transform.b, transform.c, transform.d, transform.e, transform.f)


def target_windows(
    targets: np.ndarray | AreaMask, reach: int, within: list[tuple[int, int, int, int]]
) -> list[tuple[int, int, int, int]]:
    """Boxes ``(r0, c0, r1, c1)`` around the clusters of ``targets``, grown by ``reach`` pixels, overlapping ones merged.

    ``within``: boxes that hold every target pixel (each area's, :func:`area_boxes`). The
    clusters are labelled box group by box group (boxes grown by a pixel and merged: a cluster
    never leaves its group), so the label raster follows the holes, not the span (100 M pixels,
    400 MB of int32 labels, for holes 10 km apart); the clusters and so the windows are those of
    one labelling of the whole grid.
    """
    rows, cols = targets.shape
    boxes = []
    for g0, h0, g1, h1 in _box_groups(within, targets.shape):
        labels, _ = ndi.label(targets[g0:g1, h0:h1])
        boxes += [
            [max(sl[0].start + g0 - reach, 0), max(sl[1].start + h0 - reach, 0),
             min(sl[0].stop + g0 + reach, rows), min(sl[1].stop + h0 + reach, cols)]
            for sl in ndi.find_objects(labels) if sl is not None
        ]  # fmt: skip
    return merged_boxes(boxes)


def _box_groups(within: list[tuple[int, int, int, int]], shape: tuple[int, ...]) -> list[tuple[int, int, int, int]]:
    """The boxes grown by a pixel and merged: disjoint groups, each holding its boxes' target
    pixels and every pixel touching them (so a cluster of targets never leaves its group)."""
    rows, cols = shape[0], shape[1]
    return merged_boxes(
        [[max(b[0] - 1, 0), max(b[1] - 1, 0), min(b[2] + 1, rows), min(b[3] + 1, cols)] for b in within]
    )


def merged_boxes(boxes: list[list[int]]) -> list[tuple[int, int, int, int]]:
    """Boxes ``[r0, c0, r1, c1]`` that overlap merged into their hull, until none overlaps (the finest such set)."""
    merged = True
    while merged:
        merged = False
        out: list[list[int]] = []
        for box in boxes:
            for other in out:
                if box[0] < other[2] and other[0] < box[2] and box[1] < other[3] and other[1] < box[3]:
                    other[:] = [
                        min(box[0], other[0]),
                        min(box[1], other[1]),
                        max(box[2], other[2]),
                        max(box[3], other[3]),
                    ]
                    merged = True
                    break
            else:
                out.append(box)
        boxes = out
    return sorted((b[0], b[1], b[2], b[3]) for b in boxes)


def area_boxes(
    areas: list[shapely.Geometry], shape: tuple[int, ...], transform: AffineLike
) -> list[tuple[int, int, int, int]]:
    """Per area, the pixel box ``(r0, c0, r1, c1)`` that holds every pixel whose centre lies in it (empty boxes left out)."""
    boxes = []
    t = transform
    for area in areas:
        x0, y0, x1, y1 = area.bounds
        c0, c1 = sorted(((x0 - t.c) / t.a, (x1 - t.c) / t.a))
        r0, r1 = sorted(((y0 - t.f) / t.e, (y1 - t.f) / t.e))
        c0, r0 = max(0, int(c0)), max(0, int(r0))
        c1, r1 = min(shape[1], int(math.ceil(c1)) + 1), min(shape[0], int(math.ceil(r1)) + 1)
        if c0 < c1 and r0 < r1:
            boxes.append((r0, c0, r1, c1))
    return boxes


class WindowOf:
    """The box ``(r0, c0, r1, c1)`` of a surface, indexed in its own pixels and read where indexed.

    ``view[r, c]`` and ``view[a:b, c:d]`` give what the same index of ``surface[r0:r1, c0:c1]``
    gives, without that array: the take-off search's window around the 1 B-point bench survey's
    largest cluster of holes was 31 M pixels, 248 MB of float64, of which the search reads the
    blocks near the holes (:class:`pipeline.flightplan.takeoff._BlockedOpenGround`).
    """

    def __init__(self, surface: Surface, box: tuple[int, int, int, int]) -> None:
        self._surface = surface
        self._r0, self._c0 = box[0], box[1]
        self.shape = (box[2] - box[0], box[3] - box[1])

    @property
    def size(self) -> int:
        return self.shape[0] * self.shape[1]

    def __getitem__(self, key: tuple[Any, Any]) -> Any:
        rows, cols = key
        if isinstance(rows, slice) and isinstance(cols, slice):
            a0, a1, step_r = rows.indices(self.shape[0])
            b0, b1, step_c = cols.indices(self.shape[1])
            if step_r != 1 or step_c != 1:
                raise IndexError("WindowOf reads contiguous windows only")
            a1, b1 = max(a1, a0), max(b1, b0)
            return self._surface[self._r0 + a0 : self._r0 + a1, self._c0 + b0 : self._c0 + b1]
        if isinstance(rows, (int, np.integer)) and isinstance(cols, (int, np.integer)):
            if not (0 <= rows < self.shape[0] and 0 <= cols < self.shape[1]):
                raise IndexError(f"pixel {rows}, {cols} is outside the window's {self.shape}")
            return self._surface[self._r0 + int(rows), self._c0 + int(cols)]
        raise IndexError("WindowOf reads single pixels and contiguous windows only")


def _mean_pixel(targets: np.ndarray | AreaMask, within: list[tuple[int, int, int, int]]) -> tuple[float, float] | None:
    """Mean row and column of the target pixels (None: none), read group of boxes by group.

    The boxes' groups (grown by a pixel and merged, as :func:`target_windows` groups them) hold
    every target pixel once; the sums are exact integers, so the mean is the whole grid's
    ``np.nonzero`` mean to the bit.
    """
    count = row_sum = col_sum = 0
    for g0, h0, g1, h1 in _box_groups(within, targets.shape):
        r, c = np.nonzero(targets[g0:g1, h0:h1])
        count += len(r)
        row_sum += int(r.sum()) + g0 * len(r)
        col_sum += int(c.sum()) + h0 * len(c)
    return None if count == 0 else (row_sum / count, col_sum / count)


class AreaMask:
    """The pixels whose centres lie in any of ``areas``, held area by area within each one's box.

    Sliced by rows and columns as the boolean array :func:`rasterize_areas` makes, without that
    array over the grid's span: the planned holes of a 10 x 10 km survey (1 B points at 1 m) made a
    100 MB mask for the take-off search, holes on two continents an impossible one. Each area is
    rasterized once; a slice ORs the areas' masks it meets.
    """

    def __init__(self, areas: list[shapely.Geometry], shape: tuple[int, ...], transform: AffineLike) -> None:
        self.shape = (int(shape[0]), int(shape[1]))
        self.boxes: list[tuple[int, int, int, int]] = []  # one per area that meets the grid (area_boxes')
        self._masks: list[np.ndarray] = []
        for area in areas:
            for box in area_boxes([area], shape, transform):
                self.boxes.append(box)
                self._masks.append(_area_pixels(area, box, transform))

    def __getitem__(self, key: tuple[slice, slice]) -> np.ndarray:
        rows, cols = key
        r0, r1, _ = rows.indices(self.shape[0])
        c0, c1, _ = cols.indices(self.shape[1])
        out = np.zeros((max(r1 - r0, 0), max(c1 - c0, 0)), dtype=bool)
        for (b0, d0, b1, d1), mask in zip(self.boxes, self._masks, strict=True):
            i0, i1, j0, j1 = max(b0, r0), min(b1, r1), max(d0, c0), min(d1, c1)
            if i0 < i1 and j0 < j1:
                out[i0 - r0 : i1 - r0, j0 - c0 : j1 - c0] |= mask[i0 - b0 : i1 - b0, j0 - d0 : j1 - d0]
        return out


def _area_pixels(area: shapely.Geometry, box: tuple[int, int, int, int], transform: AffineLike) -> np.ndarray:
    """Within ``box``, the pixels whose centres lie in ``area``."""
    r0, c0, r1, c1 = box
    t = transform
    rr, cc = np.ogrid[r0:r1, c0:c1]  # a column and a row: the centres broadcast, not a grid of each
    return shapely.contains_xy(area, t.a * (cc + 0.5) + t.c, t.e * (rr + 0.5) + t.f)


def rasterize_areas(areas: list[shapely.Geometry], shape: tuple[int, ...], transform: AffineLike) -> np.ndarray:
    """True at the pixels whose centres lie in any of the areas (an axis-aligned DSM grid).

    The whole grid's mask, assembled apart from :class:`AreaMask`'s slices (which the take-off
    search uses): the reference its tests compare them with.
    """
    mask = np.zeros(shape[:2], dtype=bool)
    for area in areas:
        for r0, c0, r1, c1 in area_boxes([area], shape, transform):
            mask[r0:r1, c0:c1] |= _area_pixels(area, (r0, c0, r1, c1), transform)
    return mask
