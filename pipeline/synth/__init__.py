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
  N-S width, water surface 1 m below the lowest terrain along its centre
  line, flat or falling eastward by ``river_fall_m_per_km``, banks blended
  down to it over ``RIVER_BANK_WIDTH_M``);
* optionally (``lakes``) elliptic lakes 20-80 m across with flat water, the
  terrain blended down to a shore just above it, and (``canal``) a straight
  N-S canal between quay walls with a street and a row of tall houses along
  each quay (:mod:`.water_bodies`); every water body's pixels are water in the truth;
* buildings: rotated rectangles (random orientation, sides 10-40 m, total
  height 6-25 m), half with flat roofs, half with gable roofs whose ridge runs
  along the long side; they never overlap each other, the river or its banks;
* trees: round crowns (radius 3-8 m, 5-20 m tall) shaped as a flattened
  spherical cap, never on buildings or in the river; crowns may overlap.

Coordinates inside the package are *local*: ``u`` metres east of ``x_min`` and
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

Apart from the LAZ writer (:func:`write_tile`) and :func:`write_truth`, everything
here is pure.

Modules, in the order of the simulation
---------------------------------------
``spec``
    :class:`SurveySpec`, :func:`preset`, :class:`HoleCause`, :class:`SurfaceKind`, constants.
``scene``
    The analytic scene (:class:`Terrain`, :class:`River`, :class:`Buildings`,
    :class:`Trees`, :class:`Scene`) and its sampling on a window of the fine grid.
``water_bodies``
    :class:`Lakes` and :class:`Canal`: still water, its shores and quays.
``draw``
    :func:`build_scene`: the random scene of a spec.
``flight``
    :class:`FlightLine`, :func:`flight_lines`.
``pulses``
    Per-pulse randomness, visibility, the returns of one flight line over a tile.
``tiles``
    The tile layout, the simulation of one tile and its truth, :func:`write_tile`.
``survey``
    :func:`generate_survey`, :class:`SyntheticSurvey`, :func:`write_truth`.
"""

from __future__ import annotations

from .draw import build_scene
from .flight import FlightLine, flight_lines
from .scene import Buildings, River, Scene, SceneRaster, Terrain, Trees
from .spec import (
    BASE_HEIGHT_M,
    CLASS_BUILDING,
    CLASS_GROUND,
    CLASS_HIGH_VEGETATION,
    FLIGHT_SPEED_M_S,
    LINE_INTERVAL_S,
    MAX_FINE_CELL_M,
    PULSE_JITTER_FRACTION,
    RIVER_BANK_HEIGHT_M,
    RIVER_BANK_WIDTH_M,
    SURVEY_START_GPS_TIME,
    HoleCause,
    SurfaceKind,
    SurveySpec,
    preset,
)
from .survey import SyntheticSurvey, generate_survey, write_truth
from .tiles import write_tile
from .water_bodies import Canal, Lakes

__all__ = [
    "BASE_HEIGHT_M",
    "CLASS_BUILDING",
    "CLASS_GROUND",
    "CLASS_HIGH_VEGETATION",
    "FLIGHT_SPEED_M_S",
    "LINE_INTERVAL_S",
    "MAX_FINE_CELL_M",
    "PULSE_JITTER_FRACTION",
    "RIVER_BANK_HEIGHT_M",
    "RIVER_BANK_WIDTH_M",
    "SURVEY_START_GPS_TIME",
    "Buildings",
    "Canal",
    "FlightLine",
    "HoleCause",
    "Lakes",
    "River",
    "Scene",
    "SceneRaster",
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
    "write_truth",
]
