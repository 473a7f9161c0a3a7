"""Filling, one task per cell that owns holes: each hole filled whole, over its own window.

A hole belongs to the cell holding its first pixel (raster order). Its task reads
the hole's window (bounding box grown by ``fill.margin_px``) from the kept cell
statistics and part labels of every cell under it, fills the hole in one piece
with the method its cause calls for, and keeps the results of all its holes in
``work/fill/fill_<cell id>.npz``; the writer stage paints them into every cell
they cover. Filling a hole whole, never cell by cell, makes the fill independent of
the cell size: the same hole gives the same heights with 64-pixel or 1000-pixel
cells (docs/filling.md, "Cells and layers").

Holes are chosen for filling on the client: larger than ``fill.max_area_m2`` or
farther than ``fill.max_distance_m`` from measured data, a hole is not invented;
it stays nodata, marked ``skipped: too large``.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass, replace

import numpy as np
import scipy.ndimage as ndi

from ..config import Config
from ..fill import (
    METHOD_CODES,
    METHOD_NAMES,
    FillOutcome,
    FillSettings,
    clamp_to_rim,
    fill_distance,
    fill_region,
    lower_side_support,
    river_surfaces,
)
from ..grid import Grid, PixelWindow
from ..io.intermediate import load_cell_statistics, load_labels, save_task_fill
from ..plan import HoleParams, SurveyPlan
from ..staging import Staging
from .link_holes import LINK_HOLES, HoleSet
from .merge_cells import MERGE_CELLS
from .stage import RunState, Stage

#: The cause a small void is filled as (it is not classified when a cell settles it).
SMALL_VOID = "small void"
OCCLUSION = "occlusion"

#: Largest window (pixels) a hole is filled over; a hole spread wider is a strip for the flight plan.
MAX_WINDOW_PX = 4096 * 4096

#: How a hole is filled (:func:`fill_kind`).
WATER, LOW_SIDE, RIM = "water", "low", "rim"

#: ``fill_status`` values of the ``holes`` layer.
FILLED, TOO_LARGE, NO_SUPPORT, NOT_FILLED = "filled", "skipped: too large", "skipped: no support", "unfilled"


@dataclass(frozen=True)
class FillParams:
    """The ``[fill]`` settings in survey units, shared by every fill and writer task."""

    method: str
    by_cause: bool
    pixel_size: float  # survey units
    max_distance: float  # survey units
    water_percentile: float
    jump_threshold: float  # z units
    settings: FillSettings
    clamp_to_rim: bool = True
    river_min_drop: float = math.inf  # z units; inf: every water hole one level
    river_min_elongation: float = 4.0


@dataclass(frozen=True)
class CellSource:
    """Where a cell's kept heights and hole labels are, and how its labels map to hole ids."""

    cell_id: str
    core: PixelWindow
    statistics_path: str
    labels_path: str
    hole_of_label: np.ndarray  # part label -> hole id; the last entry serves label -1 (a settled void)


@dataclass(frozen=True)
class HoleToFill:
    hole_id: int
    cause: str
    window: PixelWindow  # the hole's bounding box grown by the margin, clipped to the grid


@dataclass(frozen=True)
class FillTask:
    """Fill the holes one cell owns."""

    owner_cell: str
    holes: tuple[HoleToFill, ...]
    sources: tuple[CellSource, ...]  # every cell whose core meets one of the holes' windows
    params: FillParams
    result_path: str  # the filled holes of the task, kept for the writer stage


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


def fill_params(plan: SurveyPlan, config: Config, params: HoleParams) -> FillParams:
    fill = config.fill
    return FillParams(
        method=fill.method,
        by_cause=fill.by_cause,
        pixel_size=plan.grid.resolution,
        max_distance=fill.max_distance_m / plan.survey.horizontal_unit_m,
        water_percentile=fill.water_percentile,
        jump_threshold=params.jump_threshold,
        settings=FillSettings(estimate_error=fill.estimate_error, tin_order=fill.tin_order),
        clamp_to_rim=fill.clamp_to_rim,
        river_min_drop=fill.river_min_drop_m / plan.survey.vertical_unit_m,
        river_min_elongation=fill.river_min_elongation,
    )


def cell_sources(
    plan: SurveyPlan, holes: HoleSet, staging: Staging, merged_cell_ids: list[str]
) -> dict[str, CellSource]:
    """Every merged cell's kept files and label-to-hole lookup (one pass over the parts table)."""
    parts = holes.catalog.parts
    by_cell: dict[str, list[int]] = defaultdict(list)
    for row, cell_id in enumerate(parts["cell_id"]):
        by_cell[str(cell_id)].append(row)
    cells = plan.cell_by_id()
    sources = {}
    for cell_id in merged_cell_ids:
        rows = np.asarray(by_cell.get(cell_id, []), dtype=np.int64)
        labels = parts["label"][rows] if len(rows) else np.empty(0, np.int64)
        lookup = np.zeros(int(labels.max()) + 2 if len(labels) else 2, dtype=np.int64)
        lookup[labels] = parts["hole_id"][rows]
        lookup[-1] = -1
        sources[cell_id] = CellSource(
            cell_id,
            cells[cell_id].window,
            str(staging.cell_statistics(cell_id)),
            str(staging.cell_labels(cell_id)),
            lookup,
        )
    return sources


def fill_tasks(
    plan: SurveyPlan,
    config: Config,
    holes: HoleSet,
    sources: dict[str, CellSource],
    params: FillParams,
    staging: Staging,
) -> tuple[list[FillTask], list[HoleFill]]:
    """One task per cell owning holes to fill; the holes skipped before any work."""
    grid = plan.grid
    catalog, stats = holes.catalog, holes.catalog.stats
    margin = config.fill.margin_px
    owned: dict[str, list[HoleToFill]] = defaultdict(list)
    skipped = []
    for i, hole in enumerate(catalog.holes):
        hole_id = int(hole["hole_id"])
        if float(hole["area_px"]) * plan.pixel_area_m2 > config.fill.max_area_m2:
            skipped.append(
                HoleFill(hole_id, TOO_LARGE, detail=f"area over fill.max_area_m2 = {config.fill.max_area_m2:g}")
            )
            continue
        row0, col0 = int(stats["row_min"][i]), int(stats["col_min"][i])
        box = PixelWindow(row0, col0, int(stats["row_max"][i]) - row0 + 1, int(stats["col_max"][i]) - col0 + 1)
        if box.height * box.width > MAX_WINDOW_PX:
            skipped.append(HoleFill(hole_id, TOO_LARGE, detail=f"spread over {box.height} x {box.width} pixels"))
            continue
        owner = _cell_of_pixel(grid, int(stats["first_row"][i]), int(stats["first_col"][i]))
        owned[owner].append(
            HoleToFill(
                hole_id=hole_id,
                # a small void is filled alike whether a cell settled it or it crossed cells
                cause=SMALL_VOID if hole["is_small"] else str(holes.causes["cause"][i]),
                window=box.expand(margin).intersection(grid.window),
            )
        )
    tasks = []
    for owner, to_fill in owned.items():
        needed: dict[str, CellSource] = {}
        for hole in to_fill:
            for ix, iy in grid.cell_indices_under(hole.window):
                cell_id = grid.cell(ix, iy).id
                if cell_id in sources:
                    needed[cell_id] = sources[cell_id]
        tasks.append(FillTask(owner, tuple(to_fill), tuple(needed.values()), params, str(staging.cell_fill(owner))))
    return tasks, skipped


def fill_cell_holes(task: FillTask) -> list[HoleFill]:
    """Fill every hole a cell owns and keep the result in one file.

    The holes are read over the union of their windows and filled in one call per
    kind of fill (flat water, from the low side, from the whole rim): every hole is
    its own component of that call, solved as if it were alone (the kernels keep
    components independent), so batching changes no height, only the cost.
    """
    window = _union([hole.window for hole in task.holes])
    zmax, zmin, measured, hole_ids = _WindowReader(task.sources).read(window)
    params = task.params
    distance = fill_distance(measured, pixel_size=params.pixel_size)
    ids = np.array([hole.hole_id for hole in task.holes], dtype=np.int64)
    farthest = ndi.maximum(distance, labels=hole_ids, index=ids) if len(ids) else np.empty(0)
    results: dict[int, HoleFill] = {}
    groups: dict[str, list[HoleToFill]] = defaultdict(list)
    for hole, far in zip(task.holes, farthest):
        if far > params.max_distance:
            detail = "farther from data than fill.max_distance_m"
            results[hole.hole_id] = HoleFill(hole.hole_id, TOO_LARGE, max_distance=float(far), detail=detail)
        else:
            groups[fill_kind(hole.cause, params)].append(hole)
    heights = np.full(window.shape, np.nan)
    codes = np.zeros(window.shape, np.uint8)
    filled_ids = np.zeros(window.shape, np.int64)
    for kind, group in groups.items():
        labels = _group_labels(hole_ids, [hole.hole_id for hole in group])
        outcome = fill_hole(zmax, zmin, measured, labels, kind, params)
        for k, hole in enumerate(group, start=1):
            results[hole.hole_id] = _record(hole.hole_id, k, labels, outcome, distance, task.result_path)
        done = (labels > 0) & np.isfinite(outcome.heights)
        heights[done], codes[done] = outcome.heights[done], outcome.method_code[done]
        filled_ids[done] = hole_ids[done]
    if filled_ids.any():
        save_task_fill(task.result_path, window, filled_ids, heights, codes, distance)
    return [results[hole.hole_id] for hole in task.holes]


def fill_kind(cause: str, params: FillParams) -> str:
    """How a hole of this cause is filled: ``water`` flat, ``low`` from the low side, ``rim`` from all of it."""
    if not params.by_cause:
        return RIM
    if cause == "water":
        return WATER
    return LOW_SIDE if cause in (OCCLUSION, SMALL_VOID) else RIM


def _group_labels(hole_ids: np.ndarray, group: list[int]) -> np.ndarray:
    """Component labels 1..n for the holes of a group, 0 elsewhere."""
    lookup = np.zeros(max(int(hole_ids.max(initial=0)), max(group)) + 2, np.int32)
    lookup[group] = np.arange(1, len(group) + 1, dtype=np.int32)
    return np.where(hole_ids > 0, lookup[np.maximum(hole_ids, 0)], 0)


def _record(
    hole_id: int, label: int, labels: np.ndarray, outcome: FillOutcome, distance: np.ndarray, path: str
) -> HoleFill:
    filled = (labels == label) & np.isfinite(outcome.heights)
    if not filled.any():
        return HoleFill(hole_id, NO_SUPPORT, detail="no measured rim to fill from")
    components = [c for c in outcome.components if c.label == label]
    return HoleFill(hole_id, FILLED, result_path=path, **_summary(outcome, components, filled, distance))


def _union(windows: list[PixelWindow]) -> PixelWindow:
    r0 = min(w.row_off for w in windows)
    c0 = min(w.col_off for w in windows)
    r1 = max(w.row_end for w in windows)
    c1 = max(w.col_end for w in windows)
    return PixelWindow(r0, c0, r1 - r0, c1 - c0)


def fill_hole(
    zmax: np.ndarray,
    zmin: np.ndarray,
    measured: np.ndarray,
    labels: np.ndarray,
    kind: str,
    params: FillParams,
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
        return fill_water(np.where(measured, zmin, np.nan), heights, labels, params)
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


def fill_water(water_rim: np.ndarray, bank_rim: np.ndarray, labels: np.ndarray, params: FillParams) -> FillOutcome:
    """Water holes: a lake flat at its rim level, a river stepping down along its course (hydro-flattening).

    ``water_rim``: the lowest return of measured pixels, ``bank_rim`` the highest, NaN
    elsewhere. Every hole is filled flat first, from the lowest returns of its whole rim;
    those :func:`~pipeline.fill.river_surfaces` judges rivers (elongated, falling at least
    ``river_min_drop``) get their river surface instead, method ``river``. A river's bank
    levels come from the highest returns: a rim pixel on the shore may hold a return
    from under the water's edge, which a whole rim outvotes but a short station does not.
    """
    settings = replace(params.settings, flat_percentile=params.water_percentile)
    outcome = fill_region(
        water_rim, labels > 0, method="flat", settings=settings, pixel_size=params.pixel_size, labels=labels
    )
    if not math.isfinite(params.river_min_drop):
        return outcome
    surface, fits = river_surfaces(
        bank_rim,
        outcome.labels,
        min_drop=params.river_min_drop,
        min_elongation=params.river_min_elongation,
        percentile=params.water_percentile,
    )
    rivers = {fit.label: fit for fit in fits if fit.is_river}
    if not rivers:
        return outcome
    river = np.isin(outcome.labels, list(rivers)) & np.isfinite(surface)
    components = tuple(
        replace(
            c,
            method="river",
            level=math.nan,
            error_estimate=math.nan,
            detail=f"river: falls {rivers[c.label].drop:.2f} along {rivers[c.label].length_px * params.pixel_size:.0f}",
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


def _summary(outcome: FillOutcome, components: list, filled: np.ndarray, distance: np.ndarray) -> dict:
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
    """A cell's hole-id raster from its part labels: 0 no hole, -1 a void the cell settled."""
    known = (labels > 0) & (labels < len(hole_of_label) - 1)
    ids = np.where(known, hole_of_label[np.where(known, labels, 0)], 0)
    return np.where(labels == -1, -1, ids)


def _cell_of_pixel(grid: Grid, row: int, col: int) -> str:
    (ix, iy), *_ = grid.cell_indices_under(PixelWindow(row, col, 1, 1))
    return grid.cell(ix, iy).id


class _WindowReader:
    """Heights, measured pixels and hole ids over any window, from the kept cell files."""

    def __init__(self, sources: tuple[CellSource, ...]) -> None:
        self._sources = sources
        self._loaded: dict[str, tuple] = {}

    def _cell(self, source: CellSource) -> tuple:
        if source.cell_id not in self._loaded:
            core = load_cell_statistics(source.statistics_path, ("zmax", "zmin", "count")).crop(source.core)
            labels, _ = load_labels(source.labels_path)
            hole_ids = hole_ids_of_labels(labels, source.hole_of_label)
            self._loaded[source.cell_id] = (core.zmax, core.zmin, core.count > 0, hole_ids)
        return self._loaded[source.cell_id]

    def read(self, window: PixelWindow) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        zmax = np.full(window.shape, np.nan, np.float64)
        zmin = np.full(window.shape, np.nan, np.float64)
        measured = np.zeros(window.shape, bool)
        hole_ids = np.zeros(window.shape, np.int64)
        for source in self._sources:
            overlap = source.core.intersection(window)
            if overlap.is_empty:
                continue
            inside, within = overlap.slices_within(window), overlap.slices_within(source.core)
            cell_zmax, cell_zmin, cell_measured, cell_holes = self._cell(source)
            zmax[inside] = cell_zmax[within]
            zmin[inside] = cell_zmin[within]
            measured[inside] = cell_measured[within]
            hole_ids[inside] = cell_holes[within]
        return zmax, zmin, measured, hole_ids


# -- the stage's records ---------------------------------------------------------------------


@dataclass(frozen=True)
class FillPlan:
    """The fill's recipes, made on the client after linking: the tasks, and what the writer needs."""

    params: FillParams
    sources: dict[str, CellSource]  # every merged cell's kept files and label-to-hole lookup
    tasks: tuple[FillTask, ...]
    skipped: tuple[HoleFill, ...]  # the holes not filled, decided before any work


def fills_holes(state: RunState) -> bool:
    return state.config.holes.enabled and state.config.fill.enabled


def plan_fills(state: RunState, results: list[object]) -> FillPlan:
    plan, holes = state.plan, state[LINK_HOLES]
    params = fill_params(plan, state.config, plan.hole_params)
    sources = cell_sources(plan, holes, state.staging, [r.cell_id for r in state[MERGE_CELLS]])
    tasks, skipped = fill_tasks(plan, state.config, holes, sources, params, state.staging)
    return FillPlan(params, sources, tuple(tasks), tuple(skipped))


def by_hole(state: RunState, results: list[list[HoleFill]]) -> tuple[HoleFill, ...]:
    """Gather: every hole's fill record (the skipped ones too), by hole id."""
    fills = list(state[PLAN_FILLS].skipped)
    for cell_fills in results:
        fills.extend(cell_fills)
    return tuple(sorted(fills, key=lambda f: f.hole_id))


PLAN_FILLS: Stage[object, FillPlan] = Stage(name="plan_fills", gather=plan_fills, runs=fills_holes)

#: One task per cell owning holes to fill.
FILL_HOLES: Stage[FillTask, tuple[HoleFill, ...]] = Stage(
    name="fill_holes",
    recipes=lambda state: state[PLAN_FILLS].tasks,
    worker=fill_cell_holes,
    key=lambda task: f"fill-{task.owner_cell}",
    label=lambda task: f"cell {task.owner_cell} (fill)",
    gather=by_hole,
    bar="fill holes",
    runs=fills_holes,
)
