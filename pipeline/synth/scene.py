"""The analytic scene in local coordinates, and its sampling on a window of the fine grid.

Terrain, river, buildings and trees are functions of ``(u, v)`` (metres east of
``x_min`` and north of ``y_min``): any window can be evaluated on its own, and a
fine cell's values depend only on its global indices (:meth:`Scene.rasterize`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .shore import blend_to_shore
from .spec import RIVER_BANK_WIDTH_M, SurfaceKind
from .water_bodies import Canal, Lakes


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
    the water surface is ``water_level - fall * u`` (:meth:`level`: flat when ``fall`` is 0,
    else falling west to east; the bed and banks follow it). Being a band of constant N-S
    width it is an exact polygon (see :meth:`polygon`).
    """

    center_v: float
    meander_amplitude: float
    meander_wavelength: float
    phase: float
    half_width: float
    water_level: float
    bank_width: float = RIVER_BANK_WIDTH_M
    fall: float = 0.0  # metres of water-surface fall per metre eastward

    def level(self, u: np.ndarray) -> np.ndarray:
        """Water surface height at eastings ``u`` (``water_level`` at ``u = 0``)."""
        return self.water_level - self.fall * np.asarray(u, dtype=np.float64)

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
        level = self.level(u)
        return np.where(distance < 0, level - 1.0, blend_to_shore(ground, distance, level, self.bank_width))

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
    """An analytic scene in local coordinates: terrain, an optional river, buildings, trees, lakes and a canal."""

    width_m: float
    height_m: float
    terrain: Terrain
    river: River | None
    buildings: Buildings
    trees: Trees
    lakes: Lakes | None = None
    canal: Canal | None = None

    def ground_height(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Bare-earth height (river and lake beds under water; the quay top under a canal)."""
        return self._shape_ground(self.terrain.height(u, v), u, v)

    def _shape_ground(self, ground: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Terrain heights shaped by the water bodies: beds, banks, shores and quays."""
        if self.river is not None:
            ground = self.river.shape_ground(ground, u, v)
        if self.lakes is not None:
            ground = self.lakes.shape_ground(ground, u, v)
        if self.canal is not None:
            ground = self.canal.shape_ground(ground, u, v)
        return ground

    def water_level(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where ``(u, v)`` is water (any water body) and the water surface there (NaN elsewhere)."""
        shape = np.broadcast_shapes(np.shape(u), np.shape(v))
        water = np.zeros(shape, dtype=bool)
        level = np.full(shape, np.nan)
        if self.river is not None:
            river = self.river.is_water(u, v)
            level[river] = np.broadcast_to(self.river.level(u), shape)[river]
            water |= river
        if self.lakes is not None:
            lake = self.lakes.is_water(u, v)
            level[lake] = self.lakes.level(u, v)[lake]
            water |= lake
        if self.canal is not None:
            canal = self.canal.is_water(u, v)
            level[canal] = self.canal.water_level
            water |= canal
        return water, level

    def height_range(self) -> tuple[float, float]:
        """Bounds of every surface in the scene, for the occlusion padding."""
        low, high = self.terrain.height_range
        if self.river is not None:
            # the water falls eastward; the padding reaches a bank width beyond the extent
            low = min(low, float(self.river.level(np.asarray(self.width_m + RIVER_BANK_WIDTH_M))) - 1.0)
        if self.lakes is not None and len(self.lakes):
            low = min(low, float(self.lakes.water_level.min()) - 1.0)
        if self.canal is not None:
            low = min(low, self.canal.water_level)
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
        surface = self._shape_ground(self.terrain.height_grid(u, v), u[None, :], v[:, None])
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

        if self.river is not None or self.lakes is not None or self.canal is not None:
            water, level = self.water_level(u[None, :], v[:, None])
            surface[water] = level[water]
            hard_surface[water] = level[water]
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
