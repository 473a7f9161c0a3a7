"""Whether a survey's heights are elevations or heights above the ground ("normalised").

Some deliveries store each point's height above the ground instead of its elevation
(forest inventories; lidR's ``Megaplot.laz``; ``williams_az_urban_norm``): the ground
is z = 0 everywhere and the DSM is a height-above-ground model. A run recognises
them from the ground-class points (ASPRS 2) it bins anyway: in a normalised survey
nearly all of them lie at z = 0, in a survey of elevations almost none do, even at
sea level (AHN3 Delft: 0.35 ± 0.28 m; the Corsican coast: 17 ± 12 m). Stage 1 counts
them per read task (:func:`count_ground_at_zero`); the counts add up over the survey.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Why a survey of heights above the ground gets no re-flight plan: a drone's safe height
#: follows the terrain, and these heights have taken the terrain out.
NO_TERRAIN = (
    "heights are above the ground, so the terrain is unknown and no safe flying height can be "
    "planned; plan from a survey of elevations"
)
#: ASPRS class of ground points.
GROUND_CLASS = 2
#: A ground point within this of z = 0 (in the survey's z units) lies at zero.
AT_ZERO_TOLERANCE = 0.1
#: Normalised: at least this share of the ground points lies at zero ...
MIN_SHARE_AT_ZERO = 0.9
#: ... out of at least this many ground points (fewer say nothing).
MIN_GROUND_POINTS = 100


@dataclass(frozen=True)
class GroundLevel:
    """Ground-class points binned, and those at z = 0; adds up over tiles."""

    points: int = 0
    at_zero: int = 0

    def __add__(self, other: GroundLevel) -> GroundLevel:
        return GroundLevel(self.points + other.points, self.at_zero + other.at_zero)

    @property
    def normalised(self) -> bool:
        """Whether the heights are normalised to the ground (z = height above ground)."""
        return self.points >= MIN_GROUND_POINTS and self.at_zero >= MIN_SHARE_AT_ZERO * self.points

    def as_record(self) -> dict[str, object]:
        """The manifest's ``survey.heights`` entry."""
        return {
            "heights": "above_ground" if self.normalised else "elevation",
            "ground_points": self.points,
            "ground_points_at_zero": self.at_zero,
        }


def count_ground_at_zero(
    z: np.ndarray, is_ground: np.ndarray, *, scale: float = 1.0, offset: float = 0.0
) -> GroundLevel:
    """Count the ground points and those within ``AT_ZERO_TOLERANCE`` of z = 0.

    Parameters
    ----------
    z : ndarray, shape (P,)
        Heights ``z * scale + offset`` in the survey's z units: a LAS file's raw
        integers with its scale and offset (compared as integers, so stage 1 pays
        about a nanosecond a point), or heights with the defaults.
    is_ground : ndarray of bool, shape (P,)
        Ground-class points the run keeps.
    """
    low = (-AT_ZERO_TOLERANCE - offset) / scale
    high = (AT_ZERO_TOLERANCE - offset) / scale
    if np.issubdtype(z.dtype, np.integer):  # the integers in [low, high], clipped to the dtype's range
        info = np.iinfo(z.dtype)
        low, high = max(math.ceil(low), info.min), min(math.floor(high), info.max)
    at_zero = is_ground & (z >= low) & (z <= high)
    return GroundLevel(points=int(np.count_nonzero(is_ground)), at_zero=int(np.count_nonzero(at_zero)))
