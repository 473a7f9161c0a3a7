"""Which swaths cover a pixel, and whether the sensor saw it unobstructed (pure, numba).

A pixel without returns inside a line's swath was swept by the scanner. Whether the
laser could reach it is a matter of geometry: the line of sight from the sensor's
position, when its scan plane passed over the pixel, to the ground at the pixel.
The ray is followed over the surface model (the highest return of each pixel) from
the pixel towards the sensor; it is *blocked* where a measured pixel stands above
it. A pixel blocked from every line whose swath covers it lies in the shadow of
what blocks it (occlusion); a pixel that one line saw unobstructed and that
returned nothing did not return the pulse (water, a dark or wet surface, glass).

The ground height at an empty pixel is unknown; it is taken as the lowest return
nearby (the nearest level of ``TARGET_RADII_M``, see :func:`ground_targets`): a shadow lies
on the ground beside what casts it, and a lower target only makes a blocked ray more
certain, never a seen one. A measured pixel blocks a ray only when it stands above
the ray everywhere across the pixel (the ray's rise over half a pixel is the
tolerance): the surface model's blocks must not invent obstacles at their corners.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
import scipy.ndimage as ndi

__all__ = [
    "BLOCKED",
    "OUTSIDE_SWATHS",
    "SEEN",
    "StepPixels",
    "ground_targets",
    "pixels_beside_steps",
    "shadow_contradictions",
    "sight_classes",
]

#: Classes of a hole pixel (:func:`sight_classes`); 0: not a hole pixel.
OUTSIDE_SWATHS, BLOCKED, SEEN = 1, 2, 3
#: Square radii (metres) searched, nearest first, for the ground around an empty pixel: the
#: ground beside an obstacle lies within its shadow's length, 17 m for 30 m at a 30 degree scan angle.
TARGET_RADII_M = (1.0, 2.0, 4.0, 8.0, 16.0)


#: Rows of the pixels asked for whose ground is looked for at once: the minimum filters run over a
#: band of rows at a time, not the box of every pixel asked for (a re-flight pattern's 10 km strip:
#: a window of 13 M pixels, 430 MB of filters at once, the 1 B point run's largest moment).
TARGET_BAND_ROWS = 512


def ground_targets(
    zmin: np.ndarray, measured: np.ndarray, where: np.ndarray, *, step: float, pixel_size: float
) -> np.ndarray:
    """The ground height at the pixels ``where``: the lowest return nearby, looked for ever farther out.

    The radii of ``TARGET_RADII_M`` are searched nearest first; a wider radius replaces
    the level found when it finds one lower by more than ``step`` (the height-jump
    threshold: a wall): beside a roof the nearest returns are the roof's, and the
    ground lies beyond its edge, within a shadow's length; on a gentle slope the wider
    radii are only a little lower, and the nearest level stands. NaN where no radius
    holds a measured pixel. Each radius's minimum filter runs over the box of the pixels
    asked for, band by band of :data:`TARGET_BAND_ROWS` rows (a minimum is the same over
    any cut of the box).
    """
    out = np.full(zmin.shape, np.nan)
    rows, cols = np.nonzero(where)
    if len(rows) == 0:
        return out
    current = np.full(len(rows), np.inf)
    radii = sorted({max(1, round(r / pixel_size)) for r in TARGET_RADII_M})
    band_starts = np.arange(rows.min(), rows.max() + 1, TARGET_BAND_ROWS)
    firsts = np.searchsorted(rows, band_starts)  # rows come sorted: each band's pixels are a slice
    lasts = np.append(firsts[1:], len(rows))
    for radius in radii:
        r0, r1 = max(rows.min() - radius, 0), min(rows.max() + radius + 1, zmin.shape[0])
        c0, c1 = max(cols.min() - radius, 0), min(cols.max() + radius + 1, zmin.shape[1])
        here = np.empty(len(rows))
        for start, first, last in zip(band_starts, firsts, lasts, strict=True):
            if first == last:
                continue
            # the band's rows and the radius's reach beyond them, within the box (beyond it: no return)
            b0, b1 = max(start - radius, r0), min(start + TARGET_BAND_ROWS + radius, r1)
            band = (slice(b0, b1), slice(c0, c1))
            values = np.where(measured[band], zmin[band], np.inf).astype(np.float64, copy=False)
            low = ndi.minimum_filter(values, size=2 * radius + 1, mode="constant", cval=np.inf)
            here[first:last] = low[rows[first:last] - b0, cols[first:last] - c0]
        lower = np.isfinite(here) & (~np.isfinite(current) | (here < current - step))
        current = np.where(lower, here, current)
    out[rows, cols] = np.where(np.isfinite(current), current, np.nan)
    return out


def surface_tops(
    zmax: np.ndarray,
    measured: np.ndarray,
    where: np.ndarray,
    *,
    pixel_size: float,
    water: np.ndarray | None = None,
) -> np.ndarray:
    """The first surface at the pixels ``where``: the mean highest return within the nearest radius holding one.

    What bounds a swath is the first surface the scanner's outermost pulses meet: a void
    among trees at a swath's edge lay under the canopy the edge pulses could not reach,
    and the ground beneath is wider in the swath than the canopy. Where at least half of that
    nearest radius's returns are water returns (``water``), their level: a lake's edge lies at
    the water, not at the trees on its shore; a void among land returns with a few of the water's
    beside it lies on the land (docs/holes.md: on 30 simulated scans this moved one 4 m2 Delft
    hole to its true cause, water, and nothing else). NaN where no radius of ``TARGET_RADII_M``
    holds a measured pixel.
    """
    out = np.full(zmax.shape, np.nan)
    rows, cols = np.nonzero(where)
    if len(rows) == 0:
        return out
    on_water = measured & (water if water is not None else False)
    found = np.full(len(rows), np.nan)
    for radius in sorted({max(1, round(r / pixel_size)) for r in TARGET_RADII_M}):
        todo = np.isnan(found)
        if not todo.any():
            break
        r0, r1 = max(rows.min() - radius, 0), min(rows.max() + radius + 1, zmax.shape[0])
        c0, c1 = max(cols.min() - radius, 0), min(cols.max() + radius + 1, zmax.shape[1])
        window = (slice(r0, r1), slice(c0, c1))
        level_all, count_all = _window_mean(zmax[window], measured[window], radius)
        level_water, count_water = _window_mean(zmax[window], on_water[window], radius)
        at = (rows - r0, cols - c0)
        # on the water where most of the nearest returns are the water's, else on the land
        on_lake = np.isfinite(level_water[at]) & (count_water[at] >= 0.5 * count_all[at])
        level = np.where(on_lake, level_water[at], level_all[at])
        found = np.where(todo, level, found)
    out[rows, cols] = found
    return out


def _window_mean(values: np.ndarray, where: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``values`` over the pixels ``where`` in the square of ``radius`` around each pixel (NaN: none),
    and the share of the square's pixels those are."""
    size = 2 * radius + 1
    total = ndi.uniform_filter(np.where(where, values, 0.0).astype(np.float64), size=size, mode="constant")
    count = ndi.uniform_filter(where.astype(np.float64), size=size, mode="constant")
    return np.where(count > 0.5 / size**2, total / np.maximum(count, 1e-12), np.nan), count


def sight_classes(
    candidates: np.ndarray,
    zmax: np.ndarray,
    targets: np.ndarray,
    swaths: np.ndarray,
    tracks: list[np.ndarray],
    *,
    origin_xy: tuple[float, float],
    pixel_size: float,
    reach: float,
    max_scan_angles: list[float] | None = None,
    tops: np.ndarray | None = None,
) -> np.ndarray:
    """Per candidate pixel: ``OUTSIDE_SWATHS``, ``BLOCKED`` or ``SEEN`` (0 elsewhere).

    Parameters
    ----------
    candidates : ndarray of bool, shape (H, W)
        The empty pixels to classify (the hole pixels of a cell core, within the window).
    zmax : ndarray of float, shape (H, W)
        Highest return per pixel, NaN where empty: the surface that blocks rays.
    targets : ndarray of float, shape (H, W)
        Ground height at each candidate (:func:`ground_targets`); NaN: classified as seen
        when some swath covers it (nothing to block a ray to an unknown height).
    swaths : ndarray of bool, shape (L, H, W)
        Whether line ``l``'s swath covers each pixel.
    tracks : list of ndarray, shape (K_l, 3)
        Each line's sensor positions in time order (world x, y, z).
    origin_xy : (float, float)
        World x of the window's left edge and y of its top edge; rows grow southwards.
    pixel_size : float
        Pixel size in world units.
    reach : float
        How far (world units) a ray is followed: one that leaves the window sooner (the survey's
        grid ends there) without clearing every height within the reach proves nothing, and the
        pixel is not seen by it. A ray stops at the reach, and clears the heights when it rises
        above the highest within the reach's square around its pixel: the window (the cell's
        core grown by the reach) holds that square whatever the cell size, so a pixel's class
        does not depend on it. ``inf``: followed to the window's edge.
    max_scan_angles : list of float, optional
        Each line's largest scan angle (degrees; NaN where unknown). Where known, the swath is
        exact: a pixel lies in it when the ray from the sensor to its ground is no farther from the
        vertical than that angle (at the pixel's centre), whatever ``swaths`` says; ``swaths``
        (the returns' extent) only bounds the pixels tried.
    tops : ndarray of float, shape (H, W), optional
        The first surface at each candidate (:func:`surface_tops`), for the swath's angle; the
        ground (``targets``) where not given.
    """
    out = np.zeros(candidates.shape, np.uint8)
    rows, cols = np.nonzero(candidates)
    if len(rows) == 0:
        return out
    covered = swaths[:, rows, cols] if len(swaths) else np.zeros((0, len(rows)), bool)
    tops_within_reach = _highest_within(zmax, reach / pixel_size)
    seen = np.zeros(len(rows), np.bool_)
    swept = np.zeros(len(rows), np.bool_)
    angles = max_scan_angles if max_scan_angles is not None else [math.nan] * len(tracks)
    tops = targets if tops is None else np.where(np.isnan(tops), targets, tops)
    for index, track in enumerate(tracks):
        todo = covered[index]
        if not todo.any() or len(track) < 1:
            continue
        angle = angles[index]
        tan_max = math.tan(math.radians(angle)) if math.isfinite(angle) and angle > 0 else math.inf
        _cast(
            rows[todo], cols[todo], targets, tops, zmax, np.ascontiguousarray(track, np.float64),
            origin_xy[0], origin_xy[1], pixel_size, tops_within_reach, seen, swept, np.flatnonzero(todo), reach, tan_max,
        )  # fmt: skip
    out[rows, cols] = np.where(~swept, OUTSIDE_SWATHS, np.where(seen, SEEN, BLOCKED))
    return out


class StepPixels(NamedTuple):
    """The pixels beside a step (:func:`pixels_beside_steps`) and the ground under each."""

    ground: np.ndarray  # float: the lowest return of a measured pixel, the ground found nearby for an empty one
    open_ground: np.ndarray  # bool: measured, a single surface (``zmax - zmin`` under the step)
    voids: np.ndarray  # bool: empty


def pixels_beside_steps(
    zmax: np.ndarray,
    zmin: np.ndarray,
    measured: np.ndarray,
    *,
    step: float,
    near_px: int,
    pixel_size: float,
    within: np.ndarray | None = None,
) -> StepPixels:
    """The pixels (those ``within``, default all) with a surface more than ``step`` above their ground
    within ``near_px`` pixels: where a shadow's length tells the sensor's height (:func:`shadow_contradictions`)."""
    highest = ndi.maximum_filter(np.where(measured, zmax, -np.inf), size=2 * near_px + 1, mode="constant", cval=-np.inf)
    empty = ~measured
    ground = np.where(measured, zmin, ground_targets(zmin, measured, empty, step=step, pixel_size=pixel_size))
    near_step = np.isfinite(ground) & (highest - np.nan_to_num(ground, nan=np.inf) > step)
    if within is not None:
        near_step &= within
    return StepPixels(ground, measured & (zmax - zmin < step) & near_step, empty & near_step)


def shadow_contradictions(
    zmax: np.ndarray,
    measured: np.ndarray,
    beside: StepPixels,
    swaths: np.ndarray,
    tracks: list[np.ndarray],
    *,
    origin_xy: tuple[float, float],
    pixel_size: float,
    reach: float,
    max_scan_angles: list[float] | None = None,
) -> tuple[int, int, int]:
    """How far a trajectory's heights disagree with the shadows the survey shows beside its steps.

    Beside each step (``beside``, :func:`pixels_beside_steps`), a sensor placed too low casts
    shadows that are too long, over ground that returned points; one placed too high casts them
    too short, and the voids behind the step read as seen. Returns ``(returned_but_blocked,
    empty_but_seen, judged)``: open-ground pixels inside a swath that no line could see, empty
    pixels some line saw, and how many pixels inside a swath were judged. A dark or wet patch
    beside a step is seen from any height, and adds the same to each trajectory's count.
    Arguments as :func:`sight_classes`.
    """
    inside = swaths.any(axis=0) if len(swaths) else np.zeros(zmax.shape, bool)
    open_ground, voids = beside.open_ground & inside, beside.voids & inside
    classes = sight_classes(
        open_ground | voids,
        np.where(measured, zmax, np.nan),
        beside.ground,
        swaths,
        tracks,
        origin_xy=origin_xy,
        pixel_size=pixel_size,
        reach=reach,
        max_scan_angles=max_scan_angles,
    )
    judged = int(open_ground.sum() + voids.sum())
    return int((open_ground & (classes == BLOCKED)).sum()), int((voids & (classes == SEEN)).sum()), judged


def _highest_within(zmax: np.ndarray, reach_px: float) -> np.ndarray:
    """Per pixel, the highest measured height in the square of half-side ``reach_px`` around it (-inf: none)."""
    heights = np.where(np.isfinite(zmax), zmax, -np.inf)
    if not math.isfinite(reach_px) or reach_px >= max(zmax.shape):
        return np.full(zmax.shape, float(heights.max(initial=-np.inf)))
    size = 2 * math.ceil(reach_px) + 1
    return ndi.maximum_filter(heights, size=size, mode="constant", cval=-np.inf)


@numba.njit(cache=True, nogil=True)
def _sensor_at(track, x, y):
    """The sensor's position when its scan plane (across the track) passed over (x, y)."""
    k = len(track)
    if k == 1:
        return track[0, 0], track[0, 1], track[0, 2]
    hx, hy = track[k - 1, 0] - track[0, 0], track[k - 1, 1] - track[0, 1]
    norm = math.sqrt(hx * hx + hy * hy)
    if norm == 0.0:
        return track[0, 0], track[0, 1], track[0, 2]
    hx, hy = hx / norm, hy / norm
    target = x * hx + y * hy
    previous = track[0, 0] * hx + track[0, 1] * hy
    if target <= previous:
        return track[0, 0], track[0, 1], track[0, 2]
    for i in range(1, k):
        here = track[i, 0] * hx + track[i, 1] * hy
        if target <= here:
            f = (target - previous) / (here - previous) if here > previous else 0.0
            return (
                track[i - 1, 0] + f * (track[i, 0] - track[i - 1, 0]),
                track[i - 1, 1] + f * (track[i, 1] - track[i - 1, 1]),
                track[i - 1, 2] + f * (track[i, 2] - track[i - 1, 2]),
            )
        previous = here
    return track[k - 1, 0], track[k - 1, 1], track[k - 1, 2]


@numba.njit(cache=True, nogil=True)
def _cast(rows, cols, targets, tops, zmax, track, x_left, y_top, pixel, highest, seen, swept, slots, reach, tan_max):
    height, width = zmax.shape
    for n in range(len(rows)):
        r, c = rows[n], cols[n]
        z0 = targets[r, c]
        if z0 != z0:  # no ground height nearby: nothing to test against
            swept[slots[n]] = True
            seen[slots[n]] = True
            continue
        x0 = x_left + (c + 0.5) * pixel
        y0 = y_top - (r + 0.5) * pixel
        sx, sy, sz = _sensor_at(track, x0, y0)
        dx, dy = sx - x0, sy - y0
        distance = math.sqrt(dx * dx + dy * dy)
        if sz <= z0:
            continue  # the sensor below the ground: no line of sight
        surface = tops[r, c]
        if distance > (sz - surface) * tan_max:
            continue  # beyond the scanner's largest angle at the first surface: outside this line's swath
        swept[slots[n]] = True
        if seen[slots[n]]:
            continue
        if distance < 0.25 * pixel:
            seen[slots[n]] = True  # straight below the sensor: nothing stands in between
            continue
        ux, uy = dx / distance, dy / distance
        slope = (sz - z0) / distance
        step = 0.5 * pixel
        tolerance = slope * 0.5 * pixel
        blocked = False
        top = highest[r, c]
        t = step
        while t < distance and t < reach:
            ray_z = z0 + slope * t
            if ray_z > top:
                break
            cc = int(math.floor((x0 + ux * t - x_left) / pixel))
            rr = int(math.floor((y_top - (y0 + uy * t)) / pixel))
            if rr < 0 or rr >= height or cc < 0 or cc >= width:
                blocked = t < reach - pixel  # the grid ends before the reach: nothing proven
                break
            if not (rr == r and cc == c):
                z = zmax[rr, cc]
                if z == z and z > ray_z + tolerance:
                    blocked = True
                    break
            t += step
        if not blocked:
            seen[slots[n]] = True
