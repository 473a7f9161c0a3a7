"""Where the drone takes off and lands: open, level ground, and its height from the ground points.

Heights relative to take-off are only right when the take-off height is the ground the
drone stands on. The DSM is the top of whatever was there (a roof, a tree crown), so the
take-off height comes from the *ground-class* points (ASPRS 2) binned on the DSM's grid
(:func:`pipeline.io.flightplan_files.read_ground`), never from the DSM.

Open ground (:func:`open_ground`), per pixel of the DSM grid:

- ground points in the pixel (its height is measured, not guessed);
- nothing higher than ``obstacle_m`` above that ground within ``clear_radius_m``
  (DSM pixels without data count as obstacles: a hole may hide one);
- no water-class points (ASPRS 9) within ``clear_radius_m``;
- level: the ground points within ``clear_radius_m`` span at most
  ``2 clear_radius_m tan(max_slope_deg)`` in height.

The default home is the open-ground pixel nearest to the planned holes
(:func:`choose_takeoff`); a home the user chose is kept and only checked
(:func:`check_home`).

Pure functions: numpy arrays and an affine transform in, dataclasses out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.ndimage as ndi

from .altitude import AffineLike, _inverse
from .coverage import Point2

__all__ = ["Takeoff", "TakeoffParams", "check_home", "choose_takeoff", "ground_height_at", "open_ground"]


@dataclass(frozen=True)
class TakeoffParams:
    """What makes ground fit for take-off and landing (``[flightplan]``, metres and degrees).

    ``clear_radius_m`` 10 m: the aircraft's horizontal hold error in GNSS mode (about 1.5 m),
    wind drift while climbing through the first metres (about 2 m) and the manufacturers'
    advice to keep people and obstacles several metres away, with a margin.
    ``obstacle_m`` 1 m: grass and low crops are below it; shrubs, fences, cars, walls and
    trees are above. ``max_slope_deg`` 5 deg: a skid or leg undercarriage stands upright
    and the autopilot's level check at arming passes.
    """

    clear_radius_m: float = 10.0
    obstacle_m: float = 1.0
    max_slope_deg: float = 5.0


@dataclass(frozen=True)
class Takeoff:
    """The take-off point, its ground height, where that came from, and a warning if any."""

    xy: Point2
    ground_m: float
    source: str  # "ground points" or "DSM (no ground points)"
    warning: str = ""


def _disc(radius_px: float) -> np.ndarray:
    r = max(0, int(math.floor(radius_px)))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    return (xx * xx + yy * yy) <= radius_px * radius_px + 1e-9


def _pixel_m(transform: AffineLike) -> float:
    return max(math.hypot(transform.a, transform.d), math.hypot(transform.b, transform.e))


def open_ground(
    dsm: np.ndarray,
    ground: np.ndarray,
    water: np.ndarray | None,
    transform: AffineLike,
    *,
    params: TakeoffParams,
) -> np.ndarray:
    """Pixels fit for take-off (True), by the rules of the module docstring.

    Parameters
    ----------
    dsm, ground : ndarray of shape (M, N)
        Surface heights and mean ground-point heights on one grid; NaN where empty.
    water : ndarray of shape (M, N), optional
        Water-class points per pixel.
    """
    if dsm.shape != ground.shape:
        raise ValueError(f"dsm and ground must have the same shape, got {dsm.shape} and {ground.shape}")
    disc = _disc(params.clear_radius_m / _pixel_m(transform))
    has_ground = np.isfinite(ground)
    top = ndi.maximum_filter(np.where(np.isfinite(dsm), dsm, np.inf), footprint=disc, mode="constant", cval=np.inf)
    clear = top <= np.where(has_ground, ground, -np.inf) + params.obstacle_m
    high = ndi.maximum_filter(np.where(has_ground, ground, -np.inf), footprint=disc, mode="nearest")
    low = ndi.minimum_filter(np.where(has_ground, ground, np.inf), footprint=disc, mode="nearest")
    level = (high - low) <= 2.0 * params.clear_radius_m * math.tan(math.radians(params.max_slope_deg))
    dry = np.ones_like(has_ground)
    if water is not None:
        dry = ~ndi.maximum_filter(water > 0, footprint=disc, mode="constant", cval=False)
    return has_ground & clear & level & dry


def ground_height_at(ground: np.ndarray, transform: AffineLike, point: Point2, *, search_m: float) -> float:
    """Ground height at a point: its pixel's, else the median of the ground pixels within ``search_m``; NaN if none."""
    r, c = _pixel_of(transform, point)
    if 0 <= r < ground.shape[0] and 0 <= c < ground.shape[1] and np.isfinite(ground[r, c]):
        return float(ground[r, c])
    reach = max(1, math.ceil(search_m / _pixel_m(transform)))
    window = ground[max(0, r - reach) : max(0, r + reach + 1), max(0, c - reach) : max(0, c + reach + 1)]
    values = window[np.isfinite(window)]
    return float(np.median(values)) if values.size else math.nan


def choose_takeoff(
    dsm: np.ndarray,
    ground: np.ndarray,
    water: np.ndarray | None,
    transform: AffineLike,
    targets: np.ndarray,
    *,
    params: TakeoffParams,
    distance: np.ndarray | None = None,
    centre: tuple[float, float] | None = None,
) -> Takeoff | None:
    """The open-ground pixel nearest to the ``targets`` (True: a planned hole); None if there is none.

    Ties (pixels equally near the holes) go to the one nearest the targets' centre. A window of a
    larger grid passes the larger grid's ``distance`` to the targets (pixels, cropped) and their
    ``centre`` (row, column in the window's pixels): the targets may lie outside the window.

    The search runs on growing boxes (:func:`_search_reaches`): the pixels nearer the targets
    than a reach, with the clear radius around them, so that the filters of :func:`open_ground`
    see what they would see over the whole grid there; the first reach holding open ground
    gives the same pixel as one search over the whole grid (every pixel beyond is farther), at
    the cost of the box around the holes where open ground lies near them (0.94 -> 0.41 s for a
    missed line across the 42 M bench survey: the box of a long strip is still most of the window).
    """
    if distance is None or centre is None:
        if not targets.any():
            return None
        rows, cols = np.nonzero(targets)
        distance, centre = ndi.distance_transform_edt(~targets), (float(rows.mean()), float(cols.mean()))
    offset = np.hypot(np.arange(dsm.shape[0])[:, None] - centre[0], np.arange(dsm.shape[1])[None, :] - centre[1])
    rank = np.round(distance)
    tie_scale = 1 + offset.max()
    margin = int(math.floor(params.clear_radius_m / _pixel_m(transform))) + 1
    for reach in _search_reaches(float(rank.max()) if rank.size else 0.0):
        near = rank < reach
        if not near.any():
            continue
        rows, cols = np.nonzero(near)
        r0, r1 = max(int(rows.min()) - margin, 0), min(int(rows.max()) + margin + 1, dsm.shape[0])
        c0, c1 = max(int(cols.min()) - margin, 0), min(int(cols.max()) + margin + 1, dsm.shape[1])
        box = (slice(r0, r1), slice(c0, c1))
        fit = open_ground(dsm[box], ground[box], None if water is None else water[box], transform, params=params)
        fit &= near[box]
        if fit.any():
            score = np.where(fit, rank[box] * (1 + dsm.size) + offset[box] / tie_scale, np.inf)
            r, c = np.unravel_index(int(np.argmin(score)), score.shape)
            r, c = r + r0, c + c0
            t = transform
            xy = (t.a * (c + 0.5) + t.b * (r + 0.5) + t.c, t.d * (c + 0.5) + t.e * (r + 0.5) + t.f)
            return Takeoff((float(xy[0]), float(xy[1])), float(ground[r, c]), "ground points")
    return None


def _search_reaches(farthest: float) -> list[float]:
    """Distances (pixels, exclusive) within which :func:`choose_takeoff` looks in turn: 64, 256, ... then all.

    The nearest open ground is usually close to the holes, so the filters of
    :func:`open_ground` run on a small box first; the last reach takes every pixel.
    """
    reaches, reach = [], 64.0
    while reach <= farthest:
        reaches.append(reach)
        reach *= 4
    return [*reaches, math.inf]


def check_home(
    dsm: np.ndarray, ground: np.ndarray, transform: AffineLike, home: Point2, *, params: TakeoffParams
) -> Takeoff:
    """A chosen home, kept: its ground height from the ground points, and a warning on a roof or canopy.

    Without ground points near it (within ``clear_radius_m``), the DSM there stands in
    and the warning says so.
    """
    ground_m = ground_height_at(ground, transform, home, search_m=params.clear_radius_m)
    r, c = _pixel_of(transform, home)
    inside = 0 <= r < dsm.shape[0] and 0 <= c < dsm.shape[1]
    surface = float(dsm[r, c]) if inside and np.isfinite(dsm[r, c]) else math.nan
    if not math.isfinite(ground_m):
        return Takeoff(home, surface, "DSM (no ground points)", "no ground points near home: its height is the DSM's")
    warning = ""
    if math.isfinite(surface) and surface - ground_m > params.obstacle_m:
        warning = (
            f"home {home[0]:.1f}, {home[1]:.1f} is on a roof or canopy: the surface there is "
            f"{surface - ground_m:.1f} m above the ground points; heights are relative to the ground, "
            "so take off from the ground there or choose another home"
        )
    return Takeoff(home, ground_m, "ground points", warning)


def _pixel_of(transform: AffineLike, point: Point2) -> tuple[int, int]:
    inv = _inverse(transform)
    col = inv[0] * point[0] + inv[1] * point[1] + inv[2]
    row = inv[3] * point[0] + inv[4] * point[1] + inv[5]
    return int(math.floor(row)), int(math.floor(col))
