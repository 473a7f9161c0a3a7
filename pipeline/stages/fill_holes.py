"""Filling, one task per cell that owns holes: each hole filled whole, over its own window.

A hole belongs to the cell holding its first pixel (raster order). Its task reads
the hole's window (bounding box grown by ``fill.margin_px``) from the kept cell
statistics and part labels of every cell under it, fills the hole in one piece
the way its cause calls for (:mod:`pipeline.fill.by_cause`), and keeps the results of all its holes in
``work/fill/fill_<cell id>.npz``; the writer stage paints them into every cell
they cover. Filling a hole whole, never cell by cell, makes the fill independent of
the cell size: the same hole gives the same heights with 64-pixel or 1000-pixel
cells (docs/filling.md, "Cells and layers").

Holes are chosen for filling on the client (:func:`~pipeline.fill.by_cause.unfilled_reason`):
every void is filled but missed coverage (unless ``fill.missed_coverage``), and holes over the
limits a user set (``fill.max_area_m2``, ``fill.max_distance_m``; water never).

A water hole whose box is wider than :data:`MAX_WINDOW_PX` (a river across a large survey)
is filled over a coarser lattice of its window, ``factor`` pixels a side
(:func:`coarse_factor`): a water surface is level, or falls gently along its course, so a
coarser pixel keeps its level, and the writer paints that surface into the hole's own pixels.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass, replace

import numpy as np
import scipy.ndimage as ndi

from ..config import Config
from ..fill import fill_distance
from ..fill.by_cause import (
    FILLED,
    MISSED_NOTE,
    NO_RETURN,
    SMALL_VOID,
    TOO_LARGE,
    WATER,
    FillParams,
    HoleFill,
    fill_hole,
    fill_kind,
    hole_ids_of_labels,
    hole_record,
    unfilled_reason,
)
from ..grid import Grid, PixelWindow
from ..io.intermediate import load_cell_statistics, load_labels, save_task_fill
from ..parameters import fill_params
from ..plan import SurveyPlan
from ..staging import Staging
from .link_holes import LINK_HOLES, HoleSet
from .merge_cells import MERGE_CELLS
from .stage import RunState, Stage

#: Largest window (pixels) a hole is filled over at the grid's pixel (about 0.5 GB of a task's arrays);
#: a water hole spread wider is filled over a coarser lattice, other holes stay nodata (too large).
MAX_WINDOW_PX = 4096 * 4096


def coarse_factor(window_px: int, limit_px: int | None = None) -> int:
    """Pixels a side of the coarser lattice that brings a window of ``window_px`` within ``limit_px``
    (:data:`MAX_WINDOW_PX` by default; 1: none)."""
    return max(1, math.ceil(math.sqrt(window_px / (limit_px or MAX_WINDOW_PX))))


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
    factor: int = 1  # filled over a lattice of factor x factor pixels (a water hole wider than MAX_WINDOW_PX)


@dataclass(frozen=True)
class FillTask:
    """Fill the holes one cell owns."""

    owner_cell: str
    holes: tuple[HoleToFill, ...]
    sources: tuple[CellSource, ...]  # every cell whose core meets one of the holes' windows
    params: FillParams
    result_path: str  # the filled holes of the task, kept for the writer stage
    # water holes other cells fill whose boxes meet the task's: their water returns and shared ring
    # pixels are theirs here as in their own task (fill_cell_holes), whatever cell owns which hole
    water_neighbours: tuple[int, ...] = ()


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
    coarse: list[tuple[str, HoleToFill]] = []  # one task each: their windows are read coarser
    skipped = []
    for i, hole in enumerate(catalog.holes):
        hole_id = int(hole["hole_id"])
        # a small void is filled alike whether a cell settled it or it crossed cells: as an occlusion,
        # unless the sensor saw it unobstructed (a no-return void, filled from its whole rim)
        cause = str(holes.causes["cause"][i])
        if hole["is_small"] and cause != NO_RETURN:
            cause = SMALL_VOID
        reason = unfilled_reason(cause, area_m2=float(hole["area_px"]) * plan.pixel_area_m2, farthest=0, params=params)
        if reason:
            skipped.append(HoleFill(hole_id, reason[0], detail=reason[1]))
            continue
        row0, col0 = int(stats["row_min"][i]), int(stats["col_min"][i])
        box = PixelWindow(row0, col0, int(stats["row_max"][i]) - row0 + 1, int(stats["col_max"][i]) - col0 + 1)
        window = box.expand(margin).intersection(grid.window)
        factor = coarse_factor(window.height * window.width)
        if factor > 1 and fill_kind(cause, params) != WATER:
            skipped.append(HoleFill(hole_id, TOO_LARGE, detail=f"spread over {box.height} x {box.width} pixels"))
            continue
        owner = _cell_of_pixel(grid, int(stats["first_row"][i]), int(stats["first_col"][i]))
        hole_to_fill = HoleToFill(hole_id=hole_id, cause=cause, window=window, factor=factor)
        if factor > 1:
            coarse.append((owner, hole_to_fill))
        else:
            owned[owner].append(hole_to_fill)
    water = [h for holes_of_cell in owned.values() for h in holes_of_cell if fill_kind(h.cause, params) == WATER]
    tasks = []
    for owner, to_fill in owned.items():
        window = _union([hole.window for hole in to_fill])
        own = {hole.hole_id for hole in to_fill}
        neighbours = tuple(
            sorted(h.hole_id for h in water if h.hole_id not in own and not h.window.intersection(window).is_empty)
        )
        needed = _sources_under(grid, sources, to_fill)
        tasks.append(FillTask(owner, tuple(to_fill), needed, params, str(staging.cell_fill(owner)), neighbours))
    for owner, hole in coarse:
        name = f"{owner}_water{hole.hole_id}"
        tasks.append(
            FillTask(name, (hole,), _sources_under(grid, sources, [hole]), params, str(staging.cell_fill(name)))
        )
    return tasks, skipped


def _sources_under(grid: Grid, sources: dict[str, CellSource], holes: list[HoleToFill]) -> tuple[CellSource, ...]:
    """The kept cells whose cores meet the holes' windows."""
    needed: dict[str, CellSource] = {}
    for hole in holes:
        for ix, iy in grid.cell_indices_under(hole.window):
            cell_id = grid.cell(ix, iy).id
            if cell_id in sources:
                needed[cell_id] = sources[cell_id]
    return tuple(needed.values())


def largest_per_label(values: np.ndarray, labels: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """The largest of ``values`` (>= 0) over the pixels of each label in ``ids``; 0 for an id without pixels.

    ``scipy.ndimage.maximum`` with the same result sorts the whole window; this visits only
    the pixels of the labels asked for.
    """
    largest = np.zeros(len(ids))
    if not len(ids):
        return largest
    order = np.argsort(ids)
    sorted_ids = ids[order]
    labelled = labels > 0
    pixel_labels = labels[labelled]
    slot = np.minimum(np.searchsorted(sorted_ids, pixel_labels), len(ids) - 1)
    asked = sorted_ids[slot] == pixel_labels
    by_slot = np.zeros(len(ids))
    np.maximum.at(by_slot, slot[asked], values[labelled][asked])
    largest[order] = by_slot
    return largest


def fill_cell_holes(task: FillTask) -> list[HoleFill]:
    """Fill every hole a cell owns and keep the result in one file.

    The holes are read over the union of their windows and filled in one call per
    kind of fill (flat water, from the low side, from the whole rim): every hole is
    its own component of that call, solved as if it were alone (the kernels keep
    components independent), so batching changes no height, only the cost.
    """
    window = _union([hole.window for hole in task.holes])
    factor = max(hole.factor for hole in task.holes)
    zmax, zmin, measured, hole_ids, water, counts = _WindowReader(task.sources).read(window, factor=factor)
    params = task.params if factor == 1 else coarse_params(task.params, factor)
    distance = fill_distance(measured, pixel_size=params.pixel_size)
    ids = np.array([hole.hole_id for hole in task.holes], dtype=np.int64)
    farthest = largest_per_label(distance, hole_ids, ids)
    results: dict[int, HoleFill] = {}
    groups: dict[str, list[HoleToFill]] = defaultdict(list)
    for hole, far in zip(task.holes, farthest):
        reason = unfilled_reason(hole.cause, area_m2=0.0, farthest=float(far), params=params)
        if reason:
            results[hole.hole_id] = HoleFill(hole.hole_id, *reason, max_distance=float(far))
        else:
            groups[fill_kind(hole.cause, params)].append(hole)
    heights = np.full(zmax.shape, np.nan)
    codes = np.zeros(zmax.shape, np.uint8)
    filled_ids = np.zeros(zmax.shape, np.int64)
    present = set(np.unique(hole_ids).tolist()) if task.water_neighbours else set()
    for kind, group in groups.items():
        # water holes are filled with the other cells' water holes beside them, each hole's level read
        # from the water returns nearest to it and its own ring: the same evidence whichever cell owns it
        beside = [i for i in task.water_neighbours if kind == WATER and i in present]
        in_call = sorted([hole.hole_id for hole in group] + beside)
        labels = _group_labels(hole_ids, in_call)
        outcome = fill_hole(zmax, zmin, measured, labels, kind, params, water, counts)
        for hole in group:
            k = in_call.index(hole.hole_id) + 1
            record = hole_record(hole.hole_id, k, labels, outcome, distance, task.result_path)
            if factor > 1 and record.status == FILLED:
                note = f"filled over {factor} x {factor} pixels (its window is over {MAX_WINDOW_PX:,} pixels)"
                detail = "; ".join(d for d in (record.detail, note) if d)
                record = replace(record, pixels=record.pixels * factor**2, detail=detail)
            missed = hole.cause == "missed_coverage" and record.status == FILLED  # filled on request: flagged
            results[hole.hole_id] = replace(record, detail=MISSED_NOTE) if missed else record
        if beside:
            labels = np.where(np.isin(hole_ids, beside), 0, labels)  # their heights are their own tasks'
        done = (labels > 0) & np.isfinite(outcome.heights)
        heights[done], codes[done] = outcome.heights[done], outcome.method_code[done]
        filled_ids[done] = hole_ids[done]
    if filled_ids.any():
        if factor > 1:
            # every coarse pixel takes its nearest filled one's values: a fine pixel of the hole whose
            # coarse pixel also held data (the shore) is painted from the water beside it
            nearest = ndi.distance_transform_edt(filled_ids == 0, return_distances=False, return_indices=True)
            filled_ids, heights, codes, distance = (a[tuple(nearest)] for a in (filled_ids, heights, codes, distance))
        cells = [(source.cell_id, source.core) for source in task.sources]
        save_task_fill(task.result_path, window, filled_ids, heights, codes, distance, cells=cells, factor=factor)
    return [results[hole.hole_id] for hole in task.holes]


def coarse_params(params: FillParams, factor: int) -> FillParams:
    """The fill's settings on a lattice of ``factor`` x ``factor`` pixels: the lengths in pixels shrink, a pixel grows."""
    edge = params.water_edge
    return replace(
        params,
        pixel_size=params.pixel_size * factor,
        water_reach_px=max(1.0, params.water_reach_px / factor),
        water_edge=replace(edge, max_slope=edge.max_slope * factor),
    )


def _group_labels(hole_ids: np.ndarray, group: list[int]) -> np.ndarray:
    """Component labels 1..n for the holes of a group, 0 elsewhere."""
    lookup = np.zeros(max(int(hole_ids.max(initial=0)), max(group)) + 2, np.int32)
    lookup[group] = np.arange(1, len(group) + 1, dtype=np.int32)
    return np.where(hole_ids > 0, lookup[np.maximum(hole_ids, 0)], 0)


def _union(windows: list[PixelWindow]) -> PixelWindow:
    r0 = min(w.row_off for w in windows)
    c0 = min(w.col_off for w in windows)
    r1 = max(w.row_end for w in windows)
    c1 = max(w.col_end for w in windows)
    return PixelWindow(r0, c0, r1 - r0, c1 - c0)


def _cell_of_pixel(grid: Grid, row: int, col: int) -> str:
    (ix, iy), *_ = grid.cell_indices_under(PixelWindow(row, col, 1, 1))
    return grid.cell(ix, iy).id


class _WindowReader:
    """Heights, measured pixels and hole ids over any window, from the kept cell files."""

    def __init__(self, sources: tuple[CellSource, ...]) -> None:
        self._sources = sources
        self._loaded: dict[str, tuple] = {}

    def _cell(self, source: CellSource, *, keep: bool = True) -> tuple:
        """A cell's core rasters, kept for the next window unless ``keep`` is False (a coarse read
        passes over many cells once: keeping them all would gather the fine window after all)."""
        if source.cell_id in self._loaded:
            return self._loaded[source.cell_id]
        core = load_cell_statistics(source.statistics_path, ("zmax", "zmin", "count", "water")).crop(source.core)
        labels, _ = load_labels(source.labels_path)
        hole_ids = hole_ids_of_labels(labels, source.hole_of_label)
        rasters = (core.zmax, core.zmin, core.count, hole_ids, core.water)
        if keep:
            self._loaded[source.cell_id] = rasters
        return rasters

    def read(self, window: PixelWindow, *, factor: int = 1) -> tuple[np.ndarray, ...]:
        """The window's rasters, or with ``factor`` > 1 those of a lattice of ``factor`` x ``factor``
        pixels from the window's corner (:meth:`read_coarse`)."""
        if factor > 1:
            return self.read_coarse(window, factor)
        zmax = np.full(window.shape, np.nan, np.float64)
        zmin = np.full(window.shape, np.nan, np.float64)
        measured = np.zeros(window.shape, bool)
        hole_ids = np.zeros(window.shape, np.int64)
        water = np.zeros(window.shape, np.uint16)  # water-class returns: the level of water holes
        counts = np.zeros(window.shape, np.uint32)
        for source in self._sources:
            overlap = source.core.intersection(window)
            if overlap.is_empty:
                continue
            inside, within = overlap.slices_within(window), overlap.slices_within(source.core)
            cell_zmax, cell_zmin, cell_counts, cell_holes, cell_water = self._cell(source)
            zmax[inside] = cell_zmax[within]
            zmin[inside] = cell_zmin[within]
            measured[inside] = cell_counts[within] > 0
            counts[inside] = cell_counts[within]
            hole_ids[inside] = cell_holes[within]
            water[inside] = cell_water[within]
        return zmax, zmin, measured, hole_ids, water, counts

    def read_coarse(self, window: PixelWindow, factor: int) -> tuple[np.ndarray, ...]:
        """The window's rasters over coarse pixels of ``factor`` x ``factor``, one cell at a time.

        A coarse pixel holds the highest and the lowest return of its pixels, their points and
        water returns; it is measured where any of its pixels is, and part of a hole (the
        largest hole id among its pixels) where none is. The fine window is never gathered.
        """
        shape = (-(-window.height // factor), -(-window.width // factor))
        zmax = np.full(shape, np.nan)
        zmin = np.full(shape, np.nan)
        counts = np.zeros(shape, np.uint64)
        water = np.zeros(shape, np.uint64)
        hole_ids = np.zeros(shape, np.int64)
        for source in self._sources:
            overlap = source.core.intersection(window)
            if overlap.is_empty:
                continue
            within = overlap.slices_within(source.core)
            cell_zmax, cell_zmin, cell_counts, cell_holes, cell_water = self._cell(source, keep=False)
            row, col = overlap.row_off - window.row_off, overlap.col_off - window.col_off
            blocks, put = _coarse_blocks(row, col, overlap.shape, factor)
            zmax[blocks] = np.fmax(zmax[blocks], put(cell_zmax[within], np.nan, np.fmax))
            zmin[blocks] = np.fmin(zmin[blocks], put(cell_zmin[within], np.nan, np.fmin))
            counts[blocks] += put(cell_counts[within].astype(np.uint64), 0, np.add)
            water[blocks] += put(cell_water[within].astype(np.uint64), 0, np.add)
            hole_ids[blocks] = np.maximum(hole_ids[blocks], put(cell_holes[within].astype(np.int64), 0, np.maximum))
        measured = counts > 0
        hole_ids[measured] = 0
        return (
            zmax, zmin, measured, hole_ids,
            np.minimum(water, np.iinfo(np.uint16).max).astype(np.uint16),
            np.minimum(counts, np.iinfo(np.uint32).max).astype(np.uint32),
        )  # fmt: skip


def _coarse_blocks(row: int, col: int, shape: tuple[int, int], factor: int):
    """The coarse pixels a fine block at (``row``, ``col``) of a window meets, and how to reduce it onto them."""
    r0, c0 = row // factor, col // factor
    r1, c1 = (row + shape[0] - 1) // factor + 1, (col + shape[1] - 1) // factor + 1

    def put(values: np.ndarray, empty, reduce) -> np.ndarray:
        buffer = np.full(((r1 - r0) * factor, (c1 - c0) * factor), empty, dtype=values.dtype)
        buffer[row - r0 * factor : row - r0 * factor + shape[0], col - c0 * factor : col - c0 * factor + shape[1]] = (
            values
        )
        # the factor x factor strided views reduced pairwise: numpy's reduce over a short axis
        # of a 4-d view cost 0.25 ms a call (1.4 s of the 211 M-point bench survey's water fill)
        out = buffer[::factor, ::factor].copy()
        for i in range(factor):
            for j in range(factor):
                if i or j:
                    reduce(out, buffer[i::factor, j::factor], out=out)
        return out

    return (slice(r0, r1), slice(c0, c1)), put


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
    survey = plan.survey
    params = fill_params(
        state.config,
        plan.hole_params,
        pixel_size=plan.grid.resolution,
        horizontal_unit_m=survey.horizontal_unit_m,
        vertical_unit_m=survey.vertical_unit_m,
    )
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
