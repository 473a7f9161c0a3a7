"""Synthetic airborne lidar surveys with known ground truth.

The demo, the test-suite and the benchmarks need surveys whose holes are known
exactly *and* arise for the reasons real holes do:

* **occlusion** (scan shadow): the laser cannot see the ground behind a
  building (or, partly, a tree crown) on the side away from the aircraft;
* **missed coverage**: a flight line was dropped (wind drift, aborted line), so
  a strip between its neighbours gets no pulse at all;
* **water**: the laser returns nothing from the water surface.

:func:`generate_survey` builds a scene (:func:`build_scene`), flies N-S
flight lines over it (:func:`flight_lines`), writes the returns as LAZ tiles
with an embedded CRS, and returns the truth: the surface model and, for every
pixel of the truth grid, whether the written points leave it empty and why
(:class:`HoleCause`).

How the simulation works
------------------------
The scene is analytic, so any window of it can be evaluated on its own and the
survey can be generated tile by tile with bounded memory:

* terrain: ``BASE_HEIGHT_M`` plus a few sinusoids of random direction and
  wavelength (100-450 m) whose amplitudes add up to ``terrain_relief_m / 2``;
* one river crossing the scene west to east (a meandering band of constant
  N-S width, flat water surface 1 m below the lowest terrain along its centre
  line, banks blended down to it over ``RIVER_BANK_WIDTH_M``);
* buildings: rotated rectangles (random orientation, sides 10-40 m, total
  height 6-25 m), half with flat roofs, half with gable roofs whose ridge runs
  along the long side; they never overlap each other, the river or its banks;
* trees: round crowns (radius 3-8 m, 5-20 m tall) shaped as a flattened
  spherical cap, never on buildings or in the river; crowns may overlap.

Coordinates inside the module are *local*: ``u`` metres east of ``x_min`` and
``v`` metres north of ``y_min`` (keeps float64 arithmetic exact enough and the
same in every tile). The scene is sampled on a *fine grid* of cells
``resolution / k`` wide (``k`` chosen so that cells are at most 0.25 m),
aligned to the truth grid; that raster decides what surface each pulse hits,
while heights of returns are evaluated analytically at the pulse position.

Each flight line scans across track, so a pulse travels in the vertical plane
of constant ``y`` through the sensor. A fine cell at horizontal distance
``d = u - u_sensor > 0`` with surface height ``h`` is visible iff its
elevation slope ``(h - H) / d`` (``H`` the sensor height) is at least the
running maximum of that slope over all cells between the sensor and it
(``np.maximum.accumulate`` along each row; mirrored west of the sensor).
An object can only hide a cell within ``(z_max - z_min) * d_max / (H - z_max)``
of it, so each tile is evaluated with that much padding east and west, which
makes every tile's result identical to a whole-scene computation.

Pulses lie on a regular across/along-track grid of ``pulse_spacing_m`` per
line, jittered by up to +-40 % of the spacing with a counter-based hash of
(seed, line, pulse indices) -- not a sequential random generator -- so a pulse
is the same whatever the tiling. A pulse aimed at a visible cell returns from
the top surface there (roof: class 6; ground: class 2; canopy: class 5, and
with probability ``canopy_penetration`` a second, last return from the ground
below). A pulse aimed at a cell hidden by a building is dropped (it would hit
a wall); one hidden only by a tree crown reaches the ground with probability
``canopy_penetration``. Pulses over water return nothing.

Coordinates are written at 0.01 m. A point whose rounded position lies exactly
on a truth-pixel edge is moved 1 cm back to the side it came from, so binning
the decoded coordinates with ``floor(x / resolution)`` can never be ambiguous
and the truth hole mask (computed from the very integers that are written) is
exactly the set of empty pixels.

Apart from the LAZ writer (:func:`write_tile`), everything here is pure.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import enum
import math
import os
import pathlib
import time
import warnings
from dataclasses import dataclass, field
from typing import Any

import affine
import numpy as np

__all__ = [
    "BASE_HEIGHT_M",
    "Buildings",
    "FlightLine",
    "HoleCause",
    "River",
    "Scene",
    "SurfaceKind",
    "SurveySpec",
    "SyntheticSurvey",
    "Terrain",
    "Trees",
    "build_scene",
    "flight_lines",
    "generate_survey",
    "preset",
    "write_tile",
]

#: Height of the terrain's mean level; the flight altitude is measured from it.
BASE_HEIGHT_M = 50.0
#: Width over which the terrain is blended down to the water level beside the river.
RIVER_BANK_WIDTH_M = 15.0
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


class SurfaceKind(enum.IntEnum):
    """What the top surface of a fine-grid cell is."""

    GROUND = 0
    BUILDING = 1
    TREE = 2
    WATER = 3


# ---------------------------------------------------------------------------
# Specification
# ---------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------
# Scene
# ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Terrain:
    """Rolling terrain: ``base_height + sum(a_i * sin(k_i . (u, v) + phase_i))``.

    Attributes
    ----------
    base_height : float
    amplitudes, wavevector_u, wavevector_v, phases : ndarray of float64
        One entry per sinusoid; wave vectors in radians per metre.
    """

    base_height: float
    amplitudes: np.ndarray
    wavevector_u: np.ndarray
    wavevector_v: np.ndarray
    phases: np.ndarray

    def height(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Terrain height at local coordinates (arrays broadcast against each other)."""
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        z = np.full(np.broadcast_shapes(u.shape, v.shape), self.base_height)
        for amplitude, ku, kv, phase in zip(self.amplitudes, self.wavevector_u, self.wavevector_v, self.phases):
            z += amplitude * np.sin(ku * u + kv * v + phase)
        return z

    def height_grid(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Terrain height on the grid of 1-D ``u`` (columns) and ``v`` (rows).

        Uses ``sin(a + b) = sin a cos b + cos a sin b`` so that only 1-D sines
        are evaluated: the fine raster of a tile costs a few multiply-adds per
        cell instead of one sine per cell and wave. Each cell's value depends
        only on its own coordinates, whatever the window.
        """
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        z = np.full((len(v), len(u)), self.base_height)
        for amplitude, ku, kv, phase in zip(self.amplitudes, self.wavevector_u, self.wavevector_v, self.phases):
            across = ku * u + phase
            along = kv * v
            z += (amplitude * np.sin(across))[None, :] * np.cos(along)[:, None]
            z += (amplitude * np.cos(across))[None, :] * np.sin(along)[:, None]
        return z

    @property
    def height_range(self) -> tuple[float, float]:
        """Bounds that the terrain can never leave."""
        total = float(np.sum(np.abs(self.amplitudes)))
        return self.base_height - total, self.base_height + total


@dataclass(frozen=True, eq=False)
class River:
    """A west-east river: water where ``|v - centre(u)| < half_width``.

    The centre line is ``center_v + meander_amplitude * sin(2 pi u / meander_wavelength + phase)``;
    the water surface is flat at ``water_level``. Being a band of constant N-S
    width it is an exact polygon (see :meth:`polygon`).
    """

    center_v: float
    meander_amplitude: float
    meander_wavelength: float
    phase: float
    half_width: float
    water_level: float
    bank_width: float = RIVER_BANK_WIDTH_M

    def centerline_v(self, u: np.ndarray) -> np.ndarray:
        return self.center_v + self.meander_amplitude * np.sin(
            2.0 * np.pi * np.asarray(u) / self.meander_wavelength + self.phase
        )

    def offset(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Signed N-S distance from the centre line."""
        return np.asarray(v) - self.centerline_v(u)

    def is_water(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.abs(self.offset(u, v)) < self.half_width

    def shape_ground(self, ground: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Blend terrain down to just above the water level near the river (the banks)."""
        distance = np.abs(self.offset(u, v)) - self.half_width
        t = np.clip(distance / self.bank_width, 0.0, 1.0)
        smooth = t * t * (3.0 - 2.0 * t)
        bank_top = self.water_level + RIVER_BANK_HEIGHT_M
        shaped = bank_top + (ground - bank_top) * smooth
        return np.where(distance < 0, self.water_level - 1.0, shaped)

    @property
    def max_slope(self) -> float:
        return 2.0 * np.pi * self.meander_amplitude / self.meander_wavelength

    def polygon(self, u_min: float, u_max: float, step: float = 1.0) -> np.ndarray:
        """The water outline between ``u_min`` and ``u_max`` as an (N, 2) ring of local coordinates."""
        u = np.linspace(u_min, u_max, max(2, int(math.ceil((u_max - u_min) / step)) + 1))
        centre = self.centerline_v(u)
        south = np.column_stack([u, centre - self.half_width])
        north = np.column_stack([u[::-1], (centre + self.half_width)[::-1]])
        return np.vstack([south, north, south[:1]])


@dataclass(frozen=True, eq=False)
class Buildings:
    """Rotated rectangular buildings, as parallel arrays (one entry per building).

    Attributes
    ----------
    center_u, center_v : ndarray
        Footprint centre, local metres.
    half_length, half_width : ndarray
        Half sides; the ridge of a gable roof runs along the length axis.
    angle : ndarray
        Direction of the length axis, radians counter-clockwise from east.
    eave_z, ridge_z : ndarray
        Absolute heights of the eaves and the ridge (equal for a flat roof).
    """

    center_u: np.ndarray
    center_v: np.ndarray
    half_length: np.ndarray
    half_width: np.ndarray
    angle: np.ndarray
    eave_z: np.ndarray
    ridge_z: np.ndarray

    @classmethod
    def from_records(cls, records: list[dict[str, float]] | tuple[dict[str, float], ...]) -> Buildings:
        """Build from dicts with the attribute names as keys (``ridge_z`` defaults to ``eave_z``)."""
        names = [f.name for f in dataclasses.fields(cls)]
        columns: dict[str, list[float]] = {name: [] for name in names}
        for record in records:
            for name in names:
                if name == "ridge_z":
                    columns[name].append(float(record.get("ridge_z", record["eave_z"])))
                else:
                    columns[name].append(float(record[name]))
        return cls(**{name: np.asarray(values, dtype=np.float64) for name, values in columns.items()})

    @classmethod
    def empty(cls) -> Buildings:
        return cls.from_records([])

    def __len__(self) -> int:
        return len(self.center_u)

    @property
    def bounding_radius(self) -> np.ndarray:
        return np.hypot(self.half_length, self.half_width)

    @property
    def is_gable(self) -> np.ndarray:
        return self.ridge_z > self.eave_z

    def local_axes(self, index: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Coordinates along the length and width axes of building ``index``."""
        du = u - self.center_u[index]
        dv = v - self.center_v[index]
        cos, sin = np.cos(self.angle[index]), np.sin(self.angle[index])
        return du * cos + dv * sin, -du * sin + dv * cos

    def roof_height(self, index: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Roof height of building ``index`` at ``(u, v)`` (extended flat beyond the eaves)."""
        _, across = self.local_axes(index, u, v)
        fraction = np.clip(np.abs(across) / self.half_width[index], 0.0, 1.0)
        return self.ridge_z[index] - (self.ridge_z[index] - self.eave_z[index]) * fraction

    def distance_to_footprint(self, index: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Horizontal distance from ``(u, v)`` to the footprint (0 inside)."""
        along, across = self.local_axes(index, u, v)
        return np.hypot(
            np.maximum(np.abs(along) - self.half_length[index], 0.0),
            np.maximum(np.abs(across) - self.half_width[index], 0.0),
        )


@dataclass(frozen=True, eq=False)
class Trees:
    """Trees with round crowns, as parallel arrays.

    The canopy is a flattened spherical cap:
    ``top_z - edge_drop * (1 - sqrt(1 - (r / crown_radius)**2))`` for
    ``r < crown_radius``.
    """

    center_u: np.ndarray
    center_v: np.ndarray
    crown_radius: np.ndarray
    top_z: np.ndarray
    edge_drop: np.ndarray

    @classmethod
    def from_records(cls, records: list[dict[str, float]] | tuple[dict[str, float], ...]) -> Trees:
        names = [f.name for f in dataclasses.fields(cls)]
        return cls(**{name: np.asarray([float(r[name]) for r in records], dtype=np.float64) for name in names})

    @classmethod
    def empty(cls) -> Trees:
        return cls.from_records([])

    def __len__(self) -> int:
        return len(self.center_u)

    def canopy_height(self, index: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Canopy height of tree ``index`` at ``(u, v)`` (the crown edge height outside)."""
        du = u - self.center_u[index]
        dv = v - self.center_v[index]
        radius = self.crown_radius[index]
        fraction = np.minimum((du * du + dv * dv) / (radius * radius), 1.0)
        return self.top_z[index] - self.edge_drop[index] * (1.0 - np.sqrt(1.0 - fraction))


@dataclass(frozen=True, eq=False)
class SceneRaster:
    """The scene sampled on a window of the fine grid (row 0 is the southernmost row).

    Attributes
    ----------
    column0, row0 : int
        Fine-grid indices of the window's first column (west) and row (south).
    surface : ndarray of float64
        Top surface height (canopy, roof, ground or water level).
    hard_surface : ndarray of float64
        Top surface ignoring tree crowns (what blocks a pulse for sure).
    kind : ndarray of uint8
        :class:`SurfaceKind` of the top surface.
    object_index : ndarray of int32
        Index of the building or tree forming the top surface, -1 otherwise.
    """

    column0: int
    row0: int
    surface: np.ndarray
    hard_surface: np.ndarray
    kind: np.ndarray
    object_index: np.ndarray


@dataclass(frozen=True, eq=False)
class Scene:
    """An analytic scene: terrain, an optional river, buildings and trees, in local coordinates."""

    width_m: float
    height_m: float
    terrain: Terrain
    river: River | None
    buildings: Buildings
    trees: Trees

    def ground_height(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Bare-earth height (river bed under water)."""
        ground = self.terrain.height(u, v)
        if self.river is not None:
            ground = self.river.shape_ground(ground, u, v)
        return ground

    def height_range(self) -> tuple[float, float]:
        """Bounds of every surface in the scene, for the occlusion padding."""
        low, high = self.terrain.height_range
        if self.river is not None:
            low = min(low, self.river.water_level - 1.0)
        if len(self.buildings):
            high = max(high, float(self.buildings.ridge_z.max()))
        if len(self.trees):
            high = max(high, float(self.trees.top_z.max()))
        return low, high

    def rasterize(self, column0: int, row0: int, n_columns: int, n_rows: int, cell: float) -> SceneRaster:
        """Sample the scene at the centres of a window of the fine grid of cell size ``cell``.

        Each cell's values depend only on its global indices, never on the
        window, so overlapping windows agree exactly.
        """
        u = (np.arange(column0, column0 + n_columns) + 0.5) * cell
        v = (np.arange(row0, row0 + n_rows) + 0.5) * cell
        surface = self.terrain.height_grid(u, v)
        if self.river is not None:
            surface = self.river.shape_ground(surface, u[None, :], v[:, None])
        kind = np.zeros(surface.shape, dtype=np.uint8)
        object_index = np.full(surface.shape, -1, dtype=np.int32)
        u_lo, u_hi, v_lo, v_hi = u[0] - cell, u[-1] + cell, v[0] - cell, v[-1] + cell

        buildings = self.buildings
        if len(buildings):
            radius = buildings.bounding_radius
            near = _objects_near(buildings.center_u, buildings.center_v, radius, (u_lo, u_hi, v_lo, v_hi))
            for index in near:
                columns, rows = _cell_span(
                    u, v, buildings.center_u[index], buildings.center_v[index], radius[index], column0, row0, cell
                )
                if columns is None:
                    continue
                uu, vv = u[columns][None, :], v[rows][:, None]
                along, across = buildings.local_axes(index, uu, vv)
                inside = (np.abs(along) <= buildings.half_length[index]) & (
                    np.abs(across) <= buildings.half_width[index]
                )
                roof = buildings.roof_height(index, uu, vv)
                window = surface[rows, columns]
                take = inside & (roof > window)
                window[take] = roof[take]
                kind[rows, columns][take] = SurfaceKind.BUILDING
                object_index[rows, columns][take] = index
        hard_surface = surface.copy()

        trees = self.trees
        if len(trees):
            radius = trees.crown_radius
            near = _objects_near(trees.center_u, trees.center_v, radius, (u_lo, u_hi, v_lo, v_hi))
            for index in near:
                columns, rows = _cell_span(
                    u, v, trees.center_u[index], trees.center_v[index], radius[index], column0, row0, cell
                )
                if columns is None:
                    continue
                uu, vv = u[columns][None, :], v[rows][:, None]
                du, dv = uu - trees.center_u[index], vv - trees.center_v[index]
                inside = du * du + dv * dv < radius[index] * radius[index]
                canopy = trees.canopy_height(index, uu, vv)
                window = surface[rows, columns]
                take = inside & (canopy > window)
                window[take] = canopy[take]
                kind[rows, columns][take] = SurfaceKind.TREE
                object_index[rows, columns][take] = index

        if self.river is not None:
            water = self.river.is_water(u[None, :], v[:, None])
            surface[water] = self.river.water_level
            hard_surface[water] = self.river.water_level
            kind[water] = SurfaceKind.WATER
            object_index[water] = -1
        return SceneRaster(column0, row0, surface, hard_surface, kind, object_index)


def _objects_near(
    center_u: np.ndarray, center_v: np.ndarray, radius: np.ndarray, bounds: tuple[float, float, float, float]
) -> np.ndarray:
    """Indices of the round objects (centre, radius) that reach into a (u_lo, u_hi, v_lo, v_hi) window."""
    u_lo, u_hi, v_lo, v_hi = bounds
    return np.flatnonzero(
        (center_u + radius >= u_lo)
        & (center_u - radius <= u_hi)
        & (center_v + radius >= v_lo)
        & (center_v - radius <= v_hi)
    )


def _cell_span(
    u: np.ndarray, v: np.ndarray, center_u: float, center_v: float, radius: float, column0: int, row0: int, cell: float
) -> tuple[slice | None, slice | None]:
    """Slices of a window's cells whose centres may lie within ``radius`` of a point."""
    c0 = max(0, math.floor((center_u - radius) / cell) - column0)
    c1 = min(len(u), math.ceil((center_u + radius) / cell) - column0 + 1)
    r0 = max(0, math.floor((center_v - radius) / cell) - row0)
    r1 = min(len(v), math.ceil((center_v + radius) / cell) - row0 + 1)
    if c0 >= c1 or r0 >= r1:
        return None, None
    return slice(c0, c1), slice(r0, r1)


def build_scene(spec: SurveySpec) -> Scene:
    """Draw the scene of a spec: terrain, river, buildings and trees.

    Each component draws from its own random stream (seeded by ``spec.seed``
    and a component number), so e.g. changing the tree density leaves the
    terrain and the buildings unchanged. Object centres lie inside the extent;
    footprints may reach beyond it.

    Parameters
    ----------
    spec : SurveySpec

    Returns
    -------
    Scene
    """
    width, height = spec.width_m, spec.height_m
    area_ha = width * height / 10_000.0

    rng = np.random.default_rng([spec.seed, 1])
    n_waves = 4
    weights = rng.uniform(0.5, 1.0, n_waves)
    amplitudes = weights / weights.sum() * spec.terrain_relief_m / 2.0
    wavelengths = rng.uniform(100.0, 450.0, n_waves)
    directions = rng.uniform(0.0, 2.0 * np.pi, n_waves)
    wavenumbers = 2.0 * np.pi / wavelengths
    terrain = Terrain(
        base_height=BASE_HEIGHT_M,
        amplitudes=amplitudes,
        wavevector_u=wavenumbers * np.cos(directions),
        wavevector_v=wavenumbers * np.sin(directions),
        phases=rng.uniform(0.0, 2.0 * np.pi, n_waves),
    )

    river = None
    if spec.water and spec.water_width_m > 0:
        rng = np.random.default_rng([spec.seed, 2])
        half_width = spec.water_width_m / 2.0
        river_center_v = rng.uniform(0.35, 0.65) * height
        amplitude = min(0.12 * height, 15.0) * rng.uniform(0.3, 1.0)
        wavelength = max(width, 200.0) * rng.uniform(0.7, 1.3)
        phase = rng.uniform(0.0, 2.0 * np.pi)
        draft = River(river_center_v, amplitude, wavelength, phase, half_width, water_level=0.0)
        along = np.linspace(-RIVER_BANK_WIDTH_M, width + RIVER_BANK_WIDTH_M, int(width) + 32)
        water_level = float(terrain.height(along, draft.centerline_v(along)).min()) - 1.0
        river = dataclasses.replace(draft, water_level=water_level)

    def ground(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        z = terrain.height(u, v)
        return river.shape_ground(z, u, v) if river is not None else z

    def clear_of_river(u: np.ndarray, v: np.ndarray, radius: np.ndarray, margin: float) -> np.ndarray:
        if river is None:
            return np.ones(np.shape(u), dtype=bool)
        reach = radius * (1.0 + river.max_slope)
        return np.abs(river.offset(u, v)) - reach > river.half_width + margin

    # Buildings: candidates, then greedy rejection of overlaps in draw order.
    rng = np.random.default_rng([spec.seed, 3])
    n = rng.poisson(spec.building_density * area_ha)
    sides = rng.uniform(10.0, 40.0, (n, 2))
    half_length, half_width = sides.max(axis=1) / 2.0, sides.min(axis=1) / 2.0
    center_u, center_v = rng.uniform(0.0, width, n), rng.uniform(0.0, height, n)
    angle = rng.uniform(0.0, np.pi, n)
    total_height = rng.uniform(6.0, 25.0, n)
    gable = rng.random(n) < 0.5
    pitch = np.radians(rng.uniform(20.0, 40.0, n))
    rise = np.where(gable, np.minimum(half_width * np.tan(pitch), total_height - 3.0), 0.0)
    radius = np.hypot(half_length, half_width)
    keep = clear_of_river(center_u, center_v, radius, RIVER_BANK_WIDTH_M / 2.0)
    keep = _greedy_non_overlapping(center_u, center_v, radius, gap=3.0, allowed=keep)
    ground_at_center = ground(center_u, center_v)
    buildings = Buildings(
        center_u=center_u[keep],
        center_v=center_v[keep],
        half_length=half_length[keep],
        half_width=half_width[keep],
        angle=angle[keep],
        eave_z=(ground_at_center + total_height - rise)[keep],
        ridge_z=(ground_at_center + total_height)[keep],
    )

    # Trees: taller trees have wider crowns; none on buildings or in the river.
    rng = np.random.default_rng([spec.seed, 4])
    n = rng.poisson(spec.tree_density * area_ha)
    tree_height = rng.uniform(5.0, 20.0, n)
    crown_radius = np.clip(3.0 + 5.0 * (tree_height - 5.0) / 15.0 * rng.uniform(0.6, 1.2, n), 3.0, 8.0)
    tree_u, tree_v = rng.uniform(0.0, width, n), rng.uniform(0.0, height, n)
    keep = clear_of_river(tree_u, tree_v, crown_radius, 2.0)
    keep &= _clear_of_buildings(buildings, tree_u, tree_v, crown_radius + 1.0)
    trees = Trees(
        center_u=tree_u[keep],
        center_v=tree_v[keep],
        crown_radius=crown_radius[keep],
        top_z=(ground(tree_u, tree_v) + tree_height)[keep],
        edge_drop=np.minimum(0.6 * crown_radius, 0.45 * tree_height)[keep],
    )
    return Scene(width, height, terrain, river, buildings, trees)


def _greedy_non_overlapping(
    center_u: np.ndarray, center_v: np.ndarray, radius: np.ndarray, *, gap: float, allowed: np.ndarray | None = None
) -> np.ndarray:
    """Keep objects in order, dropping any whose bounding circle comes within ``gap`` of a kept one."""
    from scipy.spatial import cKDTree

    n = len(center_u)
    allowed = np.ones(n, dtype=bool) if allowed is None else allowed
    kept = np.zeros(n, dtype=bool)
    if n == 0:
        return kept
    points = np.column_stack([center_u, center_v])
    neighbours = cKDTree(points).query_ball_point(points, r=2.0 * float(radius.max()) + gap)
    for index in range(n):
        if not allowed[index]:
            continue
        others = [j for j in neighbours[index] if j < index and kept[j]]
        if others:
            near = np.asarray(others)
            distance = np.hypot(center_u[near] - center_u[index], center_v[near] - center_v[index])
            if np.any(distance < radius[near] + radius[index] + gap):
                continue
        kept[index] = True
    return kept


def _clear_of_buildings(buildings: Buildings, u: np.ndarray, v: np.ndarray, clearance: np.ndarray) -> np.ndarray:
    """True where a point is farther than ``clearance`` from every building footprint."""
    from scipy.spatial import cKDTree

    clear = np.ones(len(u), dtype=bool)
    if len(buildings) == 0 or len(u) == 0:
        return clear
    tree = cKDTree(np.column_stack([buildings.center_u, buildings.center_v]))
    reach = float(buildings.bounding_radius.max() + clearance.max())
    candidates = tree.query_ball_point(np.column_stack([u, v]), r=reach)
    lengths = np.fromiter((len(c) for c in candidates), dtype=np.int64, count=len(u))
    if lengths.sum() == 0:
        return clear
    point = np.repeat(np.arange(len(u)), lengths)
    building = np.fromiter((j for c in candidates for j in c), dtype=np.int64, count=int(lengths.sum()))
    too_close = buildings.distance_to_footprint(building, u[point], v[point]) < clearance[point]
    clear[point[too_close]] = False
    return clear


# ---------------------------------------------------------------------------
# Acquisition geometry
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class FlightLine:
    """One N-S flight line.

    Attributes
    ----------
    index : int
        Position from west (0) to east.
    line_id : int
        ``index + 1``; written as the points' ``point_source_id``.
    u : float
        Sensor track, metres east of ``x_min``.
    x : float
        Sensor track in CRS metres.
    sensor_z : float
        Absolute sensor height.
    half_swath_m : float
        Half-width of the pulse pattern on the ground (``n_across * spacing / 2``).
    n_across, n_along : int
        Pulses per scan line and scan lines per flight line.
    northbound : bool
        Lines alternate direction; GPS time increases along the direction flown.
    start_time : float
        GPS time of the first scan line.
    flown : bool
        False for the dropped line (``SurveySpec.missed_line``), which yields no points.
    """

    index: int
    line_id: int
    u: float
    x: float
    sensor_z: float
    half_swath_m: float
    n_across: int
    n_along: int
    northbound: bool
    start_time: float
    flown: bool

    def covers(self, u: np.ndarray) -> np.ndarray:
        """Whether local eastings lie inside the swath."""
        return np.abs(np.asarray(u) - self.u) <= self.half_swath_m


def flight_lines(spec: SurveySpec) -> list[FlightLine]:
    """Lay out the flight lines of a spec, west to east, including the dropped one.

    Lines are spaced by ``swath * (1 - side_overlap)``; the westernmost
    swath starts 5 % of a swath west of the extent and lines are added until
    the extent is covered with the same margin in the east.

    Raises
    ------
    ValueError
        ``missed_line`` is not a line index, or dropping it leaves no
        uncovered strip of at least two truth pixels inside the extent (e.g.
        ``side_overlap >= 0.5``, where the neighbours' swaths still meet).
    """
    spacing_m = spec.pulse_spacing_m
    n_across = max(1, math.floor(spec.swath_width_m / spacing_m))
    half_swath = n_across * spacing_m / 2.0
    line_spacing = 2.0 * half_swath * (1.0 - spec.side_overlap)
    margin = 0.05 * 2.0 * half_swath
    first_u = half_swath - margin
    n_lines = max(1, math.ceil((spec.width_m + margin - (first_u + half_swath)) / line_spacing - 1e-9) + 1)
    n_along = math.floor(spec.height_m / spacing_m) + 2
    sensor_z = BASE_HEIGHT_M + spec.flight_altitude_m
    if spec.missed_line is not None and spec.missed_line >= n_lines:
        raise ValueError(
            f"SurveySpec.missed_line: line {spec.missed_line} does not exist; this survey has {n_lines} "
            f"flight lines (0..{n_lines - 1})"
        )
    lines = []
    for index in range(n_lines):
        u = first_u + index * line_spacing
        lines.append(
            FlightLine(
                index=index,
                line_id=index + 1,
                u=u,
                x=spec.x_min + u,
                sensor_z=sensor_z,
                half_swath_m=half_swath,
                n_across=n_across,
                n_along=n_along,
                northbound=index % 2 == 0,
                start_time=SURVEY_START_GPS_TIME + index * LINE_INTERVAL_S,
                flown=index != spec.missed_line,
            )
        )
    if spec.missed_line is not None:
        centres = (np.arange(spec.shape[1]) + 0.5) * spec.resolution
        covered = np.zeros(len(centres), dtype=bool)
        for line in lines:
            if line.flown:
                covered |= np.abs(centres - line.u) <= line.half_swath_m - spec.resolution / 2.0
        uncovered = int((~covered).sum())
        if uncovered < 2:
            raise ValueError(
                f"SurveySpec.missed_line: dropping line {spec.missed_line} leaves no uncovered strip in the "
                f"extent ({uncovered} truth pixel columns); swath {2 * half_swath:.1f} m with side_overlap="
                f"{spec.side_overlap} needs side_overlap < 0.5 and the line's gap inside the extent"
            )
    return lines


# ---------------------------------------------------------------------------
# Deterministic per-pulse randomness
# ---------------------------------------------------------------------------

_MASK64 = (1 << 64) - 1
_GOLDEN64 = 0x9E3779B97F4A7C15


def _mix64(z: np.ndarray) -> np.ndarray:
    """SplitMix64 finaliser on a uint64 array (wrapping arithmetic)."""
    z = z ^ (z >> np.uint64(30))
    z *= np.uint64(0xBF58476D1CE4E5B9)
    z ^= z >> np.uint64(27)
    z *= np.uint64(0x94D049BB133111EB)
    z ^= z >> np.uint64(31)
    return z


def _mix64_int(z: int) -> int:
    z &= _MASK64
    z ^= z >> 30
    z = (z * 0xBF58476D1CE4E5B9) & _MASK64
    z ^= z >> 27
    z = (z * 0x94D049BB133111EB) & _MASK64
    return z ^ (z >> 31)


def _pulse_keys(seed: int, line_index: int, across: np.ndarray, along: np.ndarray) -> np.ndarray:
    """A well-mixed 64-bit key per pulse, a pure function of (seed, line, indices)."""
    line_key = _mix64_int(_mix64_int(seed * _GOLDEN64 + 0x5EED) + line_index * _GOLDEN64)
    keys = (across.astype(np.uint64) << np.uint64(32)) | along.astype(np.uint64)
    return _mix64(keys ^ np.uint64(line_key))


def _uniform(keys: np.ndarray, stream: int) -> np.ndarray:
    """Uniform [0, 1) numbers, independent for each ``stream``."""
    z = _mix64(keys + np.uint64((stream + 1) * _GOLDEN64 & _MASK64))
    return (z >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))


def _approximately_normal(keys: np.ndarray, stream: int) -> np.ndarray:
    """Standard-normal-like numbers: the sum of the four 16-bit parts of one hash.

    An Irwin-Hall(4) variable rescaled to unit variance: bell-shaped, bounded
    at +-3.46, and several times cheaper than Box-Muller (no logarithm or
    trigonometry), which matters at millions of points per second.
    """
    z = _mix64(keys + np.uint64((stream + 1) * _GOLDEN64 & _MASK64))
    low16 = np.uint64(0xFFFF)
    total = (z & low16) + ((z >> np.uint64(16)) & low16) + ((z >> np.uint64(32)) & low16) + (z >> np.uint64(48))
    return (total.astype(np.float64) * (1.0 / 65536.0) - 2.0) * math.sqrt(3.0)


(
    _STREAM_JITTER_U,
    _STREAM_JITTER_V,
    _STREAM_PENETRATION,
    _STREAM_NOISE_FIRST,
    _STREAM_NOISE_SECOND,
    _STREAM_INTENSITY,
) = range(6)


# ---------------------------------------------------------------------------
# Simulation of one tile
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class _Layout:
    """Derived geometry shared by every tile of a survey."""

    resolution_cm: int
    fine_per_pixel: int  # fine cells per truth pixel along each axis
    fine_cell: float
    pad_cells: int
    n_rows: int
    n_cols: int
    tile_pixels: int


def _layout(spec: SurveySpec, scene: Scene, lines: list[FlightLine]) -> _Layout:
    resolution_cm = round(spec.resolution * _CENTIMETRES_PER_METRE)
    fine_per_pixel = max(2, math.ceil(spec.resolution / MAX_FINE_CELL_M - 1e-9))
    fine_cell = spec.resolution / fine_per_pixel
    z_low, z_high = scene.height_range()
    sensor_z = lines[0].sensor_z
    if sensor_z - z_high < 10.0:
        raise ValueError(
            f"SurveySpec.flight_altitude_m: the sensor ({sensor_z:.1f} m) must fly at least 10 m above the "
            f"highest surface ({z_high:.1f} m)"
        )
    farthest = lines[0].half_swath_m + spec.pulse_spacing_m
    pad_m = (z_high - z_low) * farthest / (sensor_z - z_high) + 2.0 * fine_cell
    rows, cols = spec.shape
    return _Layout(
        resolution_cm=resolution_cm,
        fine_per_pixel=fine_per_pixel,
        fine_cell=fine_cell,
        pad_cells=math.ceil(pad_m / fine_cell),
        n_rows=rows,
        n_cols=cols,
        tile_pixels=round(spec.tile_size_m / spec.resolution),
    )


@dataclass(frozen=True)
class _Tile:
    """A tile as truth-pixel ranges: columns from the west, rows from the *south*."""

    col0: int
    col1: int
    row0: int
    row1: int


def _tiles(layout: _Layout) -> list[_Tile]:
    step = layout.tile_pixels
    return [
        _Tile(c, min(c + step, layout.n_cols), r, min(r + step, layout.n_rows))
        for r in range(0, layout.n_rows, step)
        for c in range(0, layout.n_cols, step)
    ]


def _quantize_off_edges(metres: np.ndarray, resolution_cm: int) -> np.ndarray:
    """Round to whole centimetres, moving points that land on a pixel edge 1 cm back to their side."""
    scaled = metres * _CENTIMETRES_PER_METRE
    quantized = np.rint(scaled).astype(np.int64)
    on_edge = quantized % resolution_cm == 0
    if on_edge.any():
        quantized[on_edge] += np.where(scaled[on_edge] < quantized[on_edge], -1, 1)
    return quantized


def _visibility(surface: np.ndarray, cell_u: np.ndarray, sensor_u: float, sensor_z: float, reach: float) -> np.ndarray:
    """Which cells a sensor at ``(sensor_u, sensor_z)`` sees, scanning along each row.

    A cell is visible iff the slope ``(h - sensor_z) / |u - sensor_u|`` of the
    ray to it is at least every such slope between the sensor and it (a
    running maximum outward from the sensor on each side). Only cells within
    ``reach`` of the sensor track are evaluated (the rest are reported hidden):
    what lies between the sensor and a cell is always nearer than the cell.
    """
    visible = np.zeros(surface.shape, dtype=bool)
    distance = cell_u - sensor_u
    first = int(np.searchsorted(distance, -reach, side="left"))
    stop = int(np.searchsorted(distance, reach, side="right"))
    west = int(np.searchsorted(distance, 0.0, side="left"))  # cells [.., west) lie strictly west
    east = int(np.searchsorted(distance, 0.0, side="right"))  # cells [east, ..) lie strictly east
    visible[:, west:east] = True  # directly below the sensor
    if east < stop:
        slope = (surface[:, east:stop] - sensor_z) / distance[east:stop]
        visible[:, east:stop] = slope >= np.maximum.accumulate(slope, axis=1)
    if first < west:
        columns = slice(west - 1, first - 1 if first > 0 else None, -1)  # outward, westwards
        slope = (surface[:, columns] - sensor_z) / -distance[columns]
        visible[:, columns] = slope >= np.maximum.accumulate(slope, axis=1)
    return visible


@dataclass
class _TileResult:
    tile: _Tile
    points: dict[str, np.ndarray]  # integer centimetre coordinates and attributes
    dsm: np.ndarray | None = None  # south-up, float32
    cause: np.ndarray | None = None  # south-up, uint8
    count: np.ndarray | None = None  # south-up, uint32
    visible_fraction: np.ndarray | None = None  # south-up, float32


def _simulate_tile(
    spec: SurveySpec, scene: Scene, lines: list[FlightLine], layout: _Layout, tile: _Tile, keep_truth: bool
) -> _TileResult:
    k = layout.fine_per_pixel
    cell = layout.fine_cell
    res_cm = layout.resolution_cm
    n_core_cols = (tile.col1 - tile.col0) * k
    column0 = tile.col0 * k - layout.pad_cells
    raster = scene.rasterize(
        column0, tile.row0 * k, n_core_cols + 2 * layout.pad_cells, (tile.row1 - tile.row0) * k, cell
    )
    cell_u = (np.arange(column0, column0 + raster.surface.shape[1]) + 0.5) * cell
    u0, u1 = tile.col0 * spec.resolution, tile.col1 * spec.resolution
    bounds_cm = (tile.col0 * res_cm, tile.col1 * res_cm, tile.row0 * res_cm, tile.row1 * res_cm)

    flown = [
        line for line in lines if line.flown and line.u + line.half_swath_m >= u0 and line.u - line.half_swath_m < u1
    ]
    core = slice(layout.pad_cells, layout.pad_cells + n_core_cols)
    visible_any = np.zeros((raster.surface.shape[0], n_core_cols), dtype=bool) if keep_truth else None
    has_trees = bool(np.any(raster.kind == SurfaceKind.TREE))
    chunks = []
    for line in flown:
        reach = line.half_swath_m + cell
        visible = _visibility(raster.surface, cell_u, line.u, line.sensor_z, reach)
        visible_hard = _visibility(raster.hard_surface, cell_u, line.u, line.sensor_z, reach) if has_trees else visible
        chunk = _line_pulses(spec, scene, line, raster, visible, visible_hard, layout, bounds_cm)
        if chunk is not None:
            chunks.append(chunk)
        if keep_truth:
            visible_any |= visible[:, core] & line.covers(cell_u[core])[None, :]

    points = _concatenate(chunks)
    result = _TileResult(tile, points)
    if not keep_truth:
        return result

    n_rows, n_cols = tile.row1 - tile.row0, tile.col1 - tile.col0
    pixel = (points["y_cm"] // res_cm - tile.row0) * n_cols + (points["x_cm"] // res_cm - tile.col0)
    count = np.bincount(pixel, minlength=n_rows * n_cols).reshape(n_rows, n_cols).astype(np.uint32)

    def per_pixel(values: np.ndarray, reduce: str) -> np.ndarray:
        blocks = values.reshape(n_rows, k, n_cols, k)
        return blocks.max(axis=(1, 3)) if reduce == "max" else blocks.sum(axis=(1, 3))

    water = raster.kind[:, core] == SurfaceKind.WATER
    covered = np.zeros(n_core_cols, dtype=bool)
    for line in lines:
        if line.flown:
            covered |= line.covers(cell_u[core])
    visible_any &= ~water
    uncovered = ~covered[None, :] & ~water
    occluded = covered[None, :] & ~visible_any & ~water
    cells_per_pixel = k * k
    water_count = per_pixel(water, "sum")
    uncovered_count = per_pixel(uncovered, "sum")
    occluded_count = per_pixel(occluded, "sum")
    cause = np.where(
        2 * water_count >= cells_per_pixel,
        HoleCause.WATER,
        np.where(uncovered_count > occluded_count, HoleCause.MISSED_COVERAGE, HoleCause.OCCLUSION),
    ).astype(np.uint8)
    cause[count > 0] = HoleCause.NONE
    result.dsm = per_pixel(raster.surface[:, core], "max").astype(np.float32)
    result.cause = cause
    result.count = count
    result.visible_fraction = (per_pixel(visible_any, "sum") / cells_per_pixel).astype(np.float32)
    return result


_POINT_FIELDS = {
    "x_cm": np.int64,
    "y_cm": np.int64,
    "z_cm": np.int64,
    "intensity": np.uint16,
    "return_number": np.uint8,
    "number_of_returns": np.uint8,
    "classification": np.uint8,
    "scan_angle": np.float32,
    "point_source_id": np.uint16,
    "gps_time": np.float64,
    "scan_direction_flag": np.uint8,
    "edge_of_flight_line": np.uint8,
}


def _concatenate(chunks: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    if not chunks:
        return {name: np.zeros(0, dtype=dtype) for name, dtype in _POINT_FIELDS.items()}
    points = {name: np.concatenate([c[name] for c in chunks]) for name in _POINT_FIELDS}
    order = np.argsort(points["gps_time"], kind="stable")
    return {name: values[order] for name, values in points.items()}


def _index_range(low: float, high: float, origin: float, spacing: float, count: int) -> tuple[int, int]:
    """Indices ``i`` in ``[0, count)`` whose nominal position ``origin + (i + 0.5) * spacing`` may jitter into [low, high)."""
    first = max(0, math.floor((low - spacing - origin) / spacing - 0.5))
    last = min(count - 1, math.ceil((high + spacing - origin) / spacing - 0.5))
    return first, last


def _line_pulses(
    spec: SurveySpec,
    scene: Scene,
    line: FlightLine,
    raster: SceneRaster,
    visible: np.ndarray,
    visible_hard: np.ndarray,
    layout: _Layout,
    bounds_cm: tuple[int, int, int, int],
) -> dict[str, np.ndarray] | None:
    """The returns of one flight line's pulses that land in a tile."""
    spacing = spec.pulse_spacing_m
    res_cm = layout.resolution_cm
    x0_cm, x1_cm, y0_cm, y1_cm = bounds_cm
    swath_west = line.u - line.half_swath_m
    i_first, i_last = _index_range(x0_cm / 100.0, x1_cm / 100.0, swath_west, spacing, line.n_across)
    j_first, j_last = _index_range(y0_cm / 100.0, y1_cm / 100.0, 0.0, spacing, line.n_along)
    if i_first > i_last or j_first > j_last:
        return None
    across_range = np.arange(i_first, i_last + 1, dtype=np.int64)
    along_range = np.arange(j_first, j_last + 1, dtype=np.int64)
    across = np.tile(across_range, len(along_range))
    along = np.repeat(along_range, len(across_range))

    keys = _pulse_keys(spec.seed, line.index, across, along)
    jitter = 2.0 * PULSE_JITTER_FRACTION * spacing
    u = swath_west + (across + 0.5) * spacing + (_uniform(keys, _STREAM_JITTER_U) - 0.5) * jitter
    v = (along + 0.5) * spacing + (_uniform(keys, _STREAM_JITTER_V) - 0.5) * jitter
    x_cm = _quantize_off_edges(u, res_cm)
    y_cm = _quantize_off_edges(v, res_cm)
    inside = (x_cm >= x0_cm) & (x_cm < x1_cm) & (y_cm >= y0_cm) & (y_cm < y1_cm)

    k = layout.fine_per_pixel
    n_raster_cols = raster.surface.shape[1]
    fine = (y_cm * k // res_cm - raster.row0) * n_raster_cols + (x_cm * k // res_cm - raster.column0)
    fine = np.where(inside, fine, 0)
    kind = raster.kind.ravel()[fine]
    sees_top = visible.ravel()[fine]
    sees_hard = visible_hard.ravel()[fine]
    penetrates = _uniform(keys, _STREAM_PENETRATION) < spec.canopy_penetration
    land = inside & (kind != SurfaceKind.WATER)
    first = land & sees_top
    # a second (last) return from the ground under a crown the pulse first hit
    under_crown = first & (kind == SurfaceKind.TREE) & penetrates
    # a pulse whose target is hidden only by a tree crown reaches the ground sometimes
    through_crown = land & ~sees_top & sees_hard & penetrates

    first_idx = np.flatnonzero(first)
    ground_idx = np.flatnonzero(under_crown | through_crown)
    if len(first_idx) + len(ground_idx) == 0:
        return None
    pulse = np.concatenate([first_idx, ground_idx])
    n_first = len(first_idx)
    u_q = x_cm[pulse] / 100.0
    v_q = y_cm[pulse] / 100.0

    # surfaces: ground everywhere, then roofs and canopies for first returns on them
    point_kind = np.concatenate([kind[first_idx], np.full(len(ground_idx), SurfaceKind.GROUND, dtype=np.uint8)])
    obj = raster.object_index.ravel()[fine[pulse]]
    z = scene.ground_height(u_q, v_q)
    on_roof = np.flatnonzero(point_kind == SurfaceKind.BUILDING)
    z[on_roof] = scene.buildings.roof_height(obj[on_roof], u_q[on_roof], v_q[on_roof])
    on_canopy = np.flatnonzero(point_kind == SurfaceKind.TREE)
    z[on_canopy] = np.maximum(z[on_canopy], scene.trees.canopy_height(obj[on_canopy], u_q[on_canopy], v_q[on_canopy]))
    if spec.noise_m > 0:
        z[:n_first] += spec.noise_m * _approximately_normal(keys[first_idx], _STREAM_NOISE_FIRST)
        z[n_first:] += spec.noise_m * _approximately_normal(keys[ground_idx], _STREAM_NOISE_SECOND)

    classification = np.select(
        [point_kind == SurfaceKind.BUILDING, point_kind == SurfaceKind.TREE],
        [CLASS_BUILDING, CLASS_HIGH_VEGETATION],
        CLASS_GROUND,
    ).astype(np.uint8)
    is_second = np.zeros(len(pulse), dtype=bool)
    is_second[n_first:] = under_crown[ground_idx]
    return_number = np.where(is_second, 2, 1).astype(np.uint8)
    number_of_returns = np.where(is_second, 2, 1).astype(np.uint8)
    number_of_returns[:n_first][under_crown[first_idx]] = 2

    # intensity: material reflectance, falling with range squared, speckled
    reflectance = np.select(
        [point_kind == SurfaceKind.BUILDING, point_kind == SurfaceKind.TREE],
        [700.0 + 600.0 * ((obj * 0.6180339887) % 1.0), 180.0],
        420.0,
    )
    reflectance = np.where(is_second, 0.45 * reflectance, reflectance)
    horizontal = u_q - line.u
    height_above = line.sensor_z - z
    range_factor = (line.sensor_z - BASE_HEIGHT_M) ** 2 / (horizontal**2 + height_above**2)
    speckle = 0.8 + 0.4 * _uniform(keys[pulse], _STREAM_INTENSITY)
    intensity = np.clip(reflectance * range_factor * speckle, 1, 65535).astype(np.uint16)

    scan_line = along[pulse] if line.northbound else line.n_along - 1 - along[pulse]
    forward = scan_line % 2 == 0
    position_in_scan = np.where(forward, across[pulse], line.n_across - 1 - across[pulse])
    scan_period = spacing / FLIGHT_SPEED_M_S
    gps_time = line.start_time + (scan_line + position_in_scan / line.n_across) * scan_period
    return {
        "x_cm": x_cm[pulse],
        "y_cm": y_cm[pulse],
        "z_cm": np.rint(z * _CENTIMETRES_PER_METRE).astype(np.int64),
        "intensity": intensity,
        "return_number": return_number,
        "number_of_returns": number_of_returns,
        "classification": classification,
        "scan_angle": np.degrees(np.arctan2(horizontal, height_above)).astype(np.float32),
        "point_source_id": np.full(len(pulse), line.line_id, dtype=np.uint16),
        "gps_time": gps_time,
        "scan_direction_flag": forward.astype(np.uint8),
        "edge_of_flight_line": ((across[pulse] == 0) | (across[pulse] == line.n_across - 1)).astype(np.uint8),
    }


# ---------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------


def write_tile(
    path: str | os.PathLike,
    points: dict[str, np.ndarray],
    *,
    origin: tuple[float, float],
    crs: str,
    las_version: str = "1.4",
    compress: bool = True,
) -> None:
    """Write one tile's points as LAS/LAZ with the CRS embedded.

    Parameters
    ----------
    path : path-like
        File to (over)write.
    points : dict of ndarray
        ``x_cm``, ``y_cm`` (integer centimetres from ``origin``), ``z_cm``
        (integer centimetres) and the point attributes produced by the
        simulation.
    origin : (float, float)
        CRS coordinates of centimetre 0; becomes the header's x/y offset, so
        the stored integers are the centimetres (scales 0.01).
    crs : str
        Embedded as a WKT VLR for point format 6 (LAS 1.4); as GeoTIFF keys
        for point format 1 (LAS 1.2), as the LAS 1.2 specification requires.
    las_version : {"1.4", "1.2"}
    compress : bool
        LAZ through the lazrs backend if true.
    """
    import laspy
    import pyproj

    point_format = 6 if las_version == "1.4" else 1
    header = laspy.LasHeader(point_format=point_format, version=las_version)
    header.scales = np.array([_COORDINATE_SCALE] * 3)
    header.offsets = np.array([origin[0], origin[1], 0.0])
    header.add_crs(pyproj.CRS(crs))
    header.global_encoding.gps_time_type = True  # adjusted standard GPS time
    header.system_identifier = "holefill synthetic"
    header.generating_software = "holefill pipeline.synth"
    las = laspy.LasData(header)
    n = len(points["x_cm"])
    las.points = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    las.X = points["x_cm"].astype(np.int32)
    las.Y = points["y_cm"].astype(np.int32)
    las.Z = points["z_cm"].astype(np.int32)
    las.intensity = points["intensity"]
    las.return_number = points["return_number"]
    las.number_of_returns = points["number_of_returns"]
    las.classification = points["classification"]
    las.point_source_id = points["point_source_id"]
    las.gps_time = points["gps_time"]
    las.scan_direction_flag = points["scan_direction_flag"]
    las.edge_of_flight_line = points["edge_of_flight_line"]
    if point_format == 6:
        las.scan_angle = np.rint(points["scan_angle"] / 0.006).astype(np.int16)  # 0.006 degree units
    else:
        las.scan_angle_rank = np.rint(points["scan_angle"]).astype(np.int8)
    las.write(os.fspath(path), laz_backend=laspy.LazBackend.Lazrs if compress else None)


def _tile_name(x: float, y: float, compress: bool) -> str:
    def coordinate(value: float) -> str:
        rounded = round(value)
        return str(rounded) if abs(value - rounded) < 1e-6 else f"{value:.2f}".rstrip("0").rstrip(".")

    return f"synth_{coordinate(x)}_{coordinate(y)}.{'laz' if compress else 'las'}"


# ---------------------------------------------------------------------------
# Public entry point
# ---------------------------------------------------------------------------


@dataclass
class SyntheticSurvey:
    """A written synthetic survey and its truth.

    Attributes
    ----------
    spec : SurveySpec
    tiles : list of pathlib.Path
        Files written, west to east within south to north. Tiles without any
        point (e.g. entirely over water) are not written.
    truth_dsm : ndarray of float32, shape (rows, cols) or None
        Highest surface per truth pixel (max of the height field over the
        fine-grid cell centres): roofs, canopy, ground, and the water level over
        water. Defined everywhere, holes included, so fills can be scored.
    hole_cause : ndarray of uint8, shape (rows, cols) or None
        :class:`HoleCause` per pixel, nonzero exactly where the written points
        leave the pixel empty (binned from the very integers written). An
        empty pixel is WATER if at least half of its fine cells are water;
        otherwise MISSED_COVERAGE if more of its land cells lie outside every
        flown swath than inside a swath but unseen, else OCCLUSION.
    transform : affine.Affine
        ``from_origin(x_min, y_max, res, res)``.
    crs : str
    n_points : int
        Points written over all tiles.
    point_count : ndarray of uint32 or None
        Points per truth pixel (all returns).
    visible_fraction : ndarray of float32 or None
        Fraction of each pixel's fine cells that some flown line sees (not
        water). An empty pixel with a large visible fraction would be a
        sampling accident; the tests check there are essentially none.
    scene : Scene
        The scene, in local coordinates (metres from ``(x_min, y_min)``).
    flight_lines : list of FlightLine
        All planned lines, the dropped one with ``flown=False``.
    generation_seconds : float
        Wall time of the generation, LAZ writing included.
    """

    spec: SurveySpec
    tiles: list[pathlib.Path]
    truth_dsm: np.ndarray | None
    hole_cause: np.ndarray | None
    transform: affine.Affine
    crs: str
    n_points: int
    point_count: np.ndarray | None = None
    visible_fraction: np.ndarray | None = None
    scene: Scene | None = None
    flight_lines: list[FlightLine] = field(default_factory=list)
    generation_seconds: float = 0.0

    @property
    def hole_mask(self) -> np.ndarray | None:
        """True where the written points leave a truth pixel empty."""
        return None if self.hole_cause is None else self.hole_cause != HoleCause.NONE

    def water_polygon(self) -> Any:
        """The river's water outline over the extent as a shapely Polygon in CRS coordinates (None without water)."""
        if self.scene is None or self.scene.river is None:
            return None
        import shapely

        ring = self.scene.river.polygon(0.0, self.spec.width_m) + (self.spec.x_min, self.spec.y_min)
        return shapely.Polygon(ring)

    def building_footprints(self) -> list[Any]:
        """Building footprints as shapely Polygons in CRS coordinates (same order as ``scene.buildings``)."""
        if self.scene is None:
            return []
        import shapely

        buildings = self.scene.buildings
        corners = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
        footprints = []
        for index in range(len(buildings)):
            along = corners[:, 0] * buildings.half_length[index]
            across = corners[:, 1] * buildings.half_width[index]
            cos, sin = math.cos(buildings.angle[index]), math.sin(buildings.angle[index])
            x = self.spec.x_min + buildings.center_u[index] + along * cos - across * sin
            y = self.spec.y_min + buildings.center_v[index] + along * sin + across * cos
            footprints.append(shapely.Polygon(np.column_stack([x, y])))
        return footprints

    def cause_counts(self) -> dict[HoleCause, int]:
        """Number of truth pixels per cause (``NONE`` included)."""
        if self.hole_cause is None:
            raise ValueError("the truth was not kept (generate_survey(..., keep_truth=False))")
        counts = np.bincount(self.hole_cause.ravel(), minlength=len(HoleCause))
        return {cause: int(counts[cause]) for cause in HoleCause}


def generate_survey(
    out_dir: str | os.PathLike,
    spec: SurveySpec = SurveySpec(),
    *,
    keep_truth: bool = True,
    scene: Scene | None = None,
) -> SyntheticSurvey:
    """Simulate an airborne lidar survey, write it as LAZ tiles and return its truth.

    Tiles are generated and written one at a time, so memory is bounded by one
    tile (plus the truth arrays when ``keep_truth``). The result depends only
    on ``spec`` (and ``scene``), not on the tiling: the same pulses, points and
    truth come out for any ``tile_size_m``.

    Parameters
    ----------
    out_dir : path-like
        Folder for the tiles (created if needed); files ``synth_{x}_{y}.laz``
        named after their lower-left corner are overwritten.
    spec : SurveySpec
    keep_truth : bool
        Compute and return the truth rasters. False for huge benchmark surveys:
        the truth arrays are then None and nothing grows with the survey size.
    scene : Scene, optional
        Use this scene instead of :func:`build_scene(spec) <build_scene>`
        (e.g. a single hand-placed building in a test).

    Returns
    -------
    SyntheticSurvey

    Raises
    ------
    ValueError
        The spec is inconsistent (see :class:`SurveySpec` and
        :func:`flight_lines`) or the sensor does not clear the scene.
    """
    started = time.perf_counter()
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    scene = build_scene(spec) if scene is None else scene
    lines = flight_lines(spec)
    layout = _layout(spec, scene, lines)
    rows, cols = layout.n_rows, layout.n_cols
    truth_shape = (rows, cols) if keep_truth else (0, 0)
    truth_dsm = np.empty(truth_shape, dtype=np.float32)
    hole_cause = np.empty(truth_shape, dtype=np.uint8)
    point_count = np.empty(truth_shape, dtype=np.uint32)
    visible_fraction = np.empty(truth_shape, dtype=np.float32)
    written: list[pathlib.Path] = []
    n_points = 0
    # One background writer: the next tile is simulated (numpy releases the GIL)
    # while the previous one is compressed; at most two tiles are in memory.
    writer = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="synth-writer")
    pending: concurrent.futures.Future | None = None
    try:
        for tile in _tiles(layout):
            result = _simulate_tile(spec, scene, lines, layout, tile, keep_truth)
            if keep_truth:
                assert result.dsm is not None and result.cause is not None
                assert result.count is not None and result.visible_fraction is not None
                # south-up tile arrays -> north-up truth grid
                top, bottom = rows - tile.row1, rows - tile.row0
                window = (slice(top, bottom), slice(tile.col0, tile.col1))
                truth_dsm[window] = result.dsm[::-1]
                hole_cause[window] = result.cause[::-1]
                point_count[window] = result.count[::-1]
                visible_fraction[window] = result.visible_fraction[::-1]
            n = len(result.points["x_cm"])
            if n == 0:
                continue
            x0 = spec.x_min + tile.col0 * spec.resolution
            y0 = spec.y_min + tile.row0 * spec.resolution
            points = dict(result.points)
            points["x_cm"] = points["x_cm"] - tile.col0 * layout.resolution_cm
            points["y_cm"] = points["y_cm"] - tile.row0 * layout.resolution_cm
            path = out_dir / _tile_name(x0, y0, spec.compress)
            if pending is not None:
                pending.result()
            pending = writer.submit(
                write_tile,
                path,
                points,
                origin=(x0, y0),
                crs=spec.crs,
                las_version=spec.las_version,
                compress=spec.compress,
            )
            written.append(path)
            n_points += n
        if pending is not None:
            pending.result()
    finally:
        writer.shutdown(wait=True, cancel_futures=True)
    stale = sorted(set(out_dir.glob("synth_*.la[sz]")) - set(written))
    if stale:
        warnings.warn(
            f"{out_dir}: {len(stale)} synth_* tile(s) not written by this survey remain there "
            f"(e.g. {stale[0].name}); readers of the folder will mix surveys",
            stacklevel=2,
        )
    return SyntheticSurvey(
        spec=spec,
        tiles=written,
        truth_dsm=truth_dsm if keep_truth else None,
        hole_cause=hole_cause if keep_truth else None,
        transform=spec.transform,
        crs=spec.crs,
        n_points=n_points,
        point_count=point_count if keep_truth else None,
        visible_fraction=visible_fraction if keep_truth else None,
        scene=scene,
        flight_lines=lines,
        generation_seconds=time.perf_counter() - started,
    )


def write_truth(survey: SyntheticSurvey, folder: str | os.PathLike) -> dict[str, pathlib.Path]:
    """Write a survey's truth beside its tiles, as GIS files a user can open and score against.

    Files: ``truth_dsm.tif`` (highest surface per pixel), ``truth_hole_cause.tif``
    (``HoleCause`` codes), ``survey_area.gpkg`` (the planned rectangle: the AOI) and
    ``water.gpkg`` (the river polygon, when there is water).

    Returns
    -------
    dict of str to pathlib.Path
        ``dsm``, ``hole_cause``, ``survey_area`` and, with water, ``water``.
    """
    import pyproj
    import shapely

    from .io.raster import write_cog
    from .io.vector import write_layer

    if survey.truth_dsm is None or survey.hole_cause is None:
        raise ValueError("the survey was generated with keep_truth=False: there is no truth to write")
    folder = pathlib.Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    crs = pyproj.CRS.from_user_input(survey.crs).to_wkt()
    spec = survey.spec
    paths = {
        "dsm": write_cog(folder / "truth_dsm.tif", survey.truth_dsm, transform=survey.transform, crs_wkt=crs),
        "hole_cause": write_cog(
            folder / "truth_hole_cause.tif",
            survey.hole_cause.astype(np.uint8),
            transform=survey.transform,
            crs_wkt=crs,
            nodata=None,
            description="0 none, 1 occlusion, 2 water, 3 missed coverage",
        ),  # fmt: skip
        "survey_area": write_layer(
            folder / "survey_area.gpkg",
            "survey_area",
            [{"name": "planned survey area"}],
            [shapely.box(spec.x_min, spec.y_min, spec.x_max, spec.y_max)],
            crs_wkt=crs,
        ),  # fmt: skip
    }
    water = survey.water_polygon()
    if water is not None and not water.is_empty:
        paths["water"] = write_layer(folder / "water.gpkg", "water", [{"name": "river"}], [water], crs_wkt=crs)
    return paths
