"""Helpers that turn a hole's cause into fill inputs (pure array functions).

* occlusion next to a building: :func:`lower_side_support`, so the hole is filled from
  the ground and not ramped up to the roof;
* water: :func:`rim_level`, the level for a ``flat`` (hydro-flattened) fill.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi

from ..quantiles import linear_quantiles
from ._problem import CROSS, fit_plane

__all__ = ["clamp_to_rim", "lower_side_support", "rim_level"]


def _components(region: np.ndarray, labels: np.ndarray | None) -> tuple[np.ndarray, int]:
    region = np.asarray(region, bool)
    if labels is None:
        lab, n = ndi.label(region, structure=CROSS)
        return lab, int(n)
    lab = np.where(region, np.asarray(labels), 0)
    return lab, int(lab.max(initial=0))


def _rim_pairs(heights: np.ndarray, lab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique (label, flat index) of finite non-region pixels 4-adjacent to a component."""
    h, w = heights.shape
    rows, cols = np.nonzero(lab)
    pairs_l, pairs_i = [], []
    finite_out = np.isfinite(heights) & (lab == 0)
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        r, c = rows + dr, cols + dc
        ok = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        r, c, ll = r[ok], c[ok], lab[rows[ok], cols[ok]]
        good = finite_out[r, c]
        pairs_l.append(ll[good])
        pairs_i.append(r[good] * w + c[good])
    key = np.unique(np.concatenate(pairs_l).astype(np.int64) * (h * w) + np.concatenate(pairs_i))
    return key // (h * w), key % (h * w)


def lower_side_support(
    heights: np.ndarray,
    region: np.ndarray,
    *,
    jump_threshold: float,
    quantile: float = 0.1,
    labels: np.ndarray | None = None,
) -> np.ndarray:
    """Rim pixels on the low side of a height step: the support for an occlusion hole.

    For each component of ``region`` the low rim level is the ``quantile`` of its rim
    heights (rim = finite pixels 4-adjacent to it; a low quantile rather than the
    minimum, so that one stray low point does not exclude the ground); rim pixels
    higher than that level plus ``jump_threshold`` (roof, wall top) are dropped, unless
    the rim lies on a slope, not at a step (:func:`_slope_not_step`): then all of it is kept.

    Parameters
    ----------
    heights : ndarray of shape (M, N)
        Heights, NaN = unknown.
    region : ndarray of bool, shape (M, N)
        Pixels to fill.
    jump_threshold : float
        Height step (z units) separating ground from roof; use the one that found the
        walls (``holes.height_jumps``).
    quantile : float
        Quantile of the rim heights taken as the low level. Default 0.1.
    labels : ndarray of int, optional
        Component labels (default: 4-connected components of ``region``).

    Returns
    -------
    ndarray of bool, shape (M, N)
        True on the low-side rim pixels; pass it as ``support`` to :func:`fill_region`.
    """
    heights = np.asarray(heights, np.float64)
    if not jump_threshold > 0:
        raise ValueError(f"`jump_threshold` must be > 0, got {jump_threshold!r}")
    if not 0 <= quantile <= 1:
        raise ValueError(f"`quantile` must be in [0, 1], got {quantile!r}")
    lab, n = _components(region, labels)
    out = np.zeros(heights.shape, bool)
    if n == 0:
        return out
    pl, pi = _rim_pairs(heights, lab)
    z = heights.ravel()[pi]
    low = np.full(n + 1, np.nan)
    bounds = np.searchsorted(pl, np.arange(n + 2))
    for k in np.unique(pl):
        (low[k],) = linear_quantiles(z[bounds[k] : bounds[k + 1]], (quantile,))
    keep = z <= low[pl] + jump_threshold
    stepped = np.unique(pl[~keep])
    boxes = ndi.find_objects(lab) if len(stepped) else []
    for k in stepped:  # a rim spanning more than a step: a wall, or a slope?
        rim = pi[bounds[k] : bounds[k + 1]]
        if _slope_not_step(heights, lab, int(k), boxes[k - 1], rim):
            keep[bounds[k] : bounds[k + 1]] = True
    out.ravel()[pi[keep]] = True
    # a pixel judged high for any neighbouring hole is not support
    out.ravel()[pi[~keep]] = False
    return out


#: How far beyond a hole's rim (pixels) the surface is checked against the rim's plane.
SLOPE_CHECK_PX = 4
#: A rim is a slope where the surface up to ``SLOPE_CHECK_PX`` beyond it departs from the rim's
#: plane by at most this share of the rim's height range (RMS).
SLOPE_MAX_DEPARTURE = 0.25


def _slope_not_step(
    heights: np.ndarray, labels: np.ndarray, label: int, box: tuple[slice, slice], rim: np.ndarray
) -> bool:
    """Whether a hole's rim, spanning more than a height step, lies on a slope rather than at a step.

    Beside a wall the rim holds two levels, ground and roof: a plane through them tilts across
    the wall, and beyond the rim the surface stays flat (the roof, the street) while the plane
    runs on, up and down (a 6 px shadow beside a 12 m wall: 5 m off 3 px out). On a hillside
    the rim's plane is the hill's, and the ground beyond the rim follows it to within its
    roughness (``pdal_alirt_afghan``: a 18 m cut void on a 48 degree mountainside, the rim 2.2 m
    about its plane). The plane is fitted to the rim's pixels (``rim``: flat indices) and
    checked on the measured pixels 2 to ``SLOPE_CHECK_PX`` pixels from the hole (``label`` of
    ``labels``, within ``box``): only the hole's own surroundings, whichever other holes the
    window holds.
    """
    h, w = heights.shape
    rows, cols = np.divmod(rim, w)
    z = heights.ravel()[rim]
    if len(z) < 4:
        return False
    low, high = linear_quantiles(z, (0.1, 0.9))
    rim_range = float(high - low)
    r0, r1 = max(box[0].start - SLOPE_CHECK_PX, 0), min(box[0].stop + SLOPE_CHECK_PX, h)
    c0, c1 = max(box[1].start - SLOPE_CHECK_PX, 0), min(box[1].stop + SLOPE_CHECK_PX, w)
    # pixels 2 to SLOPE_CHECK_PX from the hole (chessboard distance), measured
    steps = ndi.distance_transform_cdt(labels[r0:r1, c0:c1] != label, metric="chessboard")
    around = (steps >= 2) & (steps <= SLOPE_CHECK_PX) & np.isfinite(heights[r0:r1, c0:c1])
    if not around.any() or not rim_range > 0:
        return False
    plane = fit_plane(rows - r0, cols - c0, z)
    ar, ac = np.nonzero(around)
    predicted = plane[0] + plane[1] * ac + plane[2] * ar
    departure = heights[r0:r1, c0:c1][ar, ac] - predicted
    return bool(np.sqrt(np.mean(departure**2)) <= SLOPE_MAX_DEPARTURE * rim_range)


def rim_level(
    heights: np.ndarray,
    region: np.ndarray,
    *,
    percentile: float = 10.0,
    labels: np.ndarray | None = None,
) -> np.ndarray:
    """Water level of each component: a low percentile of its rim heights.

    Shore pixels carry vegetation, walls and bridges but nothing below the water, so a
    low percentile (default the 10th) is the level of the water's edge, robust to a few
    stray low returns.

    Returns
    -------
    ndarray of float64, shape (n_components + 1,)
        Level per label (index 0 and rimless components: NaN).
    """
    heights = np.asarray(heights, np.float64)
    if not 0 <= percentile <= 100:
        raise ValueError(f"`percentile` must be in [0, 100], got {percentile!r}")
    lab, n = _components(region, labels)
    levels = np.full(n + 1, np.nan)
    if n == 0:
        return levels
    pl, pi = _rim_pairs(heights, lab)
    z = heights.ravel()[pi]
    bounds = np.searchsorted(pl, np.arange(n + 2))
    for k in np.unique(pl):
        (levels[k],) = linear_quantiles(z[bounds[k] : bounds[k + 1]], (percentile / 100,))
    return levels


def clamp_to_rim(
    filled: np.ndarray,
    heights: np.ndarray,
    region: np.ndarray,
    *,
    support: np.ndarray | None = None,
    labels: np.ndarray | None = None,
) -> np.ndarray:
    """Keep every filled height within the range of its component's rim (pure).

    A smooth surface fitted to a rim with steps (a roof edge, the flank of a crown)
    carries the rim's slopes into the hole and overshoots above the highest or below
    the lowest rim height; a void in a surface has no reason to leave that range.
    The rim is the finite pixels 4-adjacent to a component, limited to ``support``
    when given (the low side of an occlusion).
    """
    out = np.array(filled, dtype=np.float64, copy=True)
    lab, n = _components(region, labels)
    if n == 0:
        return out
    rim_heights = np.where(support, heights, np.nan) if support is not None else heights
    rim_l, rim_i = _rim_pairs(rim_heights, lab)
    if len(rim_l) == 0:
        return out
    values = rim_heights.ravel()[rim_i]
    low = np.full(n + 1, np.inf)
    high = np.full(n + 1, -np.inf)
    np.minimum.at(low, rim_l, values)
    np.maximum.at(high, rim_l, values)
    has_rim = np.isfinite(low) & np.isfinite(high)
    low = np.where(has_rim, low, -np.inf)
    high = np.where(has_rim, high, np.inf)
    inside = lab > 0
    out[inside] = np.clip(out[inside], low[lab[inside]], high[lab[inside]])
    return out
