"""The surface a simulated scan flies over: :class:`Terrain`, built from a real point cloud (pure).

A terrain is a few rasters on one lattice of ``cell_m`` cells (row 0 at the north):

* ``surface``: the first surface, the highest point per cell (roofs, canopy, ground,
  the water level);
* ``ground``: the bare earth (the lowest ground-class point per cell, interpolated under
  buildings, trees and voids) and, over water, the water level;
* ``kind``: what the first surface is (:class:`Surface`): ground, building, vegetation (a
  pulse may pass through it and return several times), water, or another solid object.

:func:`terrain_from_points` makes them from a real survey's points (arrays in, arrays
out); :func:`mirror_terrain` tiles a small terrain into a larger scene by mirroring it, so
that several flight lines fit. Reading the files is :mod:`.sources`' job.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
import scipy.ndimage as ndi

#: ASPRS classes ignored when building a terrain: noise (7, 18) and anything >= 64
#: (IGN's virtual and artefact classes).
IGNORED_CLASSES = (7, 18)
#: Class-1 (unclassified) points this far above the ground are vegetation (trees in AHN,
#: in the BC forest of lasR), lower ones are other solid objects (cars, shrubs, fences).
UNCLASSIFIED_VEGETATION_M = 2.0


class Surface(enum.IntEnum):
    """What the first surface of a terrain cell is."""

    GROUND = 0
    BUILDING = 1
    VEGETATION = 2
    """Penetrable: a pulse may give a first return at the canopy and more below it."""
    WATER = 3
    """Returns nothing (apart from weak specular returns near nadir)."""
    OTHER = 4
    """Another solid object (bridge, low unclassified object)."""


#: The ASPRS class a return from each kind of surface gets.
SURFACE_CLASS = {
    Surface.GROUND: 2,
    Surface.BUILDING: 6,
    Surface.VEGETATION: 5,
    Surface.WATER: 9,
    Surface.OTHER: 1,
}


@dataclass(frozen=True, eq=False)
class Terrain:
    """Rasters of the surface a scan flies over, on one lattice.

    Attributes
    ----------
    name : str
        A short name (the real source, or "synthetic").
    surface, ground : ndarray of shape (M, N), float32
        First-surface and bare-earth (or water level) heights; row 0 is the north edge.
    kind : ndarray of shape (M, N), uint8
        :class:`Surface` codes of the first surface.
    cell_m : float
        Side of a cell (CRS units, metres).
    x_min, y_min : float
        Lower-left corner of the raster in CRS coordinates.
    crs : str
        The CRS of the coordinates (EPSG code or WKT).
    """

    name: str
    surface: np.ndarray
    ground: np.ndarray
    kind: np.ndarray
    cell_m: float
    x_min: float
    y_min: float
    crs: str

    def __post_init__(self) -> None:
        if not (self.surface.shape == self.ground.shape == self.kind.shape) or self.surface.ndim != 2:
            raise ValueError("surface, ground and kind must be 2-dimensional arrays of one shape")
        if self.cell_m <= 0:
            raise ValueError(f"cell_m must be positive, not {self.cell_m!r}")

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.surface.shape[0]), int(self.surface.shape[1]))

    @property
    def width_m(self) -> float:
        return self.shape[1] * self.cell_m

    @property
    def height_m(self) -> float:
        return self.shape[0] * self.cell_m

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) in CRS coordinates."""
        return (self.x_min, self.y_min, self.x_min + self.width_m, self.y_min + self.height_m)

    @property
    def solid(self) -> np.ndarray:
        """The surface a pulse meets once it passes the vegetation: the ground under trees."""
        return np.where(self.kind == Surface.VEGETATION, self.ground, self.surface).astype(np.float32)

    def moved_to(self, x_min: float, y_min: float) -> Terrain:
        """The same rasters with their lower-left corner at ``(x_min, y_min)``."""
        return Terrain(self.name, self.surface, self.ground, self.kind, self.cell_m, x_min, y_min, self.crs)


def terrain_from_points(
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    classification: np.ndarray,
    *,
    cell_m: float,
    bounds: tuple[float, float, float, float],
    name: str = "terrain",
    crs: str = "",
) -> Terrain:
    """The surface model of a real survey's points.

    Parameters
    ----------
    x, y, z, classification : ndarray of shape (P,)
        The points (ASPRS classes; 2 ground, 3-5 vegetation, 6 building, 9 water; class 1
        more than :data:`UNCLASSIFIED_VEGETATION_M` above the ground counts as vegetation).
    cell_m : float
        Side of a terrain cell.
    bounds : (float, float, float, float)
        (x_min, y_min, x_max, y_max) of the raster; cells lie on multiples of ``cell_m``
        from ``(x_min, y_min)``. Points outside are ignored.
    name, crs : str
        Carried into the :class:`Terrain`.

    Returns
    -------
    Terrain
        Voids of the data (cells without points) are water when they border water-class
        points, else filled: ground height (interpolated), or vegetation where the nearest
        measured cell is vegetation.
    """
    x_min, y_min, x_max, y_max = bounds
    cols = int(round((x_max - x_min) / cell_m))
    rows = int(round((y_max - y_min) / cell_m))
    if rows < 2 or cols < 2:
        raise ValueError(f"bounds {bounds} hold fewer than 2 x 2 cells of {cell_m} m")
    col = np.floor((np.asarray(x) - x_min) / cell_m).astype(np.int64)
    row = rows - 1 - np.floor((np.asarray(y) - y_min) / cell_m).astype(np.int64)
    cls = np.asarray(classification).astype(np.int64)
    keep = (col >= 0) & (col < cols) & (row >= 0) & (row < rows) & ~np.isin(cls, IGNORED_CLASSES) & (cls < 64)
    index = (row * cols + col)[keep]
    z = np.asarray(z, dtype=np.float64)[keep]
    cls = cls[keep]
    n = rows * cols
    top, top_class = _highest_points(index, z, cls, n)
    ground_z = _lowest(index[cls == 2], z[cls == 2], n)
    water_points = np.bincount(index[cls == 9], minlength=n) > 0
    void = np.isnan(top)
    water = _water_mask(water_points.reshape(rows, cols), void.reshape(rows, cols))
    level = _water_levels(water, index[cls == 9], z[cls == 9], ground_z.reshape(rows, cols))
    known = ~np.isnan(ground_z.reshape(rows, cols)) | water
    ground = fill_by_interpolation(np.where(water, level, ground_z.reshape(rows, cols)), known)
    void = void.reshape(rows, cols)
    top = top.reshape(rows, cols)
    kind = _fill_void_kinds(_surface_kinds(top_class.reshape(rows, cols), top - ground), void)
    surface = np.where(void, ground, top)
    vegetation_void = void & (kind == Surface.VEGETATION)
    if vegetation_void.any():  # a void among trees: the canopy goes on over it
        surface = np.where(vegetation_void, fill_by_interpolation(top, ~void), surface)
    kind[water] = Surface.WATER
    surface = np.where(water, level, np.maximum(surface, ground))
    return Terrain(
        name=name,
        surface=surface.astype(np.float32),
        ground=np.minimum(ground, surface).astype(np.float32),
        kind=kind.astype(np.uint8),
        cell_m=float(cell_m),
        x_min=float(x_min),
        y_min=float(y_min),
        crs=crs,
    )


def _highest_points(index: np.ndarray, z: np.ndarray, cls: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per cell: the highest z (NaN where empty) and the class of a point at that height."""
    top = np.full(n, -np.inf)
    np.maximum.at(top, index, z)
    at_top = z >= top[index]
    top_class = np.zeros(n, np.int64)
    top_class[index[at_top]] = cls[at_top]
    top[np.isinf(top)] = np.nan
    return top, top_class


def _lowest(index: np.ndarray, z: np.ndarray, n: int) -> np.ndarray:
    """Per cell: the lowest z (NaN where empty)."""
    low = np.full(n, np.inf)
    np.minimum.at(low, index, z)
    low[np.isinf(low)] = np.nan
    return low


def _water_mask(water_points: np.ndarray, void: np.ndarray) -> np.ndarray:
    """Cells with water-class points, and the voids of the data that reach them.

    A void here is a cell more than one cell away from any point (sampling gaps of sparse
    data are not voids: among trees beside a lake they would all become water); the voids
    near water-class points are grown back by that cell, over empty cells only.
    """
    wide_void = ~ndi.binary_dilation(~void, iterations=1)
    labels, _ = ndi.label(wide_void)
    near_water = ndi.binary_dilation(water_points, iterations=2)
    touching = np.unique(labels[near_water & wide_void])
    water_voids = ndi.binary_dilation(np.isin(labels, touching[touching > 0]), iterations=1) & void
    water = water_points | water_voids
    return ndi.binary_closing(water, iterations=1) | water


def _water_levels(water: np.ndarray, index: np.ndarray, z: np.ndarray, ground: np.ndarray) -> np.ndarray:
    """Each water body's flat level: the median of its water points (else its shore's 10 % quantile)."""
    labels, n = ndi.label(water)
    level = np.full(water.shape, np.nan)
    if n == 0:
        return level
    point_label = labels.ravel()[index]
    shore = ndi.binary_dilation(water, iterations=2) & ~water & ~np.isnan(ground)
    shore_labels = ndi.grey_dilation(labels, size=5)[shore]
    shore_z = ground[shore]
    levels = np.full(n + 1, np.nan)
    for label in range(1, n + 1):
        points = z[point_label == label]
        if len(points):
            levels[label] = np.median(points)
        elif np.any(shore_labels == label):
            levels[label] = np.quantile(shore_z[shore_labels == label], 0.1)
    fallback = np.nanmin(ground) if np.any(~np.isnan(ground)) else 0.0
    levels = np.where(np.isnan(levels), fallback, levels)
    level[water] = levels[labels[water]]
    return level


def _surface_kinds(top_class: np.ndarray, height_above_ground: np.ndarray) -> np.ndarray:
    """:class:`Surface` codes from the class of each cell's highest point."""
    kind = np.full(top_class.shape, Surface.OTHER, np.uint8)
    kind[top_class == 2] = Surface.GROUND
    kind[top_class == 6] = Surface.BUILDING
    kind[np.isin(top_class, (3, 4, 5))] = Surface.VEGETATION
    kind[top_class == 9] = Surface.GROUND  # a water point off the water mask: its bank
    tall = np.nan_to_num(height_above_ground, nan=0.0) > UNCLASSIFIED_VEGETATION_M
    kind[(top_class == 1) & tall] = Surface.VEGETATION
    return kind


def _fill_void_kinds(kind: np.ndarray, void: np.ndarray) -> np.ndarray:
    """Voids take vegetation where their nearest measured cell is vegetation, else ground."""
    if not void.any() or void.all():
        return np.where(void, np.uint8(Surface.GROUND), kind).astype(np.uint8)
    _, (rows, cols) = ndi.distance_transform_edt(void, return_indices=True)
    nearest = kind[rows, cols]
    filled = np.where(nearest == Surface.VEGETATION, np.uint8(Surface.VEGETATION), np.uint8(Surface.GROUND))
    return np.where(void, filled, kind).astype(np.uint8)


def fill_by_interpolation(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Linear interpolation of the unknown cells from the known ones, nearest outside their hull.

    Parameters
    ----------
    values : ndarray of shape (M, N)
        Heights; only the ``known`` cells are read.
    known : ndarray of bool, shape (M, N)

    Returns
    -------
    ndarray of shape (M, N), float64
        ``values`` where known, interpolated elsewhere (0 when nothing is known).
    """
    from scipy.interpolate import griddata

    out = np.asarray(values, dtype=np.float64).copy()
    if known.all():
        return out
    if not known.any():
        return np.zeros(values.shape)
    rows, cols = np.nonzero(known)
    # only the known cells next to unknown ones matter: interpolation inside a void needs its rim
    rim = known & ndi.binary_dilation(~known, iterations=2)
    rr, cc = np.nonzero(rim) if rim.sum() >= 3 else (rows, cols)
    wanted = np.nonzero(~known)
    points = np.column_stack([rr, cc]).astype(np.float64)
    targets = np.column_stack(wanted).astype(np.float64)
    if len(points) >= 3 and np.linalg.matrix_rank(points - points.mean(axis=0)) == 2:
        linear = griddata(points, out[rr, cc], targets, method="linear")
    else:
        linear = np.full(len(targets), np.nan)
    missing = np.isnan(linear)
    if missing.any():
        _, (near_r, near_c) = ndi.distance_transform_edt(~known, return_indices=True)
        linear[missing] = out[near_r[wanted][missing], near_c[wanted][missing]]
    out[wanted] = linear
    return out


def mirror_terrain(terrain: Terrain, *, width_m: float, height_m: float) -> Terrain:
    """A terrain of the given size: mirrored copies of ``terrain`` side by side, or its centre.

    Mirroring (``numpy.pad(mode="symmetric")``) keeps the surface continuous across the
    copies' edges. An axis longer than asked is cropped to its middle part. The corner
    stays at ``(terrain.x_min, terrain.y_min)``.
    """
    rows = int(round(height_m / terrain.cell_m))
    cols = int(round(width_m / terrain.cell_m))
    return Terrain(
        terrain.name,
        _mirror_to(terrain.surface, rows, cols),
        _mirror_to(terrain.ground, rows, cols),
        _mirror_to(terrain.kind, rows, cols),
        terrain.cell_m,
        terrain.x_min,
        terrain.y_min,
        terrain.crs,
    )


def _mirror_to(raster: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """``raster`` padded by mirroring (south and east) or cropped to its middle, to ``(rows, cols)``."""
    start_row = max(0, (raster.shape[0] - rows) // 2)
    start_col = max(0, (raster.shape[1] - cols) // 2)
    out = raster[start_row : start_row + rows, start_col : start_col + cols]
    # row 0 is the north edge: mirror northwards and eastwards, so the data keeps its lower-left corner
    out = np.pad(out, ((rows - out.shape[0], 0), (0, cols - out.shape[1])), mode="symmetric")
    return np.ascontiguousarray(out)
