"""Drawing the random scene of a spec (:func:`build_scene`): terrain, river, canal, lakes, buildings, trees.

Each component draws from its own random stream, seeded by ``spec.seed`` and a
component number, so changing one density leaves the other components unchanged.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .scene import Buildings, River, Scene, Terrain, Trees
from .spec import (
    BASE_HEIGHT_M,
    CANAL_HOUSE_DEPTH_M,
    CANAL_HOUSE_FRONTAGE_M,
    CANAL_HOUSE_HEIGHT_M,
    CANAL_QUAY_HEIGHT_M,
    CANAL_STREET_M,
    CANAL_WIDTH_M,
    LAKE_SIZE_M,
    RIVER_BANK_WIDTH_M,
    SurveySpec,
)
from .water_bodies import Canal, Lakes


def build_scene(spec: SurveySpec) -> Scene:
    """Draw the scene of a spec: terrain, river, canal, lakes, buildings and trees.

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
    terrain = _draw_terrain(spec)
    river = _draw_river(spec, terrain) if spec.water and spec.water_width_m > 0 else None
    canal = _draw_canal(spec, terrain) if spec.canal else None
    lakes = _draw_lakes(spec, terrain, river, canal) if spec.lakes else None
    waters = _Waters(river, lakes, canal)
    buildings = _draw_buildings(spec, terrain, waters)
    if canal is not None:
        buildings = _concatenate_buildings(buildings, _draw_canal_houses(spec, canal, river))
    trees = _draw_trees(spec, terrain, waters, buildings)
    return Scene(spec.width_m, spec.height_m, terrain, river, buildings, trees, lakes, canal)


@dataclass(frozen=True)
class _Waters:
    """The water bodies other objects keep clear of."""

    river: River | None
    lakes: Lakes | None
    canal: Canal | None

    def ground(self, terrain: Terrain, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Bare-earth height, banks, shores and quays included (as :meth:`Scene.ground_height`)."""
        scene = Scene(0.0, 0.0, terrain, self.river, Buildings.empty(), Trees.empty(), self.lakes, self.canal)
        return scene.ground_height(u, v)

    def clear(self, u: np.ndarray, v: np.ndarray, radius: np.ndarray, margin: float, *, canal_zone: bool) -> np.ndarray:
        """True where a round object stays more than ``margin`` from every water body.

        ``canal_zone``: keep out of the canal's whole flat zone (street and canal-side
        buildings), not only its water.
        """
        keep = _clear_of_river(self.river, u, v, radius, margin)
        if self.lakes is not None and len(self.lakes):
            distance = np.hypot(u[:, None] - self.lakes.center_u, v[:, None] - self.lakes.center_v)
            keep &= np.all(distance - radius[:, None] - self.lakes.semi_major > margin, axis=1)
        if self.canal is not None:
            zone = self.canal.flat_half_width if canal_zone else self.canal.half_width
            keep &= np.abs(u - self.canal.center_u) - radius > zone + margin
        return keep


def _area_ha(spec: SurveySpec) -> float:
    return spec.width_m * spec.height_m / 10_000.0


def _draw_terrain(spec: SurveySpec) -> Terrain:
    """Four sinusoids of random direction and wavelength; stream 1."""
    rng = np.random.default_rng([spec.seed, 1])
    n_waves = 4
    weights = rng.uniform(0.5, 1.0, n_waves)
    amplitudes = weights / weights.sum() * spec.terrain_relief_m / 2.0
    wavelengths = rng.uniform(100.0, 450.0, n_waves)
    directions = rng.uniform(0.0, 2.0 * np.pi, n_waves)
    wavenumbers = 2.0 * np.pi / wavelengths
    return Terrain(
        base_height=BASE_HEIGHT_M,
        amplitudes=amplitudes,
        wavevector_u=wavenumbers * np.cos(directions),
        wavevector_v=wavenumbers * np.sin(directions),
        phases=rng.uniform(0.0, 2.0 * np.pi, n_waves),
    )


def _draw_river(spec: SurveySpec, terrain: Terrain) -> River:
    """A meandering west-east river, its water 1 m below the lowest terrain along its centre line; stream 2."""
    width, height = spec.width_m, spec.height_m
    rng = np.random.default_rng([spec.seed, 2])
    half_width = spec.water_width_m / 2.0
    river_center_v = rng.uniform(0.35, 0.65) * height
    amplitude = min(0.12 * height, 15.0) * rng.uniform(0.3, 1.0)
    wavelength = max(width, 200.0) * rng.uniform(0.7, 1.3)
    phase = rng.uniform(0.0, 2.0 * np.pi)
    fall = spec.river_fall_m_per_km / 1000.0
    draft = River(river_center_v, amplitude, wavelength, phase, half_width, water_level=0.0, fall=fall)
    along = np.linspace(-RIVER_BANK_WIDTH_M, width + RIVER_BANK_WIDTH_M, int(width) + 32)
    # water_level is the level at u = 0: the falling surface stays 1 m under the centre line
    water_level = float((terrain.height(along, draft.centerline_v(along)) + fall * along).min()) - 1.0
    return dataclasses.replace(draft, water_level=water_level)


def _draw_canal(spec: SurveySpec, terrain: Terrain) -> Canal:
    """A N-S canal near the middle, its quays at the lowest terrain of its flat zone; stream 6."""
    rng = np.random.default_rng([spec.seed, 6])
    half_width = rng.uniform(*CANAL_WIDTH_M) / 2.0
    quay_height = rng.uniform(*CANAL_QUAY_HEIGHT_M)
    street = rng.uniform(*CANAL_STREET_M)
    center_u = rng.uniform(0.35, 0.65) * spec.width_m
    flat_half_width = half_width + street + CANAL_HOUSE_DEPTH_M[1] + 3.0  # houses and their back yards
    u = center_u + np.linspace(-flat_half_width, flat_half_width, 16)
    v = np.linspace(-RIVER_BANK_WIDTH_M, spec.height_m + RIVER_BANK_WIDTH_M, int(spec.height_m) + 32)
    quay_z = float(terrain.height(u[None, :], v[:, None]).min())
    return Canal(center_u, half_width, quay_z - quay_height, quay_height, flat_half_width, street=street)


def _draw_canal_houses(spec: SurveySpec, canal: Canal, river: River | None) -> Buildings:
    """A row of houses along each quay, facades a street's width from the water; stream 7.

    Each house's ridge runs E-W (gables facing the canal) or its roof is flat; houses
    stand side by side with gaps of 0-3 m. Houses that would stand in the river are left out.
    """
    rng = np.random.default_rng([spec.seed, 7])
    n = int(spec.height_m / CANAL_HOUSE_FRONTAGE_M[0]) + 2  # per side, enough to reach the north edge
    records = []
    for side in (-1.0, 1.0):
        frontage = rng.uniform(*CANAL_HOUSE_FRONTAGE_M, n)
        gaps = rng.uniform(0.0, 3.0, n)
        depth = rng.uniform(*CANAL_HOUSE_DEPTH_M, n)
        height = rng.uniform(*CANAL_HOUSE_HEIGHT_M, n)
        gable = rng.random(n) < 0.6
        pitch = np.radians(rng.uniform(35.0, 55.0, n))
        south = -rng.uniform(0.0, CANAL_HOUSE_FRONTAGE_M[1]) + np.concatenate([[0.0], np.cumsum(frontage + gaps)[:-1]])
        rise = np.where(gable, np.minimum(frontage / 2.0 * np.tan(pitch), height - 4.0), 0.0)
        facade = canal.center_u + side * (canal.half_width + canal.street)
        for i in np.flatnonzero(south < spec.height_m):
            records.append(
                dict(
                    center_u=facade + side * depth[i] / 2.0,
                    center_v=south[i] + frontage[i] / 2.0,
                    half_length=depth[i] / 2.0,
                    half_width=frontage[i] / 2.0,
                    angle=0.0,
                    eave_z=canal.quay_z + height[i] - rise[i],
                    ridge_z=canal.quay_z + height[i],
                )
            )
    houses = Buildings.from_records(records)
    keep = _clear_of_river(river, houses.center_u, houses.center_v, houses.bounding_radius, 2.0)
    return _select_buildings(houses, keep)


def _draw_lakes(spec: SurveySpec, terrain: Terrain, river: River | None, canal: Canal | None) -> Lakes:
    """``spec.lakes`` ellipses inside the extent, clear of the river, the canal and each other; stream 5.

    Candidates are drawn and kept in order until enough fit; each lake's water lies
    1 m below the lowest terrain over its ellipse.
    """
    rng = np.random.default_rng([spec.seed, 5])
    n = 50 * spec.lakes
    semi_major = rng.uniform(*LAKE_SIZE_M, n) / 2.0
    semi_minor = np.maximum(semi_major * rng.uniform(0.5, 1.0, n), LAKE_SIZE_M[0] / 2.0)
    angle = rng.uniform(0.0, np.pi, n)
    reach = semi_major + RIVER_BANK_WIDTH_M
    room_u, room_v = spec.width_m - 2.0 * reach, spec.height_m - 2.0 * reach
    center_u = reach + rng.random(n) * np.maximum(room_u, 0.0)
    center_v = reach + rng.random(n) * np.maximum(room_v, 0.0)
    keep = (room_u > 0) & (room_v > 0)
    keep &= _Waters(river, None, canal).clear(center_u, center_v, reach, RIVER_BANK_WIDTH_M, canal_zone=True)
    keep = _greedy_non_overlapping(center_u, center_v, reach, gap=0.0, allowed=keep)
    chosen = np.flatnonzero(keep)[: spec.lakes]
    if len(chosen) < spec.lakes:
        raise ValueError(
            f"SurveySpec.lakes: only {len(chosen)} of {spec.lakes} lakes fit in {spec.width_m:g} x "
            f"{spec.height_m:g} m clear of the river, the canal and each other"
        )
    t = np.linspace(0.0, 2.0 * np.pi, 48, endpoint=False)
    levels = []
    for index in chosen:
        scale = np.linspace(0.0, 1.0, 6)[:, None]
        a, b = scale * semi_major[index] * np.cos(t), scale * semi_minor[index] * np.sin(t)
        cos, sin = np.cos(angle[index]), np.sin(angle[index])
        z = terrain.height(center_u[index] + a * cos - b * sin, center_v[index] + a * sin + b * cos)
        levels.append(float(z.min()) - 1.0)
    return Lakes(
        center_u[chosen], center_v[chosen], semi_major[chosen], semi_minor[chosen], angle[chosen], np.asarray(levels)
    )


def _clear_of_river(river: River | None, u: np.ndarray, v: np.ndarray, radius: np.ndarray, margin: float) -> np.ndarray:
    """True where a round object (centre, radius) stays more than ``margin`` from the water."""
    if river is None:
        return np.ones(np.shape(u), dtype=bool)
    reach = radius * (1.0 + river.max_slope)
    return np.abs(river.offset(u, v)) - reach > river.half_width + margin


def _draw_buildings(spec: SurveySpec, terrain: Terrain, waters: _Waters) -> Buildings:
    """Candidates, then greedy rejection of overlaps in draw order; stream 3."""
    rng = np.random.default_rng([spec.seed, 3])
    n = rng.poisson(spec.building_density * _area_ha(spec))
    sides = rng.uniform(10.0, 40.0, (n, 2))
    half_length, half_width = sides.max(axis=1) / 2.0, sides.min(axis=1) / 2.0
    center_u, center_v = rng.uniform(0.0, spec.width_m, n), rng.uniform(0.0, spec.height_m, n)
    angle = rng.uniform(0.0, np.pi, n)
    total_height = rng.uniform(6.0, 25.0, n)
    gable = rng.random(n) < 0.5
    pitch = np.radians(rng.uniform(20.0, 40.0, n))
    rise = np.where(gable, np.minimum(half_width * np.tan(pitch), total_height - 3.0), 0.0)
    radius = np.hypot(half_length, half_width)
    keep = waters.clear(center_u, center_v, radius, RIVER_BANK_WIDTH_M / 2.0, canal_zone=True)
    keep = _greedy_non_overlapping(center_u, center_v, radius, gap=3.0, allowed=keep)
    ground_at_center = waters.ground(terrain, center_u, center_v)
    return Buildings(
        center_u=center_u[keep],
        center_v=center_v[keep],
        half_length=half_length[keep],
        half_width=half_width[keep],
        angle=angle[keep],
        eave_z=(ground_at_center + total_height - rise)[keep],
        ridge_z=(ground_at_center + total_height)[keep],
    )


def _draw_trees(spec: SurveySpec, terrain: Terrain, waters: _Waters, buildings: Buildings) -> Trees:
    """Taller trees have wider crowns; none on buildings or in the river; stream 4."""
    rng = np.random.default_rng([spec.seed, 4])
    n = rng.poisson(spec.tree_density * _area_ha(spec))
    tree_height = rng.uniform(5.0, 20.0, n)
    crown_radius = np.clip(3.0 + 5.0 * (tree_height - 5.0) / 15.0 * rng.uniform(0.6, 1.2, n), 3.0, 8.0)
    tree_u, tree_v = rng.uniform(0.0, spec.width_m, n), rng.uniform(0.0, spec.height_m, n)
    keep = waters.clear(tree_u, tree_v, crown_radius, 2.0, canal_zone=True)
    keep &= _clear_of_buildings(buildings, tree_u, tree_v, crown_radius + 1.0)
    return Trees(
        center_u=tree_u[keep],
        center_v=tree_v[keep],
        crown_radius=crown_radius[keep],
        top_z=(waters.ground(terrain, tree_u, tree_v) + tree_height)[keep],
        edge_drop=np.minimum(0.6 * crown_radius, 0.45 * tree_height)[keep],
    )


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


def _select_buildings(buildings: Buildings, keep: np.ndarray) -> Buildings:
    return Buildings(**{f.name: getattr(buildings, f.name)[keep] for f in dataclasses.fields(Buildings)})


def _concatenate_buildings(first: Buildings, second: Buildings) -> Buildings:
    """The buildings of ``first`` then those of ``second`` (indices of ``first`` unchanged)."""
    return Buildings(
        **{
            f.name: np.concatenate([getattr(first, f.name), getattr(second, f.name)])
            for f in dataclasses.fields(Buildings)
        }
    )
