"""Drawing the random scene of a spec (:func:`build_scene`): terrain, river, buildings, trees.

Each component draws from its own random stream, seeded by ``spec.seed`` and a
component number, so changing one density leaves the other components unchanged.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .scene import Buildings, River, Scene, Terrain, Trees
from .spec import BASE_HEIGHT_M, RIVER_BANK_WIDTH_M, SurveySpec


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
    terrain = _draw_terrain(spec)
    river = _draw_river(spec, terrain) if spec.water and spec.water_width_m > 0 else None
    buildings = _draw_buildings(spec, terrain, river)
    trees = _draw_trees(spec, terrain, river, buildings)
    return Scene(spec.width_m, spec.height_m, terrain, river, buildings, trees)


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
    draft = River(river_center_v, amplitude, wavelength, phase, half_width, water_level=0.0)
    along = np.linspace(-RIVER_BANK_WIDTH_M, width + RIVER_BANK_WIDTH_M, int(width) + 32)
    water_level = float(terrain.height(along, draft.centerline_v(along)).min()) - 1.0
    return dataclasses.replace(draft, water_level=water_level)


def _ground(terrain: Terrain, river: River | None, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bare-earth height, the river banks included (as :meth:`Scene.ground_height`)."""
    z = terrain.height(u, v)
    return river.shape_ground(z, u, v) if river is not None else z


def _clear_of_river(river: River | None, u: np.ndarray, v: np.ndarray, radius: np.ndarray, margin: float) -> np.ndarray:
    """True where a round object (centre, radius) stays more than ``margin`` from the water."""
    if river is None:
        return np.ones(np.shape(u), dtype=bool)
    reach = radius * (1.0 + river.max_slope)
    return np.abs(river.offset(u, v)) - reach > river.half_width + margin


def _draw_buildings(spec: SurveySpec, terrain: Terrain, river: River | None) -> Buildings:
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
    keep = _clear_of_river(river, center_u, center_v, radius, RIVER_BANK_WIDTH_M / 2.0)
    keep = _greedy_non_overlapping(center_u, center_v, radius, gap=3.0, allowed=keep)
    ground_at_center = _ground(terrain, river, center_u, center_v)
    return Buildings(
        center_u=center_u[keep],
        center_v=center_v[keep],
        half_length=half_length[keep],
        half_width=half_width[keep],
        angle=angle[keep],
        eave_z=(ground_at_center + total_height - rise)[keep],
        ridge_z=(ground_at_center + total_height)[keep],
    )


def _draw_trees(spec: SurveySpec, terrain: Terrain, river: River | None, buildings: Buildings) -> Trees:
    """Taller trees have wider crowns; none on buildings or in the river; stream 4."""
    rng = np.random.default_rng([spec.seed, 4])
    n = rng.poisson(spec.tree_density * _area_ha(spec))
    tree_height = rng.uniform(5.0, 20.0, n)
    crown_radius = np.clip(3.0 + 5.0 * (tree_height - 5.0) / 15.0 * rng.uniform(0.6, 1.2, n), 3.0, 8.0)
    tree_u, tree_v = rng.uniform(0.0, spec.width_m, n), rng.uniform(0.0, spec.height_m, n)
    keep = _clear_of_river(river, tree_u, tree_v, crown_radius, 2.0)
    keep &= _clear_of_buildings(buildings, tree_u, tree_v, crown_radius + 1.0)
    return Trees(
        center_u=tree_u[keep],
        center_v=tree_v[keep],
        crown_radius=crown_radius[keep],
        top_z=(_ground(terrain, river, tree_u, tree_v) + tree_height)[keep],
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
