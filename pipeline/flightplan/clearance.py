"""Clearance of every leg above the highest surface near it, and flight time with turns.

A leg is the straight segment between two waypoints (take-off to landing, transit,
lanes and turns alike). Its clearance is the least height of the aircraft above any
DSM pixel whose centre lies within ``radius_m`` (plus half a pixel diagonal) of the leg,
taking, for each pixel, the lowest height the aircraft has anywhere within ``radius_m``
of the pixel's along-track position (conservative on climbing legs).

``radius_m`` is the horizontal uncertainty of the aircraft's path: GNSS position
error and path-tracking error in wind, about 1.5 m each without RTK; the default
(3 m) covers both. The minimum clearance (20 m by default) covers the barometric
height drift of a sortie (a few metres), the DSM's own error, obstacles the DSM misses
(wires, cranes put up since the survey), and the lidar's minimum range.

Flight time: each leg at its speed, plus, at every waypoint, the time to change the
velocity vector by ``|v_out - v_in|`` at ``acceleration_m_s2`` (a turn, a climb, a speed
change, the start from and the stop at home); conservative for turns flown with
continuous curvature.

Pure functions on numpy arrays.
"""

from __future__ import annotations

import math

import numpy as np

from .altitude import AffineLike, Surface, pixels_near_segment
from .coverage import Point2

__all__ = ["flight_time_s", "leg_clearance"]


def leg_clearance(
    dsm: Surface,
    transform: AffineLike,
    start: Point2,
    end: Point2,
    heights: tuple[float, float],
    *,
    radius_m: float,
) -> float:
    """Least height of a straight leg above the DSM within ``radius_m``; +inf where no pixel has data.

    ``heights`` are the leg's ends in the DSM's datum.
    """
    length = math.dist(start, end)
    least = math.inf
    for values, along in pixels_near_segment(dsm, transform, start, end, radius_m):
        fraction = np.clip(np.stack([along - radius_m, along + radius_m]) / (length or 1.0), 0.0, 1.0)
        lowest = (heights[0] + (heights[1] - heights[0]) * fraction).min(axis=0)
        least = min(least, float((lowest - values).min()))
    return least


def flight_time_s(xyz: np.ndarray, speeds: np.ndarray, *, acceleration_m_s2: float) -> float:
    """Seconds to fly a polyline from rest to rest.

    Parameters
    ----------
    xyz : ndarray of shape (K, 3)
        Waypoints in metres.
    speeds : ndarray of shape (K - 1,)
        Ground speed of each leg (m/s).
    """
    legs = np.diff(xyz, axis=0)
    lengths = np.linalg.norm(legs, axis=1)
    if lengths.size == 0:
        return 0.0
    velocity = np.where(lengths[:, None] > 0, legs / np.maximum(lengths, 1e-9)[:, None], 0.0) * speeds[:, None]
    padded = np.vstack([np.zeros(3), velocity, np.zeros(3)])
    changes = np.linalg.norm(np.diff(padded, axis=0), axis=1).sum()
    return float((lengths / speeds).sum() + changes / acceleration_m_s2)
