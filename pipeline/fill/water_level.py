"""The level of water from its edge: where the water meets the land (pure; docs/filling.md, "Water").

A water hole is a surface with no returns; its height is known only where it touches
something measured. Two kinds of evidence are used, best first:

1. **Water returns** (ASPRS class 9) on or near the hole's ring: returns from the water
   itself (shallow or turbid water at the edge, wet banks, ripples). Their lowest
   return per pixel is the water surface.
2. **The ring's lowest returns**, when no water return is near: the water's edge is the
   lowest *consistent* level of the ring, the level a good share of the ring agrees on
   within the lidar's noise. What stands above it (quay walls, bridges, overhanging
   trees, bank tops) and a few stray returns below it (multipath, a return from under
   the water's edge) are outliers and left out.

:func:`edge_level` gives one level and its spread (the error of the level);
:func:`water_edge_heights` picks the evidence of each labelled hole from the rasters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.ndimage as ndi

__all__ = [
    "MIN_WATER_PX",
    "EdgeLevel",
    "edge_level",
    "lowest_consistent_level",
    "water_edge_heights",
]

#: Water-return pixels needed before they decide the level; fewer may be stray
#: misclassified points (a wet roof, a puddle), which the ring then outvotes.
MIN_WATER_PX = 3
#: Ring pixels needed for a consistent level: fewer than three cannot agree with anything.
MIN_RING_PX = 3


@dataclass(frozen=True)
class EdgeLevel:
    """The level of a water body's edge.

    Attributes
    ----------
    level : float
        The water's level (z units); NaN when there is no evidence.
    spread : float
        Standard deviation of the heights that agree on the level: the error of the level.
    count : int
        Heights that agree on it.
    source : str
        ``"water returns"``, ``"ring"`` or ``"none"``.
    """

    level: float
    spread: float
    count: int
    source: str


NO_LEVEL = EdgeLevel(math.nan, math.nan, 0, "none")


#: Quantile of the ring's agreeing heights taken as the edge: ring pixels lie up the bank by up to a
#: pixel from where the water meets it, so the edge is their lower envelope; a low quantile, not the
#: minimum, so that the lidar's noise does not pull it down.
RING_QUANTILE = 0.1


def lowest_consistent_level(
    heights: np.ndarray, *, tolerance: float, min_share: float, quantile: float = 0.5
) -> EdgeLevel:
    """The lowest level that at least ``min_share`` of ``heights`` agree on within ``tolerance``.

    The heights are sorted; the first window ``tolerance`` wide (from the lowest up)
    holding ``max(MIN_RING_PX, min_share * n)`` heights is the level's cluster, and
    the level is its ``quantile`` (the median by default). Everything below the cluster (a few stray low returns)
    and above it (walls, bridges, trees, bank tops) is left out. With no such window
    (too few heights, or none agreeing) the median of all heights is taken, with
    their whole spread.

    Parameters
    ----------
    heights : ndarray
        Candidate heights (z units), NaN ignored.
    tolerance : float
        Width of the window (z units): heights of one level agree within the lidar's noise.
    min_share : float
        Share (0-1] of the heights the level needs.
    quantile : float
        Quantile of the cluster taken as the level.
    """
    h = np.sort(np.asarray(heights, np.float64).ravel())
    h = h[np.isfinite(h)]
    if len(h) == 0:
        return NO_LEVEL
    need = max(MIN_RING_PX, math.ceil(min_share * len(h)))
    if len(h) >= need:
        ends = np.searchsorted(h, h + tolerance, side="right")
        enough = np.nonzero(ends - np.arange(len(h)) >= need)[0]
        if len(enough):
            start = int(enough[0])
            cluster = h[start : ends[start]]
            return EdgeLevel(float(np.quantile(cluster, quantile)), float(np.std(cluster)), len(cluster), "ring")
    return EdgeLevel(float(np.quantile(h, quantile)), float(np.std(h)), len(h), "ring")


def edge_level(
    ring: np.ndarray, water: np.ndarray, *, tolerance: float, min_share: float, water_share: float = 0.5
) -> EdgeLevel:
    """The water level from water returns when there are enough, else from the ring.

    Parameters
    ----------
    ring : ndarray
        The lowest return of each ring pixel (measured pixels around the hole).
    water : ndarray
        The lowest return of each pixel near the hole holding water returns.
    tolerance, min_share : float
        As in :func:`lowest_consistent_level`, for the ring.
    water_share : float
        Share of the water returns the level needs: they are all water, so a majority.
    """
    water = np.asarray(water, np.float64)
    water = water[np.isfinite(water)]
    if len(water) >= MIN_WATER_PX:
        found = lowest_consistent_level(water, tolerance=tolerance, min_share=water_share)
        return EdgeLevel(found.level, found.spread, found.count, "water returns")
    return lowest_consistent_level(ring, tolerance=tolerance, min_share=min_share, quantile=RING_QUANTILE)


def water_edge_heights(
    zmin: np.ndarray, water_points: np.ndarray, labels: np.ndarray, *, reach_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """The evidence of each labelled water hole: its ring's lowest returns and its water returns near it.

    Parameters
    ----------
    zmin : ndarray (M, N)
        Lowest return per pixel, NaN where nothing was measured.
    water_points : ndarray (M, N)
        Water-class returns per pixel (0 where none, or where unknown).
    labels : ndarray of int (M, N)
        One label > 0 per water hole.
    reach_px : float
        How far from the hole (pixels) a water return still belongs to it.

    Returns
    -------
    ring_label : ndarray of int (M, N)
        The label of the hole each measured pixel 4-adjacent to a hole is on the ring of
        (the larger label where two holes share a ring pixel), 0 elsewhere.
    water_label : ndarray of int (M, N)
        The label of the nearest hole for measured pixels holding water returns within
        ``reach_px`` of it, 0 elsewhere.
    """
    labels = np.asarray(labels)
    measured = np.isfinite(zmin)
    cross = ndi.generate_binary_structure(2, 1)
    ring_label = np.where(measured, ndi.grey_dilation(np.maximum(labels, 0), footprint=cross), 0)
    distance, (rows, cols) = ndi.distance_transform_edt(labels <= 0, return_indices=True)
    near = measured & (np.asarray(water_points) > 0) & (distance <= reach_px) & (labels <= 0)
    water_label = np.where(near, labels[rows, cols], 0)
    return ring_label, water_label
