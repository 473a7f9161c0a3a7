"""Typed, validated configuration.

Configuration is data: TOML files (``configs/default.toml`` documents every key)
are read once, at the edge, into frozen dataclasses; the rest of the code
receives typed objects and never sees raw dictionaries. Precedence, lowest
first: built-in defaults, the ``--config`` file, ``--set section.key=value``
overrides. Any unknown key or wrong value stops the run before any work, with a
message naming the key, where it came from and what is allowed.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, get_args, get_origin, get_type_hints

from .errors import ConfigError

#: The value of a key whose number is worked out from the survey (``grid.resolution_m``,
#: ``holes.min_area_m2``).
AUTO = "auto"

#: Pixels of context hole detection needs around a cell core (its local radius):
#: ``grid.halo_px`` must be at least this when holes are found.
HOLE_CONTEXT_PX = 8


def _opt(default: Any, doc: str, **rules: Any) -> Any:
    """A config field: its default, a one-line description and validation rules.

    Rules: ``choices`` (allowed values), ``gt``/``ge`` (lower bounds), ``lt``/``le``
    (upper bounds), ``item_range`` (bounds of each list item), ``item_choices``
    (allowed list items), ``lengths`` (allowed list lengths), ``auto`` (the string ``"auto"`` is allowed besides a
    number: the field's type is ``float | str``, resolved once when the survey is
    planned, see :mod:`pipeline.plan`).
    """
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata={"doc": doc, **rules})
    return field(default=default, metadata={"doc": doc, **rules})


@dataclass(frozen=True)
class GridConfig:
    """The global raster grid and the cells it is cut into."""

    resolution_m: float | str = _opt(
        "auto",
        "DSM pixel size in metres, or 'auto': the finest standard size the point density supports.",
        gt=0,
        auto=True,
    )
    cell_size_m: float | str = _opt(
        "auto",
        "Side of a square processing cell in metres, rounded to a whole multiple (>= 16) of the pixel, or 'auto': "
        "500 pixels.",
        gt=0,
        auto=True,
    )
    halo_px: int = _opt(8, "Pixels of neighbouring cells read around each cell.", ge=0)
    align: str = _opt(
        "edge",
        "Pixel edges ('edge') or pixel centres ('center') on multiples of the pixel size.",
        choices=("edge", "center"),
    )


@dataclass(frozen=True)
class FilterConfig:
    """Which points enter the rasters."""

    drop_classes: list[int] = _opt(
        [7, 18], "ASPRS classes never used (7 low noise, 18 high noise).", item_range=(0, 255)
    )
    keep_classes: list[int] = _opt([], "If not empty, only these classes are used (a DTM: [2]).", item_range=(0, 255))
    drop_withheld: bool = _opt(True, "Drop points flagged withheld.")


@dataclass(frozen=True)
class RasterizeConfig:
    """Stage 1: binning points into per-pixel statistics."""

    chunk_points: int = _opt(1_000_000, "Points decoded per chunk; bounds the memory of a tile task.", ge=10_000)
    voxel_height_m: float = _opt(0.5, "Voxel height in metres for the occupied-voxel count (vertical holes).", gt=0)
    copc_split: bool | str = _opt(
        "auto",
        "Read a COPC file as several tasks, its octree nodes grouped by cell: true, false, or 'auto' "
        "(when the file spans more than one cell).",
        auto=True,
    )


@dataclass(frozen=True)
class HolesConfig:
    """Hole detection, classification and outlines (docs/holes.md)."""

    enabled: bool = _opt(True, "Find, classify and outline holes (false: the DSM only).")
    min_area_m2: float | str = _opt(
        "auto",
        "Holes smaller than this (m2) are small voids: counted, not listed; 'auto' scales it with the point spacing.",
        ge=0,
        auto=True,
    )
    connectivity: int = _opt(4, "Pixel connectivity of hole pixels.", choices=(4, 8))
    jump_threshold_m: float = _opt(
        2.5, "Height jump (UAS eq. 1): max z - min z in a pixel, or between 4-neighbours.", gt=0
    )
    outline: str = _opt(
        "pixel",
        "Hole polygons: exact pixel edges, simplified, or straight (man-made).",
        choices=("pixel", "simplified", "straight"),
    )
    footprint_block_m: float = _opt(
        8.0, "Block size of the coarse occupancy map that decides the survey's data footprint.", gt=0
    )
    footprint_closing_m: float = _opt(
        40.0, "Gaps between data narrower than about twice this stay inside the footprint.", ge=0
    )
    water: str = _opt("", "Polygon file of known water (--water); holes inside it are water.")
    vertical_min_area_m2: float = _opt(2.0, "Groups of vertical-hole pixels smaller than this are not listed.", ge=0)
    wall_min_length_m: float = _opt(4.0, "Wall segments shorter than this are not fitted.", gt=0)


@dataclass(frozen=True)
class CausesConfig:
    """Thresholds of the hole-cause rules (docs/holes.md, "Causes"); the first rule that holds wins."""

    water_min_mask_fraction: float = _opt(
        0.5, "water_mask rule: share of the hole inside the given water polygons.", ge=0, le=1
    )
    covered_min_fraction: float = _opt(
        0.5,
        "covered rule: share of the hole under points the class filter left out (a ground-only model).",
        ge=0,
        le=1,
    )
    gap_min_fraction: float = _opt(
        0.5,
        "coverage_gap rule (missed coverage): share of the hole outside every flight line's swath.",
        ge=0,
        le=1,
    )
    water_min_point_fraction: float = _opt(
        0.1, "water_points rule: share of the ring (or of the hole) holding water-class points.", ge=0, le=1
    )
    occlusion_min_jump_fraction: float = _opt(
        0.5, "jumps rule (occlusion): share of the ring pixels that are height jumps.", ge=0, le=1
    )
    shadow_min_high_fraction: float = _opt(
        0.15,
        "shadow rule (occlusion): share of the ring more than jump_threshold_m above its low level.",
        ge=0,
        le=1,
    )
    shadow_min_residual_ratio: float = _opt(
        0.35,
        "shadow rule: ring scatter about its plane, as a multiple of jump_threshold_m, that rules out a slope.",
        ge=0,
    )
    max_terrain_slope: float = _opt(
        1.0, "shadow rule: a plane through the ring steeper than this (rise over run) is no terrain slope.", gt=0
    )
    max_shadow_ratio: float = _opt(
        0.8,
        "Occlusion rules: the hole's thickness must not exceed this times the height of the step beside it.",
        gt=0,
    )
    strip_min_fill: float = _opt(
        0.7, "strip rule (missed coverage): area / (length x width) of the hole, ~1 for a straight band.", ge=0
    )
    strip_min_length_px: float = _opt(20.0, "strip rule: least length of the band, in pixels.", ge=0)
    strip_min_elongation: float = _opt(
        4.0, "strip rule without flight-line ids: least length / width of the band.", ge=1
    )
    strip_min_elongation_with_lines: float = _opt(
        2.0, "strip rule with flight-line ids: least length / width of the band.", ge=1
    )
    strip_min_line_share: float = _opt(
        0.2, "strip rule: share of the ring a flight line must hold to count; two lines must.", ge=0, le=1
    )
    strip_two_line_share: float = _opt(
        0.8, "strip rule: share of the ring held by its two most common flight lines.", ge=0, le=1
    )
    water_flat_tolerance: float = _opt(
        0.5,
        "flat_low_rim rule: ring heights within this of the low level are flat (survey z units, not converted).",
        ge=0,
    )
    water_min_flat_fraction: float = _opt(0.7, "flat_low_rim rule: share of the ring that is flat.", ge=0, le=1)
    water_min_low_fraction: float = _opt(
        0.5, "flat_low_rim rule: share of the ring at the local minimum height.", ge=0, le=1
    )
    water_max_below_fraction: float = _opt(
        0.25,
        "level_rim rule: share of the ring below its level (the most populated height window).",
        ge=0,
        le=1,
    )
    water_max_slope: float = _opt(
        0.02,
        "river_rim rule: steepest fall of the rim along the hole (rise over run); rivers fall 0.01-1 %.",
        ge=0,
    )
    river_min_elongation: float = _opt(
        2.0, "river_rim rule: least length / width of a hole whose rim falls more than water_flat_tolerance.", ge=1
    )
    water_min_rim_area_m2: float = _opt(
        50.0,
        "level_rim, river_rim and flat_low_rim rules: smallest hole (m2) called water from its rim alone.",
        ge=0,
    )
    occlusion_min_blocked_fraction: float = _opt(
        0.5,
        "line_of_sight rule (occlusion): share of the hole's swept pixels that no line saw unobstructed.",
        ge=0,
        le=1,
    )
    low_quantile: float = _opt(0.05, "Quantile of the ring heights taken as the ring's low level.", ge=0, le=1)
    high_quantile: float = _opt(
        0.95, "Quantile of the ring heights taken as its high level (step = high - low level).", ge=0, le=1
    )


@dataclass(frozen=True)
class SensorConfig:
    """The sensor's geometry: flight lines, trajectories, swaths and lines of sight (docs/holes.md)."""

    enabled: bool = _opt(
        True, "Reconstruct the flight lines and judge causes by swath and line of sight (needs GPS times)."
    )
    nominal_fov_deg: float = _opt(
        40.0,
        "Full scan angle assumed where a line has neither multiple returns nor scan angles (reported as assumed).",
        gt=0,
        lt=180,
    )
    sight_reach_m: float = _opt(
        50.0,
        "How far (m) from a void its lines of sight are followed: obstacles up to reach / tan(scan angle) tall.",
        gt=0,
    )


@dataclass(frozen=True)
class DaskConfig:
    """The Dask cluster a run uses when no --scheduler is given."""

    workers: int = _opt(0, "Worker processes; 0 means one per CPU core.", ge=0)
    retries: int = _opt(
        2, "Times a task is retried when its worker dies (preemptible clusters); tasks are idempotent.", ge=0
    )
    memory_limit: str = _opt("auto", "Memory limit per worker, e.g. '2GB', or 'auto' to share the machine's memory.")
    connect_timeout_s: float = _opt(
        10.0, "Seconds to wait for a --scheduler to answer before stopping with exit status 1.", gt=0
    )
    no_worker_timeout_s: float = _opt(
        60.0, "Seconds a run waits while no worker is alive (all died, or none joined) before stopping (exit 1).", gt=0
    )


@dataclass(frozen=True)
class OutputConfig:
    """How rasters are written."""

    compress: str = _opt("deflate", "COG compression.", choices=("deflate", "zstd", "lzw", "none"))
    compress_level: int = _opt(1, "Deflate/zstd level: 1 writes fastest, higher values make smaller files.", ge=1)
    blocksize: int = _opt(256, "COG internal tile size in pixels.", choices=(128, 256, 512, 1024))
    overview_resampling: str = _opt(
        "average",
        "Resampling of COG overviews (fill_mask's codes: always nearest).",
        choices=("average", "nearest", "bilinear"),
    )
    keep_unfilled: bool = _opt(False, "Also write the DSM before filling (dsm_unfilled/ and dsm_unfilled.vrt).")
    keep_intermediate: bool = _opt(False, "Keep the per-tile and per-cell statistic rasters under OUT/work/.")
    points: bool = _opt(
        False, "Also write each tile as LAZ with one synthetic point per filled pixel (points/; needs fill.enabled)."
    )
    points_class: int = _opt(1, "LAS class of the added fill points (1: unclassified).", ge=0, le=31)


@dataclass(frozen=True)
class SurveyConfig:
    """How inputs are interpreted."""

    crs: str = _opt("", "CRS for tiles that have none (e.g. 'EPSG:28992'); empty: none assumed.")
    target_crs: str = _opt("", "Reproject every tile to this CRS while streaming; needed for mixed-CRS surveys.")
    on_error: str = _opt(
        "fail", "What a bad tile does: stop the run, or be skipped and listed.", choices=("fail", "skip")
    )
    area: str = _opt(
        "auto",
        "Survey area without --aoi: 'auto' (the tile grid's squares when the tiles lie on one, else the tile "
        "extents), 'tiles' (the tile grid's squares; a survey whose tiles lie on no grid is refused) or "
        "'footprint' (the tile extents, no grid inferred).",
        choices=("auto", "tiles", "footprint"),
    )


@dataclass(frozen=True)
class ReadConfig:
    """How points are read (docs/usage.md, "PDAL pipelines")."""

    reader: str = _opt(
        "laspy",
        "Point reader: laspy (built in) or pdal (python-pdal, the holefill[pdal] extra).",
        choices=("laspy", "pdal"),
    )
    pdal_pipeline: str = _opt(
        "", "JSON file of PDAL filter stages run on each tile before binning (needs reader = 'pdal')."
    )
    pdal_streaming: bool = _opt(
        True, "Refuse stages that cannot stream; false allows them, each tile then read whole into memory."
    )
    allow_network: bool = _opt(
        False,
        "Allow network paths (URLs, GDAL's /vsicurl/, /vsis3/, ...) in the configuration's file keys.",
    )


@dataclass(frozen=True)
class FlightPlanConfig:
    """Re-flight plans for the holes a drone can re-scan (docs/flightplans.md)."""

    enabled: bool = _opt(True, "Write re-flight plans after a run (needs holes.enabled).")
    causes: list[str] = _opt(
        ["missed_coverage"],
        "Hole causes that are re-flown (occlusion: from where its ground is in sight); the others are listed, not flown.",
        item_choices=("occlusion", "water", "missed_coverage", "no_return", "covered", "unknown"),
    )
    min_area_m2: float = _opt(25.0, "Holes smaller than this (m2) are not re-flown.", ge=0)
    altitude_agl_m: float = _opt(
        60.0, "Flying height in metres above the highest DSM surface under the lidar swath.", gt=0
    )
    fov_deg: float = _opt(70.0, "Lidar cross-track field of view in degrees.", gt=0, lt=180)
    side_overlap: float = _opt(0.3, "Side overlap of neighbouring lanes (0 to 0.9).", ge=0, le=0.9)
    speed_m_s: float = _opt(6.0, "Ground speed on scanning lanes (m/s).", gt=0)
    transit_speed_m_s: float = _opt(12.0, "Ground speed between lanes and patterns (m/s).", gt=0)
    run_in_m: float = _opt(20.0, "Lanes extend this far (m) beyond the hole so the lidar is steady.", ge=0)
    turnaround_m: float = _opt(10.0, "Distance (m) flown beyond each lane end to turn, not scanning.", ge=0)
    margin_m: float = _opt(5.0, "Each hole is buffered by this margin (m) before lanes are laid.", ge=0)
    max_flight_time_s: float = _opt(
        1200.0, "Longest sortie in seconds (transit included); longer routes are split.", gt=0
    )
    setup_time_s: float = _opt(90.0, "Seconds added to every sortie for take-off, climb, descent and landing.", ge=0)
    terrain_step_m: float = _opt(
        5.0, "A lane is flown inclined (not level) when that lowers its mean height by more than this (m).", gt=0
    )
    max_climb_gradient: float = _opt(
        0.15,
        "Steepest climb or descent along an inclined lane (rise over run); 0: lanes always level.",
        ge=0,
        le=0.5,
    )
    min_clearance_m: float = _opt(
        20.0, "Every leg clears the highest surface within clearance_radius_m by at least this (m).", ge=0
    )
    clearance_radius_m: float = _opt(
        3.0, "Horizontal uncertainty of the flown path (m): GNSS and path-tracking error.", ge=0
    )
    acceleration_m_s2: float = _opt(
        2.0, "Acceleration of the aircraft in turns and speed changes (m/s2), for flight times.", gt=0
    )
    home: list[float] = _opt(
        [],
        "Take-off and landing point [x, y] in the survey CRS; empty: the open ground nearest to the "
        "planned holes (ground-class points, level, clear of obstacles and water).",
        lengths=(0, 2),
    )
    home_clear_radius_m: float = _opt(
        10.0, "Open ground for take-off: no obstacle or water within this radius (m).", gt=0
    )
    home_obstacle_m: float = _opt(
        1.0, "Open ground for take-off: nothing higher than this (m) above the ground within the radius.", gt=0
    )
    home_max_slope_deg: float = _opt(5.0, "Open ground for take-off: the steepest ground slope (degrees).", gt=0, lt=45)
    altitude_reference: str = _opt(
        "takeoff",
        "Heights in drone files: relative to take-off, AMSL (the DSM's datum) or ellipsoidal.",
        choices=("takeoff", "amsl", "ellipsoid"),
    )
    vertical_crs: str = _opt(
        "", "Vertical CRS of DSM heights (e.g. 'EPSG:5720'); empty: from the DSM's CRS if compound."
    )
    dji_drone_enum: int = _opt(89, "DJI WPML droneEnumValue: 89 Matrice 350 RTK, 60 Matrice 300 RTK.", ge=0)
    dji_payload_enum: int = _opt(84, "DJI WPML payloadEnumValue of the lidar (84 Zenmuse L2, 90742 Zenmuse L1).", ge=0)


@dataclass(frozen=True)
class FillConfig:
    """Filling the holes of the DSM (docs/filling.md)."""

    enabled: bool = _opt(True, "Fill the holes of the DSM (needs holes.enabled); false keeps nodata in them.")
    method: str = _opt(
        "auto",
        "Interpolation of holes that are not water: auto (per hole, by cross-validation on its rim among"
        " fill.auto_candidates), tin (Laplacian fairing), spline (regularized spline with tension), mls,"
        " linear (linear TIN), natural (natural neighbours, Laplace coordinates), idw or nearest.",
        choices=("auto", "tin", "spline", "mls", "linear", "natural", "idw", "nearest"),
    )
    auto_candidates: list[str] = _opt(
        ["natural", "tin"],
        "Methods auto chooses among per hole, by the RMSE of each on the hole's withheld rim sectors"
        " (tin, spline, mls, linear, natural, idw, nearest); the first fills unless another is"
        " significantly better.",
        item_choices=("tin", "spline", "mls", "linear", "natural", "idw", "nearest"),
    )
    by_cause: bool = _opt(
        True, "Occlusion holes from their lower rim (the ground beside a building); water holes flat."
    )
    max_distance_m: float = _opt(
        0.0,
        "Holes with a pixel farther than this (m) from measured data stay nodata (skipped: too large); 0: no limit.",
        ge=0,
    )
    max_area_m2: float = _opt(0.0, "Holes larger than this (m2) stay nodata (skipped: too large); 0: no limit.", ge=0)
    missed_coverage: bool = _opt(
        False, "Also fill missed coverage (flagged in fill_note); false leaves it nodata for the re-flight."
    )
    margin_px: int = _opt(8, "Pixels of measured data read around each hole for its support.", ge=1)
    tin_order: int = _opt(
        1, "Fairing of tin fills: 1 harmonic (umbrella operator), 2 biharmonic (second order).", choices=(1, 2)
    )
    clamp_to_rim: bool = _opt(
        True, "Keep interpolated heights within the range of the hole's rim (no overshoot at steps)."
    )
    water_edge_tolerance_m: float = _opt(
        0.15,
        "Heights of one water level agree within this (m): the lidar's vertical noise (0.05-0.10 m, 1 sigma).",
        gt=0,
    )
    water_edge_min_share: float = _opt(
        0.1, "The water's edge is the lowest level at least this share of a hole's ring agrees on.", gt=0, le=1
    )
    water_edge_reach_m: float = _opt(
        2.0, "Water-class returns within this (m) of a water hole's ring give its level.", ge=0
    )
    river_min_drop_m: float = _opt(
        0.25, "A water hole is a river (surface stepping down its course) when it falls at least this (m).", ge=0
    )
    river_min_elongation: float = _opt(
        4.0, "... and its course is at least this many times as long as its mean width (length^2 / area).", ge=0
    )
    estimate_error: bool = _opt(
        True, "Estimate each hole's fill error by refilling it with part of its rim withheld (costs a second fill)."
    )


@dataclass(frozen=True)
class Config:
    """The whole resolved configuration of a run."""

    grid: GridConfig = field(default_factory=GridConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)
    rasterize: RasterizeConfig = field(default_factory=RasterizeConfig)
    holes: HolesConfig = field(default_factory=HolesConfig)
    causes: CausesConfig = field(default_factory=CausesConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    dask: DaskConfig = field(default_factory=DaskConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    survey: SurveyConfig = field(default_factory=SurveyConfig)
    read: ReadConfig = field(default_factory=ReadConfig)
    flightplan: FlightPlanConfig = field(default_factory=FlightPlanConfig)
    fill: FillConfig = field(default_factory=FillConfig)

    @property
    def plans_flights(self) -> bool:
        """Whether a run plans re-flights for the holes it finds (``holes.enabled`` and ``flightplan.enabled``)."""
        return self.holes.enabled and self.flightplan.enabled

    def replace(self, section: str, *, source: str = "replace()", **values: Any) -> Config:
        """Return a copy with some keys of one section changed, validated like a file.

        ``source`` names where the values come from in error messages (e.g. ``--crs``).
        """
        if section not in SECTIONS:
            raise ConfigError(f"{source}: unknown section '{section}'; allowed sections: {', '.join(SECTIONS)}")
        for key in values:
            _check_key(section, key, source)
        merged = to_dict(self)
        merged[section].update(values)
        return _build(merged, {f"{section}.{k}": source for k in values})

    def to_toml(self) -> str:
        """The configuration as a TOML document (what ``holefill config --show`` prints)."""
        lines: list[str] = []
        for section in dataclasses.fields(self):
            sub = getattr(self, section.name)
            lines.append(f"[{section.name}]")
            for f in dataclasses.fields(sub):
                lines.append(f"{f.name} = {_toml_value(getattr(sub, f.name))}  # {f.metadata['doc']}")
            lines.append("")
        return "\n".join(lines)


SECTIONS: dict[str, type] = {f.name: get_type_hints(Config)[f.name] for f in dataclasses.fields(Config)}


def to_dict(config: Config) -> dict[str, dict[str, Any]]:
    """The configuration as nested plain dictionaries."""
    return {name: dataclasses.asdict(getattr(config, name)) for name in SECTIONS}


def config_key(config: Config) -> str:
    """The configuration a result was made with (the ``[dask]`` settings aside), as a short hash."""
    import hashlib
    import json

    from . import __version__

    settings = {k: v for k, v in to_dict(config).items() if k != "dask"}
    return hashlib.sha1(json.dumps([__version__, settings], sort_keys=True, default=str).encode()).hexdigest()[:16]


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """Read, merge and validate the configuration.

    Parameters
    ----------
    path : path-like, optional
        A TOML file whose keys override the defaults.
    overrides : list of str
        ``section.key=value`` strings (``--set``); the value is parsed as TOML,
        or taken as a plain string when it is not valid TOML.

    Raises
    ------
    ConfigError
        Naming the key, the file (or ``--set``) and the allowed values.
    """
    merged = to_dict(Config())
    sources: dict[str, str] = {}
    if path is not None:
        path = Path(path)
        try:
            with path.open("rb") as fh:
                data = tomllib.load(fh)
        except FileNotFoundError:
            raise ConfigError(f"{path}: configuration file not found") from None
        except tomllib.TOMLDecodeError as e:
            raise ConfigError(f"{path}: not valid TOML: {e}") from None
        for section, table in data.items():
            if section not in SECTIONS:
                raise ConfigError(f"{path}: unknown section [{section}]; allowed sections: {', '.join(SECTIONS)}")
            if not isinstance(table, dict):
                raise ConfigError(f"{path}: '{section}' must be a table ([{section}])")
            for key, value in table.items():
                _check_key(section, key, str(path))
                merged[section][key] = _relative_to(path, f"{section}.{key}", value)
                sources[f"{section}.{key}"] = str(path)
    for item in overrides:
        section, key, value = _parse_override(item)
        merged[section][key] = value
        sources[f"{section}.{key}"] = f"--set {item}"
    return _build(merged, sources)


#: Keys that name files: a relative path in a configuration file is relative to that file's folder
#: (as a user who keeps the file beside its water polygons expects); from ``--set``, to the
#: working directory.
PATH_KEYS = ("holes.water", "read.pdal_pipeline")
#: Prefixes of paths that reach over the network (GDAL's virtual file systems, URLs): a
#: configuration handed to a scheduled job must not make it fetch from elsewhere unasked.
NETWORK_PREFIXES = (
    "/vsicurl",
    "/vsis3",
    "/vsigs",
    "/vsiaz",
    "/vsiadls",
    "/vsioss",
    "/vsiswift",
    "/vsihdfs",
    "/vsiwebhdfs",
)


def is_network_path(value: str) -> bool:
    """Whether a path names a network location (``scheme://`` or one of ``NETWORK_PREFIXES``)."""
    text = value.strip()
    return "://" in text or any(text.startswith(prefix) for prefix in NETWORK_PREFIXES)


def _relative_to(config_file: Path, key: str, value: Any) -> Any:
    """A file key's relative path from a configuration file, made relative to that file's folder."""
    if key not in PATH_KEYS or not isinstance(value, str) or not value.strip() or is_network_path(value):
        return value
    candidate = Path(value).expanduser()
    return value if candidate.is_absolute() else str(config_file.parent / candidate)


def _parse_override(item: str) -> tuple[str, str, Any]:
    if "=" not in item or "." not in item.split("=", 1)[0]:
        raise ConfigError(f"--set {item}: expected section.key=value, e.g. grid.resolution_m=0.5")
    dotted, raw = item.split("=", 1)
    section, key = dotted.strip().split(".", 1)
    if section not in SECTIONS:
        raise ConfigError(f"--set {item}: unknown section '{section}'; allowed sections: {', '.join(SECTIONS)}")
    _check_key(section, key, f"--set {item}")
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    return section, key, value


def _check_key(section: str, key: str, source: str) -> None:
    allowed = [f.name for f in dataclasses.fields(SECTIONS[section])]
    if key not in allowed:
        raise ConfigError(f"{source}: unknown key '{section}.{key}'; allowed keys in [{section}]: {', '.join(allowed)}")


def _build(merged: dict[str, dict[str, Any]], sources: dict[str, str]) -> Config:
    sections = {}
    for name, cls in SECTIONS.items():
        hints = get_type_hints(cls)
        values = {}
        for f in dataclasses.fields(cls):
            where = sources.get(f"{name}.{f.name}", "default")
            values[f.name] = _validate(f"{name}.{f.name}", merged[name][f.name], hints[f.name], dict(f.metadata), where)
        sections[name] = cls(**values)
    config = Config(**sections)
    _check_across_keys(config, sources)
    return config


def _check_across_keys(config: Config, sources: dict[str, str]) -> None:
    """Rules that tie keys together, checked at load time so that no worker meets them later."""
    if config.holes.enabled and config.grid.halo_px < HOLE_CONTEXT_PX:
        where = sources.get("grid.halo_px", "default")
        raise ConfigError(
            f"{where}: grid.halo_px = {config.grid.halo_px} is too small; hole detection reads "
            f"{HOLE_CONTEXT_PX} pixels around each cell (set holes.enabled = false to build the DSM only)"
        )
    if config.output.points and not (config.holes.enabled and config.fill.enabled):
        where = sources.get("output.points", "default")
        raise ConfigError(
            f"{where}: output.points = true adds the filled pixels to the point clouds; "
            "it needs holes.enabled = true and fill.enabled = true"
        )
    for dotted in PATH_KEYS:
        section, key = dotted.split(".")
        value = getattr(getattr(config, section), key)
        if isinstance(value, str) and is_network_path(value) and not config.read.allow_network:
            where = sources.get(dotted, "default")
            raise ConfigError(
                f"{where}: {dotted} = {value!r} is a network path; set read.allow_network = true to read it"
            )
    if config.read.pdal_pipeline and config.read.reader != "pdal":
        where = sources.get("read.pdal_pipeline", "default")
        raise ConfigError(
            f"{where}: read.pdal_pipeline = {config.read.pdal_pipeline!r} needs read.reader = 'pdal' "
            f"(it is {config.read.reader!r})"
        )
    if config.flightplan.altitude_agl_m < config.flightplan.min_clearance_m:
        where = sources.get("flightplan.altitude_agl_m", sources.get("flightplan.min_clearance_m", "default"))
        raise ConfigError(
            f"{where}: flightplan.altitude_agl_m ({config.flightplan.altitude_agl_m:g}) is below "
            f"flightplan.min_clearance_m ({config.flightplan.min_clearance_m:g}); every lane would be refused"
        )
    if not config.causes.low_quantile < config.causes.high_quantile:
        where = sources.get("causes.low_quantile", sources.get("causes.high_quantile", "default"))
        raise ConfigError(
            f"{where}: causes.low_quantile ({config.causes.low_quantile}) must be below "
            f"causes.high_quantile ({config.causes.high_quantile})"
        )


def _validate(key: str, value: Any, kind: Any, rules: dict[str, Any], where: str) -> Any:
    def fail(expected: str) -> ConfigError:
        return ConfigError(f"{where}: {key} = {value!r} is invalid; expected {expected}")

    if get_origin(kind) is types.UnionType:  # float | str or bool | str: a number or a flag, or "auto"
        if rules.get("auto") and value == AUTO:
            return AUTO
        other = next(a for a in get_args(kind) if a is not str)
        if isinstance(value, str) or not _is(value, other):
            raise fail(f"{'true, false' if other is bool else 'a number'} or {AUTO!r}")
        return _validate(key, value, other, rules, where)
    if get_origin(kind) is list:
        item_kind = get_args(kind)[0]
        if not isinstance(value, list) or not all(_is(v, item_kind) for v in value):
            raise fail(f"a list of {item_kind.__name__}")
        if "item_range" in rules:
            low, high = rules["item_range"]
            if any(not low <= v <= high for v in value):
                raise fail(f"items between {low} and {high}")
        if "lengths" in rules and len(value) not in rules["lengths"]:
            raise fail("a list of " + " or ".join(str(n) for n in rules["lengths"]) + " items")
        if "item_choices" in rules and any(v not in rules["item_choices"] for v in value):
            raise fail("items among " + ", ".join(repr(c) for c in rules["item_choices"]))
        return [item_kind(v) for v in value]
    if not _is(value, kind):
        raise fail(f"a {kind.__name__}")
    value = kind(value)
    if "choices" in rules and value not in rules["choices"]:
        raise fail("one of " + ", ".join(repr(c) for c in rules["choices"]))
    if "gt" in rules and not value > rules["gt"]:
        raise fail(f"a number > {rules['gt']}")
    if "ge" in rules and not value >= rules["ge"]:
        raise fail(f"a number >= {rules['ge']}")
    if "lt" in rules and not value < rules["lt"]:
        raise fail(f"a number < {rules['lt']}")
    if "le" in rules and not value <= rules["le"]:
        raise fail(f"a number <= {rules['le']}")
    if kind is float and not math.isfinite(value):
        raise fail("a finite number")
    return value


def _is(value: Any, kind: type) -> bool:
    if kind is bool:
        return isinstance(value, bool)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if kind is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    return isinstance(value, kind)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)
