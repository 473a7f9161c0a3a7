"""Point density and what it supports: the pixel size, the cell size, what a sampling gap is.

Small pure functions of counts and areas. The survey's density is measured on
the data footprint by a pre-pass over the points' x, y
(:mod:`pipeline.survey.footprint_density`); without it (nothing "auto" to settle) it is
the header counts over the tile bounds, a lower bound.

The rules, in survey terms:

- A DSM pixel needs points to be measured. ``grid.resolution_m = "auto"`` picks the
  finest standard pixel size (:data:`STANDARD_PIXEL_SIZES_M`) holding on average at
  least :data:`AUTO_PULSES_PER_PIXEL` first returns (pulses): 4, so that a pixel
  left empty by chance is rare (about e^-4, 2 %, for a random pattern, far fewer
  for a scanner's regular one). IGN's 0.5 m DSMs from about 18 first returns/m²
  meet it (4.5 per pixel).
- The nominal point spacing is ``1 / sqrt(first-return density)``. A void
  narrower than :data:`SAMPLING_GAP_SPACINGS` spacings *across* (:func:`void_width`:
  a strip's width, a compact void's side) can be the
  scan pattern (between scan lines, between a rotating scanner's loops), not a
  missing surface: it is a *sampling gap*, filled as part of the DSM and counted,
  never listed as a hole. The spacing is the local one, from the footprint's
  blocks around the void; a void wider than that in both directions is never a
  sampling gap. ``holes.min_area_m2 = "auto"`` is the area of such a gap at the
  survey's spacing, a square of that width, and never less than
  :data:`MIN_AREA_FLOOR_M2`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Pixel sizes ``grid.resolution_m = "auto"`` chooses from (metres), finest first.
STANDARD_PIXEL_SIZES_M: tuple[float, ...] = (0.25, 0.5, 1.0, 2.0, 4.0, 5.0, 10.0)

#: First returns a pixel must hold on average for ``"auto"`` to choose its size.
AUTO_PULSES_PER_PIXEL = 4.0

#: Voids narrower than this many nominal point spacings are sampling gaps.
SAMPLING_GAP_SPACINGS = 4.0

#: Pulses a footprint block holds on average at the block size the footprint is measured
#: with: a block inside the data is empty by chance with probability e^-8 (0.03 %) for a
#: random pattern, fewer for a scanner's regular one (:mod:`pipeline.survey.footprint_density`).
BLOCK_PULSES = 8.0

#: ``holes.min_area_m2 = "auto"`` is never below this (the fixed default it replaces).
MIN_AREA_FLOOR_M2 = 4.0

#: A cell is at least this many pixels wide.
MIN_CELL_PX = 16
#: Pixels per cell side for ``grid.cell_size_m = "auto"``. Every cell costs a few fixed
#: milliseconds in each stage (reading its statistics, writing its COG tiles, the scheduler's
#: work on its tasks), and a worker holds a cell with its halo and the cells around it: sized in
#: pixels, both are the same at every pixel size. On the bench survey at 1 m (211 M points, 2
#: workers) cells of 250, 500 and 1,000 pixels ran the default command in 73.2, 61.7 and 62.9 s
#: (docs/performance.md, tenth session); 500 pixels at 1 m are 500 m, the common tile size.
AUTO_CELL_PX = 500


@dataclass(frozen=True)
class Density:
    """Points per square metre of a tile or a survey, from header counts.

    Attributes
    ----------
    points : int
        Points the headers declare.
    pulses : int
        First returns when the header's per-return counts can be trusted (they
        add up to ``points`` and count some first returns), else ``points``.
    area_m2 : float
        The area the points cover (tile bounds, their union for a survey).
    first_returns : bool
        Whether ``pulses`` are first returns.
    """

    points: int
    pulses: int
    area_m2: float
    first_returns: bool
    area_source: str = "tile bounds"  # or "data footprint" (pipeline.survey.footprint_density)

    @property
    def points_per_m2(self) -> float:
        return self.points / self.area_m2 if self.area_m2 > 0 else math.inf

    @property
    def pulses_per_m2(self) -> float:
        """First returns per m² (all points where the header cannot tell returns apart)."""
        return self.pulses / self.area_m2 if self.area_m2 > 0 else math.inf

    @property
    def spacing_m(self) -> float:
        """Nominal point spacing, ``1 / sqrt(pulses per m²)``."""
        return nominal_spacing_m(self.pulses_per_m2)

    def as_record(self) -> dict[str, object]:
        """The figures as written into the manifest."""
        return {
            "points": self.points,
            "first_returns": self.pulses if self.first_returns else None,
            "area_m2": round(self.area_m2, 2),
            "area_source": self.area_source,
            "points_per_m2": round(self.points_per_m2, 4),
            "first_returns_per_m2": round(self.pulses_per_m2, 4) if self.first_returns else None,
            "spacing_m": round(self.spacing_m, 4),
        }


def pulse_count(points: int, by_return: tuple[int, ...] | list[int]) -> tuple[int, bool]:
    """First returns from a header's per-return counts, when they can be trusted.

    Returns ``(count, True)`` when ``by_return`` adds up to ``points`` and holds
    some first returns, else ``(points, False)``: writers leave the counts at zero,
    or (``williams_az_urban_norm``) at values of another file, and a Geiger-mode
    survey can hold no return numbered 1 at all (``pdal_alirt_afghan``).
    """
    counts = [int(c) for c in by_return]
    if counts and counts[0] > 0 and sum(counts) == points:
        return counts[0], True
    return points, False


def nominal_spacing_m(pulses_per_m2: float) -> float:
    """Mean distance between neighbouring pulses: ``1 / sqrt(density)`` (0 for an infinite density)."""
    if pulses_per_m2 <= 0:
        return math.inf
    return 1.0 / math.sqrt(pulses_per_m2)


def auto_resolution_m(
    pulses_per_m2: float,
    *,
    per_pixel: float = AUTO_PULSES_PER_PIXEL,
    sizes: tuple[float, ...] = STANDARD_PIXEL_SIZES_M,
) -> float:
    """The finest of ``sizes`` whose pixel holds at least ``per_pixel`` pulses; else the coarsest.

    >>> auto_resolution_m(20.0), auto_resolution_m(10.0), auto_resolution_m(0.05)
    (0.5, 1.0, 10.0)
    """
    for size in sorted(sizes):
        if size * size * pulses_per_m2 >= per_pixel:
            return size
    return max(sizes)


def supported_resolution_m(pulses_per_m2: float, *, per_pixel: float = AUTO_PULSES_PER_PIXEL) -> float:
    """The finest pixel size (m) holding ``per_pixel`` pulses on average, not rounded to a standard size."""
    if pulses_per_m2 <= 0:
        return math.inf
    return math.sqrt(per_pixel / pulses_per_m2)


def round_cell_size(cell_size: float | str, resolution: float, *, min_px: int = MIN_CELL_PX) -> tuple[float, int]:
    """A cell size that is a whole multiple (at least ``min_px``) of the pixel size, nearest the one asked.

    ``"auto"``: :data:`AUTO_CELL_PX` pixels. Returns the size (same unit as the inputs) and its
    number of pixels.

    >>> round_cell_size(250.0, 4.0), round_cell_size(250.0, 0.5), round_cell_size(50.0, 10.0)
    ((248.0, 62), (250.0, 500), (160.0, 16))
    >>> round_cell_size("auto", 1.0), round_cell_size("auto", 0.25)
    ((500.0, 500), (125.0, 500))
    """
    if cell_size == "auto":
        return AUTO_CELL_PX * resolution, AUTO_CELL_PX
    pixels = max(min_px, round(float(cell_size) / resolution))
    return pixels * resolution, pixels


def sampling_gap_width_m(spacing_m: float, *, spacings: float = SAMPLING_GAP_SPACINGS) -> float:
    """Voids narrower than this (m) are sampling gaps."""
    return spacings * spacing_m


def narrow_width(area: np.ndarray | float, edge_length: np.ndarray | float) -> np.ndarray:
    """The narrow side of the rectangle with the same area and perimeter: a void's width across.

    ``(P - sqrt(P^2 - 16 A)) / 4``: exact for rectangles (a strip's width, a square's
    side) and for strips that bend (a gap between a rotating scanner's loops), 1 for
    a plus of five pixels; shapes more compact than a square (a disc) give ``P / 4``
    (0.79 of a disc's diameter). A staircase edge (a diagonal strip at pixel level)
    is longer than the true one, so a diagonal strip reads up to sqrt(2) narrower.

    >>> narrow_width(np.array([9.0, 5.0, 20.0]), np.array([12.0, 12.0, 24.0])).tolist()
    [3.0, 1.0, 2.0]
    """
    area = np.asarray(area, np.float64)
    edge = np.asarray(edge_length, np.float64)
    return (edge - np.sqrt(np.maximum(edge * edge - 16.0 * area, 0.0))) / 4.0


def void_width(area: np.ndarray, edge_length: np.ndarray, moment_width: np.ndarray) -> np.ndarray:
    """A void's width across, the figure the sampling-gap rule compares: the larger of two estimates.

    :func:`narrow_width` is exact for strips, straight or bent, but a pixel-level
    notch (one point jittered into a 3 x 3 px void: area 8, edge 14) lengthens the
    edge and reads 1.44 px. ``min(moment width, 4 area / edge)`` is a compact void's
    side (3 x 3 px: 3) and never more than twice a strip's width. Taking the larger
    never calls a void wider than the gap in both directions a gap.

    >>> void_width(np.array([8.0, 9.0]), np.array([14.0, 20.0]), np.array([2.9, 9.0])).tolist()
    [2.2857142857142856, 1.8]
    """
    area = np.asarray(area, np.float64)
    edge = np.maximum(np.asarray(edge_length, np.float64), 1.0)
    compact = np.minimum(np.asarray(moment_width, np.float64), 4.0 * area / edge)
    return np.maximum(narrow_width(area, edge), compact)


def auto_min_area_m2(spacing_m: float, *, floor_m2: float = MIN_AREA_FLOOR_M2) -> float:
    """``holes.min_area_m2 = "auto"``: a square sampling gap, never below ``floor_m2``.

    >>> auto_min_area_m2(0.2), auto_min_area_m2(5.0)
    (4.0, 400.0)
    """
    if not math.isfinite(spacing_m):
        return floor_m2
    return max(floor_m2, sampling_gap_width_m(spacing_m) ** 2)


__all__ = [
    "AUTO_PULSES_PER_PIXEL",
    "BLOCK_PULSES",
    "MIN_AREA_FLOOR_M2",
    "SAMPLING_GAP_SPACINGS",
    "STANDARD_PIXEL_SIZES_M",
    "Density",
    "auto_min_area_m2",
    "auto_resolution_m",
    "narrow_width",
    "nominal_spacing_m",
    "pulse_count",
    "round_cell_size",
    "sampling_gap_width_m",
    "supported_resolution_m",
    "void_width",
]
