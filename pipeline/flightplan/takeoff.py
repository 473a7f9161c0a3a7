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

from .altitude import AffineLike, Surface, _inverse
from .coverage import Point2

__all__ = ["Takeoff", "TakeoffParams", "check_home", "choose_takeoff", "disc_filter", "ground_height_at", "open_ground"]


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
    radius = params.clear_radius_m / _pixel_m(transform)
    has_ground = np.isfinite(ground)
    top = disc_filter(np.where(np.isfinite(dsm), dsm, np.inf), radius, maximum=True, mode="constant", cval=np.inf)
    clear = top <= np.where(has_ground, ground, -np.inf) + params.obstacle_m
    high = disc_filter(np.where(has_ground, ground, -np.inf), radius, maximum=True, mode="nearest")
    low = disc_filter(np.where(has_ground, ground, np.inf), radius, maximum=False, mode="nearest")
    level = (high - low) <= 2.0 * params.clear_radius_m * math.tan(math.radians(params.max_slope_deg))
    dry = np.ones_like(has_ground)
    if water is not None:
        wet = (water > 0).astype(np.uint8)
        dry = disc_filter(wet, radius, maximum=True, mode="constant", cval=0) == 0
    return has_ground & clear & level & dry


def disc_filter(values: np.ndarray, radius_px: float, *, maximum: bool, mode: str, cval: float = 0.0) -> np.ndarray:
    """The largest (``maximum``) or smallest value within a disc of ``radius_px`` around each pixel.

    The same as ``scipy.ndimage.maximum_filter`` (``minimum_filter``) with the disc as footprint
    (``mode`` and ``cval`` as there), made row by row: a disc is a stack of runs, one per row,
    so a one-dimensional filter per run's width and a shift per row give it in ``2 r + 1``
    passes of a running extreme instead of the disc's ``pi r^2`` pixels per pixel (21 passes
    against 317 pixels for a 10 m radius at 1 m).
    """
    r = max(0, int(math.floor(radius_px)))
    along_row = ndi.maximum_filter1d if maximum else ndi.minimum_filter1d
    extreme = np.maximum if maximum else np.minimum
    rows = values.shape[0]
    runs: dict[int, np.ndarray] = {}
    out = None
    for dy in range(-r, r + 1):
        half = int(math.floor(math.sqrt(max(radius_px * radius_px + 1e-9 - dy * dy, 0.0))))  # dx^2 + dy^2 <= r^2
        if half not in runs:
            runs[half] = along_row(values, size=2 * half + 1, axis=1, mode=mode, cval=cval)
        run = runs[half]
        if mode == "nearest":
            shifted = run[np.clip(np.arange(rows) + dy, 0, rows - 1)]
        else:  # rows beyond the edge hold cval
            shifted = np.full(values.shape, cval, values.dtype)
            shifted[max(0, -dy) : min(rows, rows - dy)] = run[max(0, dy) : min(rows, rows + dy)]
        out = shifted if out is None else extreme(out, shifted, out=out)
    assert out is not None
    return out


def ground_height_at(ground: Surface, transform: AffineLike, point: Point2, *, search_m: float) -> float:
    """Ground height at a point: its pixel's, else the median of the ground pixels within ``search_m``; NaN if none."""
    r, c = _pixel_of(transform, point)
    if 0 <= r < ground.shape[0] and 0 <= c < ground.shape[1] and np.isfinite(ground[r, c]):
        return float(ground[r, c])
    reach = max(1, math.ceil(search_m / _pixel_m(transform)))
    window = ground[max(0, r - reach) : max(0, r + reach + 1), max(0, c - reach) : max(0, c + reach + 1)]
    values = window[np.isfinite(window)]
    return float(np.median(values)) if values.size else math.nan


def choose_takeoff(
    dsm: np.ndarray | Surface,
    ground: np.ndarray | Surface,
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

    The search reaches out step by step (:func:`_search_reaches`), and the filters of
    :func:`open_ground` run only on the blocks holding pixels within reach (:class:`_BlockedOpenGround`,
    each with the clear radius around it, so that they see there what they would over the whole
    grid); the first reach holding open ground gives the same pixel as one search over the whole
    grid (every pixel beyond is farther), at the cost of the blocks along the holes (a missed line
    across the 42 M bench survey: 0.94 -> 0.2 s).
    """
    if distance is None or centre is None:
        if not targets.any():
            return None
        rows, cols = np.nonzero(targets)
        distance, centre = ndi.distance_transform_edt(~targets), (float(rows.mean()), float(cols.mean()))
    rows_n, cols_n = dsm.shape
    # whole pixels: exact in float32, half the memory (and no second copy of a float32 window's)
    rank = np.round(distance).astype(np.float32, copy=False)
    # ties go to the pixel nearest the centre, scaled by the largest such distance (a corner's)
    corners = np.hypot(np.array([0, rows_n - 1])[:, None] - centre[0], np.array([0, cols_n - 1])[None, :] - centre[1])
    tie_scale = 1 + corners.max()
    blocks = _BlockedOpenGround(dsm, ground, water, transform, params)
    for reach in _search_reaches(float(rank.max()) if rank.size else 0.0):
        near = rank < reach
        if not near.any():
            continue
        fit = blocks.where(near)
        if fit.any():
            # scored where open: the first best pixel in row order, as over the whole grid
            index = np.flatnonzero(fit)
            r_all, c_all = np.divmod(index, cols_n)
            offset = np.hypot(r_all - centre[0], c_all - centre[1])
            score = rank.ravel()[index].astype(np.float64) * (1 + rows_n * cols_n) + offset / tie_scale
            best = int(index[int(np.argmin(score))])
            r, c = divmod(best, cols_n)
            t = transform
            xy = (t.a * (c + 0.5) + t.b * (r + 0.5) + t.c, t.d * (c + 0.5) + t.e * (r + 0.5) + t.f)
            return Takeoff((float(xy[0]), float(xy[1])), float(ground[r, c]), "ground points")
    return None


class _BlockedOpenGround:
    """:func:`open_ground` where asked: block by block (256 pixels a side), on the box of the asked
    pixels within each block grown by the clear radius (so that the filters see there what they
    would over the whole grid), each pixel computed once unless a later ask widens its block's box."""

    BLOCK = 256

    def __init__(
        self,
        dsm: np.ndarray | Surface,
        ground: np.ndarray | Surface,
        water: np.ndarray | None,
        transform: AffineLike,
        params: TakeoffParams,
    ) -> None:
        self.dsm, self.ground, self.water, self.transform, self.params = dsm, ground, water, transform, params
        self.margin = int(math.floor(params.clear_radius_m / _pixel_m(transform))) + 1
        self.fit = np.zeros(dsm.shape, bool)
        self.done: dict[tuple[int, int], tuple[int, int, int, int]] = {}  # block -> the box computed in it

    def where(self, wanted: np.ndarray) -> np.ndarray:
        """Open ground among the ``wanted`` pixels (False elsewhere)."""
        b, (rows, cols), m = self.BLOCK, wanted.shape, self.margin
        for r0 in range(0, rows, b):
            for c0 in range(0, cols, b):
                block = wanted[r0 : r0 + b, c0 : c0 + b]
                in_rows, in_cols = np.flatnonzero(block.any(axis=1)), np.flatnonzero(block.any(axis=0))
                if len(in_rows) == 0:
                    continue
                box = (r0 + int(in_rows[0]), c0 + int(in_cols[0]), r0 + int(in_rows[-1]) + 1, c0 + int(in_cols[-1]) + 1)
                known = self.done.get((r0, c0))
                if known is not None:
                    if known[0] <= box[0] and known[1] <= box[1] and box[2] <= known[2] and box[3] <= known[3]:
                        continue
                    box = (min(box[0], known[0]), min(box[1], known[1]), max(box[2], known[2]), max(box[3], known[3]))
                self.done[(r0, c0)] = box
                outer = (
                    slice(max(box[0] - m, 0), min(box[2] + m, rows)),
                    slice(max(box[1] - m, 0), min(box[3] + m, cols)),
                )
                water = None if self.water is None else self.water[outer]
                fit = open_ground(self.dsm[outer], self.ground[outer], water, self.transform, params=self.params)
                a0, b0 = box[0] - outer[0].start, box[1] - outer[1].start
                self.fit[box[0] : box[2], box[1] : box[3]] = fit[a0 : a0 + box[2] - box[0], b0 : b0 + box[3] - box[1]]
        return self.fit & wanted


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


def check_home(dsm: Surface, ground: Surface, transform: AffineLike, home: Point2, *, params: TakeoffParams) -> Takeoff:
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
