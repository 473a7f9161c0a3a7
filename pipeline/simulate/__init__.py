"""Airborne lidar scans simulated over real terrain, with the truth of every hole's cause.

The cause rules of :mod:`pipeline.holes` reason about the sensor's geometry (flight lines,
swaths, lines of sight). This package tests them on scans that arise the way real ones
do, over real surfaces, independently of :mod:`pipeline.synth`'s box scenes:

``terrain``
    :class:`Terrain`: first surface, ground, surface kind (ground, building, vegetation,
    water, other) on one lattice, from a real point cloud (:func:`terrain_from_points`);
    :func:`mirror_terrain` makes a larger scene of a small file.
``sources``
    :data:`TERRAINS` (real files of ``../shared/data``) and :func:`load_terrain`.
``params``
    :class:`FlightLine`, :class:`ScanParams`; :func:`random_scan_params` draws a survey
    from a seed (heading, lines, ids, order, a dropped line, a crossing line, density...).
``_kernels``
    numba: pulses of a line cast through the surface, and what each line sees.
``truth``
    Why an empty pixel is empty: :func:`truth_causes` on any pixel lattice.
``scan``
    :func:`simulate_scan` (LAZ tiles + truth), :func:`write_truth`.

See docs/simulate.md.
"""

from __future__ import annotations

from .params import FlightLine, ScanParams, plan_lines, random_scan_params, swath_width_m
from .scan import ScanResult, simulate_scan, write_truth
from .sources import TERRAINS, TerrainSource, load_terrain
from .terrain import Surface, Terrain, mirror_terrain, terrain_from_points
from .truth import cell_causes, truth_causes

__all__ = [
    "TERRAINS",
    "FlightLine",
    "ScanParams",
    "ScanResult",
    "Surface",
    "Terrain",
    "TerrainSource",
    "cell_causes",
    "load_terrain",
    "mirror_terrain",
    "plan_lines",
    "random_scan_params",
    "simulate_scan",
    "swath_width_m",
    "terrain_from_points",
    "truth_causes",
    "write_truth",
]
