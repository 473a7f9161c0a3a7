"""The configuration turned into typed parameter records for each stage: the one place that does it.

``config`` validates the TOML (every range and every rule across keys, at load time);
this module turns the validated :class:`~pipeline.config.Config` into the small frozen
records the kernels and stages take, in the survey's units, once. No kernel imports
``config``: a kernel's parameters are its own record (``FillParams`` in
:mod:`pipeline.fill`, ``CauseRules`` in :mod:`pipeline.holes.causes`, ``FlightParams``
in :mod:`pipeline.flightplan`, ``RasterOptions`` in :mod:`pipeline.io.raster`,
``PointFilter`` in :mod:`pipeline.rasterize`), built here from configuration, or by
hand in a test.

=========================  ===================  ==============================================
adapter                    record               sections
=========================  ===================  ==============================================
:func:`read_params`        :class:`ReadParams`  ``[read]``, ``[filter]``, ``[rasterize]`` (stage 1)
:func:`hole_params`        :class:`HoleParams`  ``[holes]``, ``[rasterize]`` (the plan, detection)
:func:`cause_rules`        ``CauseRules``       ``[causes]``, ``holes.jump_threshold_m`` (linking)
:func:`fill_params`        ``FillParams``       ``[fill]`` (fill and writer stages)
:func:`raster_options`     ``RasterOptions``    ``[output]`` (the COG writer)
:func:`flight_params`      ``FlightParams``     ``[flightplan]`` (flight planning)
=========================  ===================  ==============================================

The adapters take the plan's numbers (pixel size, units) as arguments, not the plan:
the plan itself is built with :func:`hole_params`, so this module imports nothing that
runs after ``config``'s consumers. The plan imports this module, and stage 1's workers
import the plan: the records of the later stages (fill, rasters, flight plans) are
imported inside their adapters, so a worker does not load those packages to bin points.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from .config import AUTO, CausesConfig, Config
from .holes.causes import CauseRules
from .io import pdal_reader
from .rasterize import PointFilter
from .survey.density import auto_min_area_m2, sampling_gap_width_m

if TYPE_CHECKING:
    from .fill.by_cause import FillParams
    from .flightplan import FlightParams
    from .io.raster import RasterOptions

__all__ = [
    "CONFIG_KEYS",
    "HoleParams",
    "ReadParams",
    "cause_rules",
    "default_cause_rules",
    "fill_params",
    "flight_params",
    "hole_params",
    "raster_options",
    "read_params",
]


@dataclass(frozen=True)
class ReadParams:
    """How stage 1 reads and bins points (``[read]``, ``[filter]``, ``[rasterize]``), heights in z units."""

    point_filter: PointFilter
    voxel_height: float  # z units
    chunk_points: int
    sensor: bool  # decode the pulses' fields and sum them for the flight lines' trajectories
    ground: bool  # sum the ground points' heights per pixel: the take-off height of flight plans
    pdal: bool = False  # read through PDAL (read.reader = "pdal"), else laspy
    pdal_pipeline: pdal_reader.UserPipeline | None = None  # the user's filter stages, checked


@dataclass(frozen=True)
class HoleParams:
    """Hole-stage parameters in survey units (from ``[holes]``), computed once for every stage."""

    jump_threshold: float  # z units
    voxel_height: float  # z units
    connectivity: int
    min_area_px: int
    vertical_min_px: int
    wall_min_length_px: float
    min_area_m2: float = 4.0  # holes.min_area_m2, "auto" resolved
    sampling_gap_px: float = 0.0  # holes no thicker than this (pixels) are sampling gaps; 0: none


def point_filter(config: Config) -> PointFilter:
    """Which points enter the rasters, from ``[filter]``."""
    f = config.filter
    return PointFilter(tuple(f.drop_classes), tuple(f.keep_classes), f.drop_withheld)


def read_params(config: Config, *, vertical_unit_m: float) -> ReadParams:
    """Stage 1's parameters; with ``read.reader = "pdal"`` the user's pipeline file is read and checked here."""
    pdal = config.read.reader == "pdal"
    return ReadParams(
        point_filter=point_filter(config),
        voxel_height=config.rasterize.voxel_height_m / vertical_unit_m,
        chunk_points=config.rasterize.chunk_points,
        sensor=config.holes.enabled and config.sensor.enabled,
        # summed while the points are decoded anyway, the planner need not decode the files near the
        # take-off again (1.4 s of a 42 M-point run's client, 4.9 s at 211 M: the run's serial tail);
        # kept wherever holes are sought, so that turning flight plans on or off in an incremental
        # run does not decode every tile again
        ground=config.holes.enabled,
        pdal=pdal,
        pdal_pipeline=_user_pipeline(config) if pdal else None,
    )


def _user_pipeline(config: Config) -> pdal_reader.UserPipeline | None:
    """The checked ``read.pdal_pipeline`` (without one, python-pdal is checked)."""
    if not config.read.pdal_pipeline:
        pdal_reader.import_pdal()
        return None
    return pdal_reader.load_user_pipeline(config.read.pdal_pipeline, streaming=config.read.pdal_streaming)


def hole_params(config: Config, *, pixel_size_m: float, spacing_m: float, vertical_unit_m: float) -> HoleParams:
    """The ``[holes]`` settings in the survey's units, "auto" resolved: computed once, in the plan.

    ``spacing_m`` is the survey's nominal point spacing. With ``holes.min_area_m2 =
    "auto"`` it sets the smallest listed area and the width under which a void is a
    sampling gap (:mod:`pipeline.survey.density`); a number set there is the only rule, as
    it always was (synthetic surveys whose truth counts every one-pixel sliver).
    """
    holes = config.holes
    pixel_area_m2 = pixel_size_m**2
    auto = holes.min_area_m2 == AUTO
    min_area_m2 = auto_min_area_m2(spacing_m) if auto else float(holes.min_area_m2)
    gap_m = sampling_gap_width_m(spacing_m) if auto and math.isfinite(spacing_m) else 0.0
    return HoleParams(
        jump_threshold=holes.jump_threshold_m / vertical_unit_m,
        voxel_height=config.rasterize.voxel_height_m / vertical_unit_m,
        connectivity=holes.connectivity,
        min_area_px=math.ceil(min_area_m2 / pixel_area_m2),
        vertical_min_px=math.ceil(holes.vertical_min_area_m2 / pixel_area_m2),
        wall_min_length_px=holes.wall_min_length_m / pixel_size_m,
        min_area_m2=min_area_m2,
        sampling_gap_px=gap_m / pixel_size_m,
    )


def cause_rules(config: Config, *, pixel_size_m: float, vertical_unit_m: float) -> CauseRules:
    """The cause rules of a run, in the survey's units.

    Parameters
    ----------
    config : Config
        The ``[causes]`` thresholds and ``holes.jump_threshold_m``.
    pixel_size_m : float
        The grid's pixel side in metres (``grid.resolution`` times the CRS's horizontal unit).
    vertical_unit_m : float
        Metres per z unit.
    """
    return CauseRules(
        pixel_size=pixel_size_m / vertical_unit_m,
        jump_threshold=config.holes.jump_threshold_m / vertical_unit_m,
        pixel_area_m2=pixel_size_m**2,
        **_thresholds(config.causes),
    )


def default_cause_rules(*, pixel_size: float, jump_threshold: float, **thresholds: float) -> CauseRules:
    """The ``[causes]`` defaults, some of them replaced by ``thresholds`` (z units, pixels): kernels used on their own."""
    return CauseRules(
        pixel_size=pixel_size,
        jump_threshold=jump_threshold,
        **{"pixel_area_m2": pixel_size**2, **_thresholds(CausesConfig()), **thresholds},
    )


#: The fields of :class:`~pipeline.holes.causes.CauseRules` derived from other sections, in survey units.
_DERIVED: dict[str, str] = {
    "pixel_size": "grid.resolution_m",
    "jump_threshold": "holes.jump_threshold_m",
    "pixel_area_m2": "grid.resolution_m",
}

#: The configuration key behind each field of ``CauseRules``: the others are ``[causes]`` keys of the same name.
CONFIG_KEYS: dict[str, str] = {f.name: _DERIVED.get(f.name, f"causes.{f.name}") for f in dataclasses.fields(CauseRules)}


def _thresholds(causes: CausesConfig) -> dict[str, float]:
    """The ``[causes]`` values by CauseRules field."""
    return {name: getattr(causes, name) for name in CONFIG_KEYS if name not in _DERIVED}


def fill_params(
    config: Config, holes: HoleParams, *, pixel_size: float, horizontal_unit_m: float, vertical_unit_m: float
) -> FillParams:
    """The ``[fill]`` settings in survey units (``pixel_size`` in survey units, as ``grid.resolution``)."""
    from .fill import FillSettings, WaterEdge
    from .fill.by_cause import FillParams

    fill = config.fill
    pixel_m = pixel_size * horizontal_unit_m
    edge = WaterEdge(
        tolerance=fill.water_edge_tolerance_m / vertical_unit_m,
        min_share=fill.water_edge_min_share,
        max_slope=config.causes.water_max_slope * pixel_m / vertical_unit_m,  # z units per pixel of course
    )
    return FillParams(
        method=fill.method,
        by_cause=fill.by_cause,
        pixel_size=pixel_size,
        max_distance=fill.max_distance_m / horizontal_unit_m if fill.max_distance_m > 0 else math.inf,
        max_area_m2=fill.max_area_m2 if fill.max_area_m2 > 0 else math.inf,
        fill_missed_coverage=fill.missed_coverage,
        bare_earth=point_filter(config).bare_earth,
        water_edge=edge,
        water_reach_px=1.0 + fill.water_edge_reach_m / pixel_m,  # the ring, and the reach beyond it
        jump_threshold=holes.jump_threshold,
        settings=FillSettings(
            estimate_error=fill.estimate_error,
            tin_order=fill.tin_order,
            auto_candidates=tuple(dict.fromkeys(fill.auto_candidates)),
            auto_rough_rim=holes.jump_threshold,
        ),
        clamp_to_rim=fill.clamp_to_rim,
        river_min_drop=fill.river_min_drop_m / vertical_unit_m,
        river_min_elongation=fill.river_min_elongation,
    )


def raster_options(config: Config) -> RasterOptions:
    """How the COGs are written, from ``[output]``."""
    from .io.raster import RasterOptions

    out = config.output
    return RasterOptions(
        compress=out.compress,
        compress_level=out.compress_level,
        blocksize=out.blocksize,
        overview_resampling=out.overview_resampling,
    )


def flight_params(config: Config) -> FlightParams:
    """The flight-planning kernels' parameters from ``[flightplan]`` (its ranges are checked by ``config``)."""
    from .flightplan import CoverageParams, FlightParams
    from .flightplan.takeoff import TakeoffParams

    plan = config.flightplan
    coverage = CoverageParams(
        altitude_agl_m=plan.altitude_agl_m,
        fov_deg=plan.fov_deg,
        side_overlap=plan.side_overlap,
        run_in_m=plan.run_in_m,
        turnaround_m=plan.turnaround_m,
        margin_m=plan.margin_m,
    )
    return FlightParams(
        coverage=coverage,
        causes=tuple(plan.causes),
        min_area_m2=plan.min_area_m2,
        speed_m_s=plan.speed_m_s,
        transit_speed_m_s=plan.transit_speed_m_s,
        max_flight_time_s=plan.max_flight_time_s,
        setup_time_s=plan.setup_time_s,
        terrain_step_m=plan.terrain_step_m,
        altitude_reference=plan.altitude_reference,
        max_climb_gradient=plan.max_climb_gradient,
        min_clearance_m=plan.min_clearance_m,
        clearance_radius_m=plan.clearance_radius_m,
        acceleration_m_s2=plan.acceleration_m_s2,
        takeoff=TakeoffParams(
            clear_radius_m=plan.home_clear_radius_m,
            obstacle_m=plan.home_obstacle_m,
            max_slope_deg=plan.home_max_slope_deg,
        ),
        ground_step_m=config.holes.jump_threshold_m,
    )
