"""The tile grid: whether a survey's tiles lie on a regular grid of squares, and on which (pure).

Production surveys are cut into tiles on a national or project grid (IGN: 1 km
squares named by the kilometres of their upper-left corner; 500 m, 250 m ...):
the tiles' header bounds coincide with the squares' edges wherever the data
reaches them. When a grid is found, the survey area is the union of the squares
(:func:`grid_survey_area`), so that a gap between two tiles' data, or a missing
tile enclosed by others, lies inside the survey and becomes a hole.

A wrong grid invents holes, so the evidence must be strong (docs/holes.md, "The
survey area"):

- at least two tiles (one tile has nothing between tiles);
- a tile size from :data:`STANDARD_SIZES` (CRS units: metres, or feet for a
  survey in feet), per axis, with squares on the multiples of the size (every
  national tiling puts its corners there);
- every tile lies inside one square (its bounds may overhang by ``tolerance``)
  and no two tiles share a square;
- at least half the tile sides along an axis lie on a square edge (within
  ``tolerance``, a few point spacings: the last point of a tile lies just before
  its edge). An axis with less evidence (a corridor cut across its length, where
  the data never reaches the sides) takes the other axis' size: the squares are
  square.

Names confirm a grid when they carry the squares' corners: IGN ``_0299_6802``
(km of the upper-left corner), ``77050_627755`` (tens of metres), or metres of
the lower-left corner; a tile whose header could not be read is then placed by
its name (:meth:`TileGrid.square_of_name`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import PurePath

import numpy as np
import shapely

__all__ = ["STANDARD_SIZES", "GridArea", "GridInference", "TileGrid", "grid_survey_area", "infer_tile_grid"]

#: Tile sides (CRS units) a grid may have.
STANDARD_SIZES: tuple[float, ...] = (
    10, 20, 25, 50, 100, 125, 150, 200, 250, 300, 400, 500, 600, 750, 1000, 1250, 1500, 2000, 2500, 3000, 4000,
    5000, 10000,
)  # fmt: skip
#: Share of the tile sides along an axis that must lie on square edges for the axis to count as evidence.
MIN_EDGE_SHARE = 0.5
#: Name scales tried: CRS units per unit of the coordinates in a name (m, dam, hm, km).
NAME_SCALES = (1, 10, 100, 1000)
_NAME_PAIR = re.compile(r"(?<![\d.])(\d{3,8})[_-](\d{3,8})(?![\d.])")

Square = tuple[int, int]


@dataclass(frozen=True)
class TileGrid:
    """A regular grid of tiles: square ``(ix, iy)`` covers ``[ix, ix + 1) * size_x`` x ``[iy, iy + 1) * size_y``.

    Attributes
    ----------
    size_x, size_y : float
        Tile sides in CRS units.
    squares : tuple of (int, int)
        The square of each tile, in input order.
    evidence : str
        What showed the grid, for the log and the manifest.
    naming : (int, str) or None
        How names carry the squares: (CRS units per name unit, "upper-left" or "lower-left").
    """

    size_x: float
    size_y: float
    squares: tuple[Square, ...]
    evidence: str
    naming: tuple[int, str] | None = None

    def square_bounds(self, square: Square) -> tuple[float, float, float, float]:
        ix, iy = square
        return (ix * self.size_x, iy * self.size_y, (ix + 1) * self.size_x, (iy + 1) * self.size_y)

    def square_of_name(self, name: str) -> Square | None:
        """The square a file name places its tile in (with the grid's naming), or None."""
        if self.naming is None:
            return None
        scale, corner = self.naming
        for nx, ny in _name_pairs(name):
            x, y = nx * scale, ny * scale
            ix, iy = x / self.size_x, y / self.size_y - (1 if corner == "upper-left" else 0)
            if _whole(ix) and _whole(iy):
                return (round(ix), round(iy))
        return None

    def describe(self) -> str:
        size = f"{self.size_x:g}" if self.size_x == self.size_y else f"{self.size_x:g} x {self.size_y:g}"
        return f"{len(self.squares)} tiles on a {size} grid (from the {self.evidence})"

    def as_record(self) -> dict[str, object]:
        """What the manifest records of the grid."""
        return {
            "size_x": self.size_x,
            "size_y": self.size_y,
            "origin": [0.0, 0.0],
            "evidence": self.evidence,
            "naming": list(self.naming) if self.naming else None,
        }


@dataclass(frozen=True)
class GridInference:
    """The outcome of :func:`infer_tile_grid`: a grid, or why there is none."""

    grid: TileGrid | None
    reason: str


@dataclass(frozen=True)
class _Axis:
    size: float
    index: np.ndarray  # the square index of each tile along the axis
    on_edge: int  # tile sides on a square edge
    share: float


def infer_tile_grid(
    bounds: Sequence[tuple[float, float, float, float]] | np.ndarray,
    names: Sequence[str] = (),
    *,
    tolerance: float,
    sizes: Sequence[float] = STANDARD_SIZES,
) -> GridInference:
    """Whether tiles lie on a regular grid of squares (the rules are in the module docstring).

    Parameters
    ----------
    bounds : sequence of (minx, miny, maxx, maxy)
        The tiles' header bounds, in CRS units.
    names : sequence of str
        The tiles' file names (same order), for confirmation; may be empty.
    tolerance : float
        How far (CRS units) a bound may lie from a square edge and still be on it.
    sizes : sequence of float
        Tile sides to try.

    Returns
    -------
    GridInference
        The grid, or None with the reason.
    """
    b = np.asarray(bounds, dtype=np.float64).reshape(-1, 4)
    if len(b) < 2:
        return GridInference(None, "one tile: nothing lies between tiles")
    if not np.isfinite(b).all():
        return GridInference(None, "tile bounds are not finite")
    axes = [[a for s in sizes if (a := _axis(b[:, k], b[:, k + 2], float(s), tolerance)) is not None] for k in (0, 1)]
    best: tuple[tuple[int, bool, float], _Axis, _Axis] | None = None
    for ax in axes[0]:
        for ay in axes[1]:
            if not _plausible(ax, ay):
                continue
            if len(set(zip(ax.index.tolist(), ay.index.tolist()))) < len(b):
                continue
            score = (ax.on_edge + ay.on_edge, ax.size == ay.size, -ax.size * ay.size)
            if best is None or score > best[0]:
                best = (score, ax, ay)
    if best is None:
        return GridInference(None, _why_not(axes))
    _, ax, ay = best
    squares = tuple(zip(ax.index.tolist(), ay.index.tolist()))
    grid = TileGrid(ax.size, ay.size, squares, "tile bounds")
    naming = _naming(grid, names)
    if naming is not None:
        what = {1: "m", 10: "tens of m", 100: "hundreds of m", 1000: "km"}[naming[0]]
        grid = TileGrid(ax.size, ay.size, squares, f"tile bounds and names ({what} of the {naming[1]} corner)", naming)
    return GridInference(grid, grid.describe())


def _axis(lo: np.ndarray, hi: np.ndarray, size: float, tolerance: float) -> _Axis | None:
    """Squares of side ``size`` along one axis, if every tile fits inside one of them."""
    tol = min(tolerance, size / 10)
    first = np.floor((lo + tol) / size)
    last = np.floor((hi - tol) / size)
    if not np.array_equal(first, last):
        return None
    on_edge = int((np.abs(lo - np.round(lo / size) * size) <= tol).sum())
    on_edge += int((np.abs(hi - np.round(hi / size) * size) <= tol).sum())
    return _Axis(size, first.astype(np.int64), on_edge, on_edge / (2 * len(lo)))


def _plausible(ax: _Axis, ay: _Axis) -> bool:
    """One axis at least shows the grid; an axis without evidence takes the other's size."""
    x_shown, y_shown = ax.share >= MIN_EDGE_SHARE, ay.share >= MIN_EDGE_SHARE
    if x_shown and y_shown:
        return True
    return (x_shown or y_shown) and ax.size == ay.size


def _why_not(axes: list[list[_Axis]]) -> str:
    for name, candidates in zip("xy", axes):
        if not candidates:
            return f"along {name}, no standard tile size holds every tile inside one square"
    if not any(a.share >= MIN_EDGE_SHARE for axis in axes for a in axis):
        return "the tile bounds do not lie on the edges of any standard grid of squares"
    return "the tiles do not fall into distinct squares of one standard grid"


def _name_pairs(name: str) -> list[tuple[int, int]]:
    return [(int(m.group(1)), int(m.group(2))) for m in _NAME_PAIR.finditer(PurePath(name).stem)]


def _naming(grid: TileGrid, names: Sequence[str]) -> tuple[int, str] | None:
    """How every name carries its square's corner (scale, corner), if one way fits them all."""
    if len(names) != len(grid.squares) or not names:
        return None
    pairs = [_name_pairs(n) for n in names]
    for scale in NAME_SCALES:
        for corner in ("upper-left", "lower-left"):
            trial = TileGrid(grid.size_x, grid.size_y, grid.squares, grid.evidence, (scale, corner))
            if all(_placed(trial, p, square) for p, square in zip(pairs, grid.squares)):
                return (scale, corner)
    return None


def _placed(grid: TileGrid, pairs: list[tuple[int, int]], square: Square) -> bool:
    assert grid.naming is not None
    scale, corner = grid.naming
    x0, y0, _, y1 = grid.square_bounds(square)
    y = y1 if corner == "upper-left" else y0
    return any(math.isclose(nx * scale, x0) and math.isclose(ny * scale, y) for nx, ny in pairs)


def _whole(value: float) -> bool:
    return abs(value - round(value)) < 1e-9


@dataclass(frozen=True)
class GridArea:
    """The survey area of a tile grid.

    Attributes
    ----------
    area : shapely geometry
        The squares of the tiles read and the missing squares they enclose, less the
        squares of skipped tiles.
    missing : tuple of (int, int)
        Squares without a tile, enclosed by squares with one (missing tiles).
    skipped : tuple of (int, int)
        Squares of tiles that were skipped (placed by their names): exterior.
    note : str
        Why missing squares were not looked for, when they were not; else empty.
    """

    area: shapely.Geometry
    missing: tuple[Square, ...]
    skipped: tuple[Square, ...]
    note: str = ""


def grid_survey_area(grid: TileGrid, *, skipped_names: Sequence[str] = ()) -> GridArea:
    """The union of the tiles' squares, with the missing squares they enclose; skipped tiles' squares left out.

    A square holding no tile but enclosed by squares holding one (a hole in their
    union) is a missing tile: inside the survey. Squares of skipped tiles (placed by
    their names) are neither: they are exterior. When a skipped tile cannot be
    placed, a missing square might be it, so no square is called missing.
    """
    placed = [grid.square_of_name(name) for name in skipped_names]
    skipped = tuple(sorted({s for s in placed if s is not None} - set(grid.squares)))
    present = set(grid.squares) | set(skipped)
    union = shapely.union_all([shapely.box(*grid.square_bounds(s)) for s in sorted(present)])
    note = ""
    if any(s is None for s in placed):
        missing: tuple[Square, ...] = ()
        note = "a skipped tile cannot be placed on the grid by its name: no square is called a missing tile"
    else:
        missing = _enclosed_squares(grid, union, present)
    squares = set(grid.squares) | set(missing)
    area = shapely.union_all([shapely.box(*grid.square_bounds(s)) for s in sorted(squares)])
    return GridArea(area, missing, skipped, note)


def _enclosed_squares(grid: TileGrid, union: shapely.Geometry, present: set[Square]) -> tuple[Square, ...]:
    """The squares inside the holes of the union of the present squares."""
    found = []
    for polygon in shapely.get_parts(union):
        for ring in polygon.interiors:
            hole = shapely.Polygon(ring)
            minx, miny, maxx, maxy = hole.bounds
            for ix in range(math.floor(minx / grid.size_x), math.ceil(maxx / grid.size_x)):
                for iy in range(math.floor(miny / grid.size_y), math.ceil(maxy / grid.size_y)):
                    centre = shapely.Point((ix + 0.5) * grid.size_x, (iy + 0.5) * grid.size_y)
                    if (ix, iy) not in present and hole.contains(centre):
                        found.append((ix, iy))
    return tuple(sorted(found))
