"""Holes: detection per cell, linking across cells, causes, walls and outlines.

A *hole* is a connected set of empty pixels (no point, ``count == 0``) inside the
area of interest (AOI). Everything here is a pure array kernel: arrays and
:mod:`pipeline.grid` geometry in, arrays, shapely geometries and frozen
dataclasses out; no I/O, no Dask, no configuration objects (:class:`CauseRules`
is built from the configuration by the caller). The per-cell functions see one
cell (its core plus halo) at a time; the cross-cell functions see only the small
per-cell results, never a survey-sized array. See ``docs/holes.md``.

Modules, in the order of the data flow (each imports only earlier ones):

``_kernels``
    the numba passes over hole and ring pixels, sparse-table helpers
``masks``
    full-raster masks: :func:`hole_mask`, :func:`height_jumps` ([UAS] eq. 1),
    :func:`vertical_holes` ([UAS] eq. 2)
``stats``
    the mergeable statistics (:class:`HoleStats`), :func:`merge_hole_stats`,
    :func:`shape_metrics`, :func:`ring_metrics`
``detect``
    per cell: :func:`detect_cell_holes` -> :class:`CellHoles`
``link``
    on the client: :func:`link_holes` -> :class:`HoleCatalog`; :func:`mark_sampling_gaps`
``causes``
    :func:`classify_causes` with :class:`CauseRules`
``walls``
    wall segments and S-curve fits ([WALL])
``outlines``
    exact, simplified and straight hole polygons ([STRAIGHT])
``vertical``
    :func:`vertical_hole_records`: the ``vertical_holes`` layer's rows from the eq. 2 mask

Beside the flow: ``flight_lines`` (each flight line's direction from its pixels, the
direction of a missed strip's re-flight: :func:`~.flight_lines.strip_azimuths`) and
``coverage`` (the flight lines' swaths and the gaps between them).

Sources (``DESIGN.md`` seeds)
-----------------------------
[UAS]
    Fiolka, Rouatbi, Bender, "Automated detection and closing of holes in aerial
    point clouds using an UAS": height map (section 3.1), height jumps (eq. 1),
    vertical holes (eq. 2), inner boundaries in 4-connectivity and the count of
    height jumps around each hole (section 3.2, "Detection of inner boundaries").
[OPEN]
    Wang, Liu, Zhu, Wu, "A parallel method for open hole filling in large-scale
    3D automatic modeling based on oblique photography", Remote Sens. 2021, 13,
    3512: closed/open holes per cell, types I/II and shapes A-D (section 3.1),
    hierarchy of open holes, layers outer-to-inner (section 3.2).

Pipeline contract
-----------------
1. Per cell (a Dask task): :func:`detect_cell_holes` on the cell's halo arrays
   -> :class:`CellHoles` (call :meth:`CellHoles.without_labels` before sending
   it to the client).
2. On the client: :func:`link_holes` on every cell's result -> :class:`HoleCatalog`
   (global hole ids, layers, merged statistics), then :func:`classify_causes`
   on ``catalog.stats``.
3. Per cell again (fill): ``catalog.hole_id_lookup(cell_id)[labels]`` turns the
   cell's part labels into global hole ids.
"""

from __future__ import annotations

from .causes import CAUSE_DTYPE, CAUSES, CauseRules, classify_causes, strip_joins
from .detect import PART_DTYPE, SIDE_BITS, SIDES, CellEvidence, CellHoles, DetectParams, EdgeStrip, detect_cell_holes
from .link import HoleCatalog, PartRecord, link_holes, mark_sampling_gaps, number_listed_first
from .masks import height_jumps, hole_mask, vertical_holes
from .stats import STATS_COLUMNS, HoleStats, merge_hole_stats, ring_metrics, shape_metrics

__all__ = [
    "CAUSES",
    "CAUSE_DTYPE",
    "PART_DTYPE",
    "SIDES",
    "SIDE_BITS",
    "STATS_COLUMNS",
    "CauseRules",
    "CellEvidence",
    "CellHoles",
    "DetectParams",
    "EdgeStrip",
    "HoleCatalog",
    "HoleStats",
    "PartRecord",
    "classify_causes",
    "detect_cell_holes",
    "height_jumps",
    "hole_mask",
    "link_holes",
    "mark_sampling_gaps",
    "number_listed_first",
    "merge_hole_stats",
    "ring_metrics",
    "shape_metrics",
    "strip_joins",
    "vertical_holes",
]
