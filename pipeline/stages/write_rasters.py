"""The writer stage, one task per cell: the cell's rasters as Cloud-optimized GeoTIFFs.

It runs after every stage that changes a cell's heights, so the products are
written once, from the kept stage results, not inside the merge:

- ``dsm``: the highest point per pixel, with the filled holes painted in;
- ``fill_mask`` (when filling): 0 measured, the fill method's code on filled
  pixels (``pipeline.fill.METHOD_CODES``), 255 nodata (outside the survey area,
  and skipped holes);
- ``fill_distance`` (when filling): metres from each filled pixel to measured
  data, 0 on measured pixels;
- ``dsm_unfilled`` (``output.keep_unfilled``): the DSM before filling.

Small voids a cell settled itself (closed, under ``holes.min_area_m2``) have no
hole record; they are filled here from the cell's halo.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.ndimage as ndi

from ..config import Config
from ..fill import NOT_FILLED, fill_distance
from ..fill.by_cause import (
    FILLED,
    NO_RETURN,
    SMALL_VOID,
    FillParams,
    HoleFill,
    fill_hole,
    fill_kind,
    hole_ids_of_labels,
)
from ..grid import Cell, Grid
from ..io.intermediate import load_cell_statistics, load_labels, load_seen_voids, load_task_fill
from ..io.raster import RasterOptions, write_cog
from ..parameters import raster_options
from ..plan import SurveyPlan
from ..rasterize import PixelStatistics
from ..staging import Staging
from .fill_holes import FILL_HOLES, PLAN_FILLS, CellSource, fills_holes
from .link_holes import LINK_HOLES, HoleSet
from .merge_cells import MERGE_CELLS
from .stage import RunState, Stage, in_plan_order

#: Descriptions of the raster products, also used for their mosaics.
DESCRIPTIONS = {
    "dsm": "DSM: highest point per pixel",
    "dsm_filled": "DSM: highest point per pixel, holes filled (see fill_mask)",
    "dsm_unfilled": "DSM before filling: highest point per pixel",
    "fill_mask": "0 measured, fill method code on filled pixels, 255 nodata",
    "fill_distance": "Distance (m) from a filled pixel to measured data; 0 measured",
}


@dataclass(frozen=True)
class CellFill:
    """What the writer needs to paint a cell's fills: its labels, the hole results, the settings."""

    labels_path: str
    hole_of_label: np.ndarray
    hole_results: tuple[str, ...]  # kept results of the filled holes touching the cell
    params: FillParams
    unit_m: float  # metres per survey horizontal unit (fill_distance is in metres)


@dataclass(frozen=True)
class WriteTask:
    """Write the rasters of one cell core."""

    cell: Cell
    grid: Grid
    statistics_path: str
    paths: dict[str, str]  # product -> tile path ("dsm", and with fill: "fill_mask", "fill_distance", ...)
    raster_options: RasterOptions
    fill: CellFill | None = None


@dataclass(frozen=True)
class WriteResult:
    cell_id: str
    paths: dict[str, str]  # product -> the tile written; empty when the cell holds no point and no fill
    filled_px: int = 0


def cell_fills(
    plan: SurveyPlan, holes: HoleSet, sources: dict[str, CellSource], fills: list[HoleFill], params: FillParams
) -> dict[str, CellFill]:
    """Per merged cell: the kept results of the filled holes that have a part in it."""
    result_of = {f.hole_id: f.result_path for f in fills if f.status == FILLED and f.result_path}
    parts = holes.catalog.parts
    touching: dict[str, set[int]] = {cell_id: set() for cell_id in sources}
    for cell_id, hole_id in zip(parts["cell_id"], parts["hole_id"]):
        if int(hole_id) in result_of and str(cell_id) in touching:
            touching[str(cell_id)].add(int(hole_id))
    return {
        cell_id: CellFill(
            labels_path=source.labels_path,
            hole_of_label=source.hole_of_label,
            hole_results=tuple(sorted({result_of[h] for h in touching[cell_id]})),
            params=params,
            unit_m=plan.survey.horizontal_unit_m,
        )
        for cell_id, source in sources.items()
    }


def write_tasks(
    plan: SurveyPlan,
    config: Config,
    merged_cell_ids: list[str],
    staging: Staging,
    fills: dict[str, CellFill] | None = None,
) -> list[WriteTask]:
    """One task per merged cell; ``fills`` (cell id -> CellFill) when holes are filled."""
    cells = plan.cell_by_id()
    options = raster_options(config)
    products = ["dsm"]
    if fills is not None:
        products += ["fill_mask", "fill_distance"] + (["dsm_unfilled"] if config.output.keep_unfilled else [])
    return [
        WriteTask(
            cell=cells[cell_id],
            grid=plan.grid,
            statistics_path=str(staging.cell_statistics(cell_id)),
            paths={product: str(staging.raster_tile(product, cell_id)) for product in products},
            raster_options=options,
            fill=fills.get(cell_id) if fills is not None else None,
        )
        for cell_id in merged_cell_ids
    ]


def write_cell_rasters(task: WriteTask, *after: object) -> WriteResult:
    """Write a cell core's rasters from its kept statistics (and fills).

    ``after`` are results of the tasks this one must follow (the cell's merge, or the
    fills touching it); they are passed only so that Dask orders the tasks.
    """
    cell = task.cell
    needed = ("zmax", "count") if task.fill is None else ("zmax", "zmin", "count")
    stats = load_cell_statistics(task.statistics_path, needed)
    core = stats.crop(cell.window)
    if not core.count.any() and task.fill is None:
        return WriteResult(cell.id, {})
    rasters: dict[str, np.ndarray] = {"dsm": core.zmax}
    filled_px = 0
    if task.fill is not None:
        rasters["dsm_unfilled"] = core.zmax
        rasters["dsm"], rasters["fill_mask"], rasters["fill_distance"] = _paint_fills(task, stats, core)
        filled_px = int(((rasters["fill_mask"] > 0) & (rasters["fill_mask"] < NOT_FILLED)).sum())
        # a cell without a point is written where a fill reaches it: a lake wider than a cell
        if not core.count.any() and not filled_px:
            return WriteResult(cell.id, {})
    written = {}
    for product, path in task.paths.items():
        write_cog(
            path,
            rasters[product],
            transform=task.grid.window_transform(cell.window),
            crs_wkt=task.grid.crs_wkt,
            options=task.raster_options,
            nodata=NOT_FILLED if product == "fill_mask" else -9999.0,
            description=DESCRIPTIONS["dsm_filled" if product == "dsm" and task.fill else product],
            categorical=product == "fill_mask",
        )
        written[product] = path
    return WriteResult(cell.id, written, filled_px)


def _paint_fills(task: WriteTask, stats: PixelStatistics, core: PixelStatistics):
    """The filled DSM, the method codes and the distances over the cell core."""
    fill = task.fill
    assert fill is not None
    window = task.cell.window
    measured = core.count > 0
    dsm = np.where(measured, core.zmax, np.nan).astype(np.float32)
    codes = np.where(measured, 0, NOT_FILLED).astype(np.uint8)
    distance = np.where(measured, 0.0, np.nan).astype(np.float32)
    labels, _ = load_labels(fill.labels_path)
    cell_holes = hole_ids_of_labels(labels, fill.hole_of_label)
    for path in fill.hole_results:
        piece = load_task_fill(path, task.cell.id, window)
        if piece is None:
            continue
        here = piece.window.slices_within(window)
        # a coarse result (a water surface wider than a fill window) covers the shore's measured
        # pixels too: only the holes' own pixels take its values
        paint = (piece.hole_ids > 0) & (cell_holes[here] == piece.hole_ids)
        dsm[here] = np.where(paint, piece.heights, dsm[here])
        codes[here] = np.where(paint, piece.codes, codes[here])
        distance[here] = np.where(paint, piece.distance * fill.unit_m, distance[here])
    settled = cell_holes == -1
    if settled.any():
        seen = load_seen_voids(fill.labels_path)
        seen = np.zeros(settled.shape, bool) if seen is None else seen & settled
        near = fill_distance(stats.count > 0, pixel_size=fill.params.pixel_size)[window.slices_within(stats.window)]
        # seen unobstructed: no ground hidden behind a step, filled from the whole rim as a no-return void
        for voids, cause in ((settled & ~seen, SMALL_VOID), (seen, NO_RETURN)):
            if voids.any():
                kind = fill_kind(cause, fill.params)
                _fill_settled_voids(fill, stats, window, voids, (dsm, codes, distance), near, kind=kind)
    return dsm, codes, distance


def _fill_settled_voids(
    fill: CellFill, stats: PixelStatistics, window, settled, rasters: tuple, near: np.ndarray, *, kind: str
) -> None:
    """Small closed voids of the core, filled from the cell and its halo (they never cross a cell).

    ``rasters``: the core's DSM, method codes and distances, painted in place; ``near``: each core
    pixel's distance to measured data (pixels). No error estimate: these voids are not listed.
    """
    dsm, codes, distance = rasters
    halo = stats.window
    rows, cols = window.slices_within(halo)
    region = np.zeros(halo.shape, bool)
    region[rows, cols] = settled
    measured = stats.count > 0
    labels, _ = ndi.label(region, structure=[[0, 1, 0], [1, 1, 1], [0, 1, 0]])
    params = replace(fill.params, settings=replace(fill.params.settings, estimate_error=False))
    outcome = fill_hole(stats.zmax, stats.zmin, measured, labels, kind, params)
    done = settled & np.isfinite(outcome.heights[rows, cols])
    dsm[done] = outcome.heights[rows, cols][done]
    codes[done] = outcome.method_code[rows, cols][done]
    distance[done] = near[done] * fill.unit_m


# -- the stage's records: the rasters right after the merge, or after the fill ---------------


def merged_write_tasks(state: RunState) -> list[WriteTask]:
    """One task per cell, right after its merge; none when holes are filled (the writer then follows the fill)."""
    if fills_holes(state):
        return []
    return write_tasks(state.plan, state.config, [cell.id for cell in state.plan.cells], state.staging)


def filled_write_tasks(state: RunState) -> list[WriteTask]:
    """One task per merged cell, painting in the fills of the holes that have a part in it."""
    plan, fill_plan = state.plan, state[PLAN_FILLS]
    fills = cell_fills(plan, state[LINK_HOLES], fill_plan.sources, list(state[FILL_HOLES]), fill_plan.params)
    return write_tasks(plan, state.config, [r.cell_id for r in state[MERGE_CELLS]], state.staging, fills)


def _write_key(task: WriteTask) -> str:
    return f"write-{task.cell.id}"


def _write_label(task: WriteTask) -> str:
    return f"cell {task.cell.id} (write rasters)"


#: The writer in stage 2's graph: a cell's rasters as soon as it is merged (its bar stays empty when filling).
WRITE_MERGED: Stage[WriteTask, tuple[WriteResult, ...]] = Stage(
    name="write_rasters",
    recipes=merged_write_tasks,
    worker=write_cell_rasters,
    key=_write_key,
    label=_write_label,
    gather=lambda state, results: in_plan_order(state.plan, results),
    bar="write rasters",
    after=lambda task: ((MERGE_CELLS.name, task.cell.id),),
    priority=lambda task: 2,
    lap="merge_tail",
)

#: The writer after the fill: one task per merged cell.
WRITE_FILLED: Stage[WriteTask, tuple[WriteResult, ...]] = Stage(
    name="write_filled_rasters",
    recipes=filled_write_tasks,
    worker=write_cell_rasters,
    key=_write_key,
    label=_write_label,
    gather=lambda state, results: in_plan_order(state.plan, [*state[WRITE_MERGED], *results]),
    bar="write rasters",
    runs=fills_holes,
    lap="fill",
)
