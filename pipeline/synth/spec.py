"""What defines a synthetic survey: :class:`SurveySpec`, the presets, the truth codes and constants."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Any

import affine

BASE_HEIGHT_M = 50.0
#: Width over which the terrain is blended down to the water level beside the river.
RIVER_BANK_WIDTH_M = 15.0
#: Lakes' water ellipses span this many metres (min, max) across.
LAKE_SIZE_M = (20.0, 80.0)
#: Canal width, quay height above the water and street width (min, max), metres.
CANAL_WIDTH_M = (8.0, 15.0)
CANAL_QUAY_HEIGHT_M = (1.5, 2.0)
CANAL_STREET_M = (3.0, 6.0)
#: Canal-side buildings: height, depth (E-W) and frontage (N-S), metres (min, max).
CANAL_HOUSE_HEIGHT_M = (10.0, 20.0)
CANAL_HOUSE_DEPTH_M = (10.0, 20.0)
CANAL_HOUSE_FRONTAGE_M = (6.0, 16.0)
#: Height of the top of a river bank above the water surface.
RIVER_BANK_HEIGHT_M = 0.3
#: Pulse positions are jittered uniformly by up to this fraction of the spacing.
PULSE_JITTER_FRACTION = 0.4
#: Aircraft ground speed: sets the GPS time between scan lines.
FLIGHT_SPEED_M_S = 60.0
#: Adjusted standard GPS time (GPS seconds - 1e9) at the start of the first line.
SURVEY_START_GPS_TIME = 300_000_000.0
#: Time between the starts of consecutive flight lines (line plus turn).
LINE_INTERVAL_S = 900.0
#: Largest fine-grid cell used to sample the scene.
MAX_FINE_CELL_M = 0.25
#: ASPRS classification codes written.
CLASS_GROUND = 2
CLASS_HIGH_VEGETATION = 5
CLASS_BUILDING = 6

_COORDINATE_SCALE = 0.01  # metres per stored integer (x, y and z)
_CENTIMETRES_PER_METRE = 100


class HoleCause(enum.IntEnum):
    """Why a truth pixel holds no point."""

    NONE = 0
    """Not a hole: the pixel has points."""
    OCCLUSION = 1
    """Inside some flight line's swath, but every line's view is blocked by a taller object."""
    WATER = 2
    """Mostly over water: the laser returns nothing."""
    MISSED_COVERAGE = 3
    """Outside every flown line's swath (gap left by a dropped line)."""
    NO_RETURN = 4
    """Seen by a line, unobstructed, not water, yet no return (a dark or wet surface)."""
    COVERED = 5
    """A DTM void under points that were removed (buildings, vegetation); reserved."""


class SurfaceKind(enum.IntEnum):
    """What the top surface of a fine-grid cell is."""

    GROUND = 0
    BUILDING = 1
    TREE = 2
    WATER = 3


@dataclass(frozen=True)
class SurveySpec:
    """Everything that defines a synthetic survey; the same spec gives the same files.

    Attributes
    ----------
    x_min, y_min : float
        Lower-left corner of the surveyed extent in CRS metres (multiples of
        ``resolution``).
    width_m, height_m : float
        Size of the extent (multiples of ``resolution``).
    crs : str
        Any CRS string pyproj understands; embedded in every tile.
    resolution : float
        Truth grid pixel size in metres (a multiple of 0.01 m). Pixel
        ``(row, col)`` covers x in ``[x_min + col*res, x_min + (col+1)*res)``
        and y in ``[y_max - (row+1)*res, y_max - row*res)``, row 0 at the top.
    tile_size_m : float
        Side of the LAZ tiles (a multiple of ``resolution``), on a grid aligned
        to ``(x_min, y_min)``; tiles at the east/north edge are clipped to the
        extent.
    seed : int
        Seeds the scene and the pulse jitter.
    terrain_relief_m : float
        Peak-to-peak amplitude of the rolling terrain around ``BASE_HEIGHT_M``.
    building_density, tree_density : float
        Objects per hectare before rejection of overlapping placements.
    water : bool
        Whether a river crosses the scene west to east.
    water_width_m : float
        N-S width of the river.
    river_fall_m_per_km : float
        Fall of the river's water surface from west to east (m per km; real
        rivers fall 0.1-3 m/km); the bed and the banks follow it. 0: flat.
    lakes : int
        Lakes to place (ellipses 20-80 m across, flat water, the terrain blended
        down to a shore just above the water), clear of the river, the canal
        and each other, inside the extent; too many for the extent is an error.
    canal : bool
        A straight N-S canal 8-15 m wide across the scene: flat water, quay walls
        1.5-2 m high, a 3-6 m street, and a row of 10-20 m tall buildings along
        each quay, whose scan shadows can fall on the street and the water.
    flight_altitude_m : float
        Sensor height above ``BASE_HEIGHT_M``.
    scan_angle_deg : float
        Half-angle of the scan; the swath is ``2 * altitude * tan(angle)``.
    side_overlap : float
        Fraction of swath shared by adjacent flight lines (0 <= f < 1).
    pulse_spacing_m : float
        Along- and across-track pulse spacing on the ground; at most
        ``resolution / 1.8`` so that every visible pixel is guaranteed a pulse.
    missed_line : int or None
        Index (0 = westernmost) of a flight line that is dropped, leaving an
        uncovered strip; ``None`` flies every line.
    canopy_penetration : float
        Probability that a pulse reaches the ground through a tree crown.
    noise_m : float
        Standard deviation of the (approximately Gaussian, bounded at 3.5
        sigma) z noise.
    las_version : str
        ``"1.4"`` (point format 6, WKT CRS) or ``"1.2"`` (point format 1,
        GeoTIFF-key CRS, which needs an EPSG-coded CRS).
    compress : bool
        Write ``.laz`` (lazrs) if true, ``.las`` otherwise.
    """

    x_min: float = 500_000.0
    y_min: float = 5_000_000.0
    width_m: float = 400.0
    height_m: float = 300.0
    crs: str = "EPSG:32631"
    resolution: float = 1.0
    tile_size_m: float = 100.0
    seed: int = 0
    # scene
    terrain_relief_m: float = 8.0
    building_density: float = 2.5
    tree_density: float = 25.0
    water: bool = True
    water_width_m: float = 20.0
    river_fall_m_per_km: float = 0.0
    lakes: int = 0
    canal: bool = False
    # acquisition
    flight_altitude_m: float = 300.0
    scan_angle_deg: float = 20.0
    side_overlap: float = 0.3
    pulse_spacing_m: float = 0.35
    missed_line: int | None = 1
    canopy_penetration: float = 0.3
    noise_m: float = 0.03
    las_version: str = "1.4"
    compress: bool = True

    def __post_init__(self) -> None:
        def fail(name: str, message: str) -> None:
            raise ValueError(f"SurveySpec.{name}: {message}")

        if not (self.resolution > 0 and _is_multiple(self.resolution, _COORDINATE_SCALE)):
            fail("resolution", f"must be a positive multiple of 0.01 m, got {self.resolution!r}")
        for name in ("x_min", "y_min", "width_m", "height_m", "tile_size_m"):
            value = getattr(self, name)
            if not _is_multiple(value, self.resolution):
                fail(name, f"must be a multiple of resolution={self.resolution}, got {value!r}")
        for name in ("width_m", "height_m", "tile_size_m", "flight_altitude_m", "pulse_spacing_m"):
            if not getattr(self, name) > 0:
                fail(name, f"must be positive, got {getattr(self, name)!r}")
        for name in ("terrain_relief_m", "building_density", "tree_density", "water_width_m", "noise_m"):
            if not getattr(self, name) >= 0:
                fail(name, f"must be >= 0, got {getattr(self, name)!r}")
        if not (math.isfinite(self.river_fall_m_per_km) and 0 <= self.river_fall_m_per_km <= 100):
            fail("river_fall_m_per_km", f"must be in [0, 100] m/km, got {self.river_fall_m_per_km!r}")
        if isinstance(self.lakes, bool) or not isinstance(self.lakes, int) or self.lakes < 0:
            fail("lakes", f"must be a whole number >= 0, got {self.lakes!r}")
        if not isinstance(self.canal, bool):
            fail("canal", f"must be true or false, got {self.canal!r}")
        if not 0 < self.scan_angle_deg < 60:
            fail("scan_angle_deg", f"must be in (0, 60), got {self.scan_angle_deg!r}")
        if not 0 <= self.side_overlap < 1:
            fail("side_overlap", f"must be in [0, 1), got {self.side_overlap!r}")
        if not 0 <= self.canopy_penetration <= 1:
            fail("canopy_penetration", f"must be in [0, 1], got {self.canopy_penetration!r}")
        if self.pulse_spacing_m * (1 + 2 * PULSE_JITTER_FRACTION) > self.resolution * (1 + 1e-9):
            fail(
                "pulse_spacing_m",
                f"{self.pulse_spacing_m} m is too sparse for resolution={self.resolution} m: pixels could be "
                f"empty by chance; use at most {self.resolution / (1 + 2 * PULSE_JITTER_FRACTION):.4g} m",
            )
        if self.las_version not in ("1.2", "1.4"):
            fail("las_version", f"must be '1.2' or '1.4', got {self.las_version!r}")
        if self.missed_line is not None and self.missed_line < 0:
            fail("missed_line", f"must be a line index >= 0 or None, got {self.missed_line!r}")

    @property
    def x_max(self) -> float:
        return self.x_min + self.width_m

    @property
    def y_max(self) -> float:
        return self.y_min + self.height_m

    @property
    def shape(self) -> tuple[int, int]:
        """Truth grid shape ``(rows, cols)``."""
        return (round(self.height_m / self.resolution), round(self.width_m / self.resolution))

    @property
    def transform(self) -> affine.Affine:
        """Rasterio-style transform of the truth grid (north-up, row 0 at ``y_max``)."""
        return affine.Affine(self.resolution, 0.0, self.x_min, 0.0, -self.resolution, self.y_max)

    @property
    def swath_width_m(self) -> float:
        """Nominal swath width on the base terrain level, ``2 * altitude * tan(scan angle)``."""
        return 2.0 * self.flight_altitude_m * math.tan(math.radians(self.scan_angle_deg))


def _is_multiple(value: float, step: float) -> bool:
    ratio = value / step
    return abs(ratio - round(ratio)) < 1e-6


_PRESETS: dict[str, dict[str, Any]] = {
    # 128 m x 96 m, 2 tiles, ~7k points: each hole cause present, for fast tests.
    "unit": dict(
        width_m=128.0,
        height_m=96.0,
        tile_size_m=96.0,
        resolution=2.0,
        pulse_spacing_m=1.1,
        flight_altitude_m=100.0,
        water_width_m=8.0,
        building_density=8.0,
        tree_density=20.0,
    ),
    # 600 m x 400 m, 24 tiles of 100 m, ~1.8M points at ~8 pulses/m2.
    "demo": dict(width_m=600.0, height_m=400.0, tile_size_m=100.0),
    # 2 km x 2 km, 64 tiles of 250 m, ~42M points; scale with width_m/height_m.
    "bench": dict(width_m=2000.0, height_m=2000.0, tile_size_m=250.0),
}


def preset(name: str, **overrides: Any) -> SurveySpec:
    """A named survey specification, optionally with some fields replaced.

    Parameters
    ----------
    name : {"unit", "demo", "bench"}
        ``"unit"``: 128 x 96 m at 2 m pixels and 0.8 pulse/m^2 from 100 m
        altitude, two tiles and ~7 thousand points with every hole cause,
        for fast tests. ``"demo"``: 600 x 400 m at the
        default 0.35 m pulse spacing, ~1.8 million points in 24 tiles
        (about a second). ``"bench"``: 2 x 2 km in 250 m tiles, ~42 million
        points (about 15 s on two cores, LAZ writing included); scale it with
        ``width_m``/``height_m`` (points grow with the area) and generate it
        with ``keep_truth=False``.
    **overrides
        Any :class:`SurveySpec` field, e.g. ``seed=3`` or ``width_m=4000``.

    Returns
    -------
    SurveySpec
    """
    try:
        fields = _PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(_PRESETS)}") from None
    return SurveySpec(**{**fields, **overrides})
