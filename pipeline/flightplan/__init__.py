"""Re-flight planning for holes a drone can re-scan (docs/flightplans.md).

Pure kernels: :mod:`.coverage` (boustrophedon lanes over a hole), :mod:`.rescan` (lanes
where an occlusion's ground is in sight), :mod:`.route`
(greedy order improved by 2-opt / or-opt, sorties), :mod:`.altitude` (heights
from the DSM, vertical reference checks) and :mod:`.mission` (the whole plan).
File formats live in :mod:`pipeline.io.flightplan_files`; the planning tool (holes
and DSM read, planned, files written) is :func:`pipeline.flight_planning.plan_flights`;
the kernels' parameters come from ``[flightplan]`` through
:func:`pipeline.parameters.flight_params`.
"""

from __future__ import annotations

from .altitude import corridor_profile, ellipsoid_transformer, height_at, lane_sections, max_height_along
from .coverage import CoverageParams, CoveragePattern, Lane, cluster_holes, lane_spacing, plan_pattern, swath_width
from .mission import FlightParams, FlightPlan, HoleDecision, HoleInput, Sortie, Waypoint, plan_mission
from .route import greedy_route, improve_route, pattern_ends, pattern_variants, route_length, split_sorties

__all__ = [
    "CoverageParams",
    "CoveragePattern",
    "FlightParams",
    "FlightPlan",
    "HoleDecision",
    "HoleInput",
    "Lane",
    "Sortie",
    "Waypoint",
    "cluster_holes",
    "corridor_profile",
    "ellipsoid_transformer",
    "greedy_route",
    "height_at",
    "improve_route",
    "lane_sections",
    "lane_spacing",
    "max_height_along",
    "pattern_ends",
    "pattern_variants",
    "plan_mission",
    "plan_pattern",
    "route_length",
    "split_sorties",
    "swath_width",
]
