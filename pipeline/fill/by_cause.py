"""How a hole is filled by its cause: the one answer, on arrays (pure; docs/filling.md, "Fill by cause").

:func:`fill_kind` says how a hole of a given cause is filled (``water`` flat or as a
river, ``low`` from the low side of its rim, ``rim`` from all of it); :func:`fill_hole`
fills labelled holes that way; :func:`hole_record` turns the outcome into the hole's
row of the ``holes`` layer (:class:`HoleFill`). The fill stage
(``pipeline/stages/fill_holes.py``) and the writer stage (small voids a cell settled,
``pipeline/stages/write_rasters.py``) both call these, so a hole of a cause is filled
alike wherever it is filled. The parameters (:class:`FillParams`) come from ``[fill]``
through :func:`pipeline.parameters.fill_params`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .causes import clamp_to_rim, lower_side_support
from .hydro import RiverFit, WaterEdge, river_surfaces
from .region import fill_region
from .settings import METHOD_CODES, METHOD_NAMES, ComponentFill, FillOutcome, FillSettings
from .water_level import MIN_WATER_PX, NO_LEVEL, EdgeLevel, edge_level, water_edge_heights

__all__ = [
    "FILLED",
    "LOW_SIDE",
    "MISSED",
    "MISSED_NOTE",
    "NO_RETURN",
    "NO_SUPPORT",
    "OCCLUSION",
    "RIM",
    "SMALL_VOID",
    "TOO_LARGE",
    "UNFILLED",
    "WATER",
    "FillParams",
    "HoleFill",
    "fill_hole",
    "fill_kind",
    "fill_water",
    "hole_ids_of_labels",
    "hole_record",
    "unfilled_reason",
]

#: The cause a small void is filled as (it is not classified when a cell settles it), unless the
#: sensor saw it unobstructed: then as a void that returned nothing (``NO_RETURN``), from its whole rim.
SMALL_VOID = "small void"
OCCLUSION = "occlusion"
NO_RETURN = "no_return"

#: How a hole is filled (:func:`fill_kind`).
WATER, LOW_SIDE, RIM = "water", "low", "rim"

#: ``fill_status`` values of the ``holes`` layer.
FILLED, TOO_LARGE, NO_SUPPORT, UNFILLED = "filled", "skipped: too large", "skipped: no support", "unfilled"
MISSED = "skipped: missed coverage"
#: ``fill_note`` of missed coverage filled on request (``fill.missed_coverage = true``).
MISSED_NOTE = "missed coverage, interpolated"


@dataclass(frozen=True)
class FillParams:
    """The ``[fill]`` settings in survey units, shared by every fill and writer task."""

    method: str
    by_cause: bool
    pixel_size: float  # survey units
    max_distance: float  # survey units
    jump_threshold: float  # z units
    settings: FillSettings
    clamp_to_rim: bool = True
    river_min_drop: float = math.inf  # z units; inf: every water hole one level
    river_min_elongation: float = 4.0
    # the water's edge (z units, pixels): its noise, the share of a ring on it, the steepest fall per pixel
    water_edge: WaterEdge = WaterEdge(tolerance=0.15, min_share=0.1, max_slope=0.02)
    water_reach_px: float = 3.0  # how far from a hole its water returns are looked for
    max_area_m2: float = math.inf  # fill.max_area_m2; inf: no limit
    fill_missed_coverage: bool = False  # fill.missed_coverage
    bare_earth: bool = False  # only bare-earth classes kept (a DTM): no object's top on any rim


@dataclass(frozen=True)
class HoleFill:
    """How one hole was filled (or why not): a row of the ``holes`` layer's fill fields."""

    hole_id: int
    status: str
    method: str | None = None
    pixels: int = 0
    max_distance: float = math.nan  # survey units, farthest filled pixel from measured data
    error_estimate: float = math.nan  # z units, leave-rim-out RMSE
    degraded: bool = False
    detail: str = ""
    result_path: str | None = None


def fill_kind(cause: str, params: FillParams) -> str:
    """How a hole of this cause is filled: ``water`` flat, ``low`` from the low side, ``rim`` from all of it.

    The low side is for a void beside an object whose top stands on its rim (the ground a
    building hides); in a bare-earth model (``params.bare_earth``: a DTM) the class filter took
    every object away, so a rim spanning more than a step is terrain (a slope, a bank, a cliff)
    and the whole of it is the support.
    """
    if not params.by_cause:
        return RIM
    if cause == "water":
        return WATER
    return LOW_SIDE if cause in (OCCLUSION, SMALL_VOID) and not params.bare_earth else RIM


def unfilled_reason(cause: str, *, area_m2: float, farthest: float, params: FillParams) -> tuple[str, str] | None:
    """Why a hole stays nodata (``fill_status``, ``fill_note``), or None: it is filled.

    Every void inside the survey area is filled but missed coverage, which awaits a
    re-flight unless ``fill.missed_coverage`` asks for it. Size (``area_m2``) and distance
    from data (``farthest``, survey units) are limits only where the user set them, and
    never for water: a water surface is known from its edge whatever its size.
    """
    if cause == "missed_coverage" and not params.fill_missed_coverage:
        return MISSED, "awaiting re-flight (fill.missed_coverage = false)"
    if cause == WATER:
        return None
    if area_m2 > params.max_area_m2:
        return TOO_LARGE, f"area over fill.max_area_m2 = {params.max_area_m2:g}"
    if farthest > params.max_distance:
        return TOO_LARGE, "farther from data than fill.max_distance_m"
    return None


def fill_hole(
    zmax: np.ndarray,
    zmin: np.ndarray,
    measured: np.ndarray,
    labels: np.ndarray,
    kind: str,
    params: FillParams,
    water_points: np.ndarray | None = None,
    counts: np.ndarray | None = None,
) -> FillOutcome:
    """Fill labelled holes (each label one hole, 0 elsewhere) one way (pure; docs/filling.md).

    ``kind`` (:func:`fill_kind`): ``water`` is flat at a low percentile of its rim's
    lowest returns (hydro-flattening); ``low`` (an occlusion, a small void at a step)
    is ground hidden by a building or a tree, filled from the low side of its rim
    only, so no ramp runs from the roof to the street; ``rim`` with the configured
    method from the whole rim.
    """
    heights = np.where(measured, zmax, np.nan)
    region = labels > 0
    if kind == WATER:
        water_z, water_pure = _water_heights(zmin, zmax, measured, water_points, counts)
        return fill_water(np.where(measured, zmin, np.nan), labels, params, water_points, water_z, water_pure)
    support = None
    if kind == LOW_SIDE:
        # a small void at a step (a building's edge) is hidden ground like an occlusion; with
        # no step on its rim every rim pixel is on the low side and nothing changes
        support = lower_side_support(heights, region, jump_threshold=params.jump_threshold, labels=labels)
    outcome = fill_region(
        heights,
        region,
        method=params.method,
        settings=params.settings,
        support=support,
        pixel_size=params.pixel_size,
        labels=labels,
    )
    if not params.clamp_to_rim:
        return outcome
    clamped = clamp_to_rim(outcome.heights, heights, region, support=support, labels=labels)
    return replace(outcome, heights=np.where(np.isfinite(outcome.heights), clamped, np.nan))


def _water_heights(
    zmin: np.ndarray, zmax: np.ndarray, measured: np.ndarray, water_points: np.ndarray | None, counts: np.ndarray | None
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The height of the water returns of each pixel, and whether the pixel holds water returns only.

    The height is the mid-range of a pixel of water returns only, else its lowest return. The
    lowest of several noisy returns from one surface lies below it (by about the noise), the
    highest above; their mid-range does not. A pixel with land returns too keeps its lowest
    (its highest is the bank), biased low: see :func:`_pure_where_enough`.
    """
    if water_points is None or counts is None:
        return None, None
    pure = measured & (water_points > 0) & (water_points == counts)
    return np.where(pure, 0.5 * (zmin + zmax), np.where(measured, zmin, np.nan)), pure


def _pure_where_enough(water_label: np.ndarray, pure: np.ndarray) -> np.ndarray:
    """``water_label`` without the mixed pixels (water and bank returns) of holes with enough pure ones.

    A mixed pixel gives only its lowest return: the lowest of its few water returns, below
    the water by about the lidar's noise (the lowest of two returns by 0.56 standard deviations,
    of three by 0.85). Where a hole has at least :data:`MIN_WATER_PX` pixels of water returns
    only (unbiased, their mid-range), its level is read from those alone: on the synthetic river
    falling 10 m/km (3 cm noise) the mixed pixels put its level 1 cm low along most of its course
    (0.021 m at worst, 0.015 m without them).
    """
    n = int(water_label.max(initial=0))
    if n == 0:
        return water_label
    pure_count = np.bincount(water_label[pure & (water_label > 0)], minlength=n + 1)
    enough = pure_count >= MIN_WATER_PX
    enough[0] = False
    return np.where(~pure & enough[water_label], 0, water_label)


def fill_water(
    zmin: np.ndarray,
    labels: np.ndarray,
    params: FillParams,
    water_points: np.ndarray | None = None,
    water_z: np.ndarray | None = None,
    water_pure: np.ndarray | None = None,
) -> FillOutcome:
    """Water holes at the level of their edge: a lake one level, a river falling along its course.

    ``zmin``: the lowest return of measured pixels, NaN elsewhere (the highest returns
    are bridges, walls and crowns over the water, never its level); ``water_points``: water-class returns per pixel. The level of each hole is where
    its water meets the land (:func:`~pipeline.fill.water_level.edge_level`): its water
    returns near the ring when there are some, else the lowest consistent level of its
    ring's lowest returns (``water_z``: the height of each pixel's water returns, default
    ``zmin``; ``water_pure``: the pixels of water returns only, which alone give the level of
    a hole that has enough of them, :func:`_pure_where_enough`). Holes :func:`~pipeline.fill.river_surfaces` judges rivers
    (elongated, falling at least ``river_min_drop``) get their river surface instead,
    method ``river``, never falling faster than the water's steepest slope. The error
    estimate of a hole is the spread of the heights its level was read from.
    """
    settings = replace(params.settings, estimate_error=False)
    outcome = fill_region(
        zmin, labels > 0, method="flat", settings=settings, pixel_size=params.pixel_size, labels=labels
    )
    points = np.zeros(zmin.shape, np.uint16) if water_points is None else water_points
    ring_label, water_label = water_edge_heights(zmin, points, outcome.labels, reach_px=params.water_reach_px)
    if water_pure is not None:
        water_label = _pure_where_enough(water_label, water_pure)
    water_z = zmin if water_z is None else water_z
    levels = _edge_levels(zmin, water_z, ring_label, water_label, params.water_edge)
    heights = outcome.heights.copy()
    lake = (outcome.labels > 0) & np.isfinite(heights)
    heights[lake] = np.array([levels[k].level for k in range(len(levels))])[outcome.labels[lake]]
    components = tuple(_water_component(c, levels[c.label]) for c in outcome.components)
    outcome = replace(outcome, heights=heights, components=components)
    if not math.isfinite(params.river_min_drop):
        return outcome
    surface, fits = river_surfaces(
        zmin,
        outcome.labels,
        edge=params.water_edge,
        min_drop=params.river_min_drop,
        min_elongation=params.river_min_elongation,
        water_heights=np.where(water_label > 0, water_z, np.nan),
        water_labels=water_label,
    )
    return _as_rivers(outcome, surface, {fit.label: fit for fit in fits if fit.is_river}, params.pixel_size)


def _edge_levels(
    zmin: np.ndarray, water_z: np.ndarray, ring_label: np.ndarray, water_label: np.ndarray, edge: WaterEdge
) -> list[EdgeLevel]:
    """The edge level of every label 0..max (entry 0 unused)."""
    n = int(max(ring_label.max(initial=0), water_label.max(initial=0)))
    ring = _by_label(zmin, ring_label, n)
    water = _by_label(water_z, water_label, n)
    return [NO_LEVEL] + [
        edge_level(ring[k], water[k], tolerance=edge.tolerance, min_share=edge.min_share) for k in range(1, n + 1)
    ]


def _by_label(values: np.ndarray, labels: np.ndarray, n: int) -> list[np.ndarray]:
    """The values of each label 0..n (one sort, no pass per label)."""
    flat = labels.ravel()
    order = np.argsort(flat, kind="stable")
    bounds = np.searchsorted(flat[order], np.arange(n + 2))
    picked = values.ravel()[order]
    return [picked[bounds[k] : bounds[k + 1]] for k in range(n + 1)]


def _water_component(component: ComponentFill, found: EdgeLevel) -> ComponentFill:
    """A flat water component at its edge level; its error the spread of the edge heights."""
    if not component.filled:
        return component
    note = f"water level {found.level:.2f} from {found.count} {found.source} pixels"
    return replace(component, level=found.level, error_estimate=found.spread, detail=note)


def _as_rivers(
    outcome: FillOutcome, surface: np.ndarray, rivers: dict[int, RiverFit], pixel_size: float
) -> FillOutcome:
    """The outcome with the holes judged rivers on their river surface (method ``river``)."""
    if not rivers:
        return outcome
    river = np.isin(outcome.labels, list(rivers)) & np.isfinite(surface)
    components = tuple(
        replace(
            c,
            method="river",
            level=math.nan,
            error_estimate=rivers[c.label].spread,
            detail=f"river: falls {rivers[c.label].drop:.2f} along {rivers[c.label].length_px * pixel_size:.0f}",
        )
        if c.label in rivers
        else c
        for c in outcome.components
    )
    return replace(
        outcome,
        heights=np.where(river, surface, outcome.heights),
        method_code=np.where(river, np.uint8(METHOD_CODES["river"]), outcome.method_code),
        components=components,
    )


def hole_record(
    hole_id: int, label: int, labels: np.ndarray, outcome: FillOutcome, distance: np.ndarray, result_path: str
) -> HoleFill:
    """The ``holes`` layer's fill fields of the hole labelled ``label`` in a :func:`fill_hole` outcome.

    ``distance``: from each pixel to measured data (survey units); ``result_path``: where
    the filled heights are kept. A hole none of whose pixels got a height has no support.
    """
    filled = (labels == label) & np.isfinite(outcome.heights)
    if not filled.any():
        return HoleFill(hole_id, NO_SUPPORT, detail="no measured rim to fill from")
    components = [c for c in outcome.components if c.label == label]
    return HoleFill(hole_id, FILLED, result_path=result_path, **_summary(outcome, components, filled, distance))


def _summary(outcome: FillOutcome, components: list[ComponentFill], filled: np.ndarray, distance: np.ndarray) -> dict:
    """The method that filled most of a hole's pixels, the worst error estimate, degradation notes."""
    counts = np.bincount(outcome.method_code[filled], minlength=256)
    errors = [c.error_estimate for c in components if np.isfinite(c.error_estimate)]
    return {
        "method": METHOD_NAMES.get(int(counts.argmax()), "unknown"),
        "pixels": int(filled.sum()),
        "max_distance": float(distance[filled].max()),
        "error_estimate": max(errors) if errors else math.nan,
        "degraded": any(c.degraded for c in components),
        "detail": "; ".join(c.detail for c in components if c.detail),
    }


def hole_ids_of_labels(labels: np.ndarray, hole_of_label: np.ndarray) -> np.ndarray:
    """A cell's hole-id raster from its part labels: 0 no hole, -1 a void the cell settled.

    ``hole_of_label``: part label -> hole id; its last entry serves label -1 (a settled void).
    """
    known = (labels > 0) & (labels < len(hole_of_label) - 1)
    ids = np.where(known, hole_of_label[np.where(known, labels, 0)], 0)
    return np.where(labels == -1, -1, ids)
