"""Hole-fill kernels: pure array-in / array-out functions (no I/O, no Dask).

References (files under ``shared/seeds``):

* [MLS] "Hole repair algorithm based on improved moving least squares"
  (``improved-mls-hole-repair.txt``);
* [OPEN] "A parallel method for open hole filling in large-scale 3D automatic
  modeling" (``parallel-open-hole-filling.txt``), sections 3.3-3.4.

See docs/filling.md for the methods, the ``auto`` rule and measured figures. How a hole
is filled by its cause (water, occlusion, the rest) is :mod:`.by_cause`.
"""

from .by_cause import (
    FILLED,
    MISSED,
    NO_SUPPORT,
    TOO_LARGE,
    UNFILLED,
    FillParams,
    HoleFill,
    fill_hole,
    fill_kind,
    fill_water,
    hole_ids_of_labels,
    hole_record,
)
from .causes import clamp_to_rim, lower_side_support, rim_level
from .hydro import RiverFit, WaterEdge, river_surfaces
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
    "FILLED",
    "MISSED",
    "FILL_METHODS",
    "METHOD_CODES",
    "METHOD_NAMES",
    "NOT_FILLED",
    "NO_SUPPORT",
    "RiverFit",
    "TOO_LARGE",
    "UNFILLED",
    "UNTOUCHED",
    "ComponentFill",
    "FillOutcome",
    "FillParams",
    "FillSettings",
    "HoleFill",
    "choose_methods",
    "clamp_to_rim",
    "fill_distance",
    "fill_hole",
    "fill_kind",
    "fill_region",
    "fill_water",
    "hole_ids_of_labels",
    "hole_record",
    "leave_boundary_out_error",
    "lower_side_support",
    "rim_level",
    "river_surfaces",
    "WaterEdge",
    "smooth_seams",
]
