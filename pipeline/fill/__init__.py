"""Hole-fill kernels: pure array-in / array-out functions (no I/O, no Dask).

References (files under ``shared/seeds``):

* [MLS] "Hole repair algorithm based on improved moving least squares"
  (``improved-mls-hole-repair.txt``);
* [OPEN] "A parallel method for open hole filling in large-scale 3D automatic
  modeling" (``parallel-open-hole-filling.txt``), sections 3.3-3.4.

See docs/filling.md for the methods, the ``auto`` rule and measured figures.
"""

from .causes import clamp_to_rim, lower_side_support, rim_level
from .hydro import RiverFit, river_surfaces
from .provenance import fill_distance, leave_boundary_out_error
from .region import FILL_METHODS, choose_methods, fill_region
from .seams import smooth_seams
from .settings import (
    METHOD_CODES,
    METHOD_NAMES,
    NOT_FILLED,
    UNTOUCHED,
    ComponentFill,
    FillOutcome,
    FillSettings,
)

__all__ = [
    "FILL_METHODS",
    "METHOD_CODES",
    "METHOD_NAMES",
    "NOT_FILLED",
    "RiverFit",
    "UNTOUCHED",
    "ComponentFill",
    "FillOutcome",
    "FillSettings",
    "choose_methods",
    "clamp_to_rim",
    "fill_distance",
    "fill_region",
    "leave_boundary_out_error",
    "lower_side_support",
    "rim_level",
    "river_surfaces",
    "smooth_seams",
]
