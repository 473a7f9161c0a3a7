"""Walls and vertical holes, one task per cell: layers of ``holes.gpkg`` that no later stage reads.

Both come from a cell's merged statistics alone ([UAS] eq. 1 and 2, [WALL]), not from the
holes, the coverage or the lines of sight. Their tasks are therefore submitted as soon as
the merge is gathered, below every other task's priority, and gathered last
(:attr:`~.stage.Stage.deferred`): the workers fit the walls while the client finds the
flight lines and links the holes, and in the tail of detection and filling, instead of
inside detection's own time (on the 42 M point bench survey they were 55 % of it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..grid import Cell, Grid
from ..holes import height_jumps, vertical_holes
from ..holes.vertical import vertical_hole_records
from ..holes.walls import Wall, WallParams, find_walls
from ..io.intermediate import load_cell_statistics
from ..plan import HoleParams
from .detect_holes import finds_holes
from .merge_cells import MERGE_CELLS
from .stage import RunState, Stage, in_plan_order

#: The statistics a task reads (the others stay on disk).
NEEDED = ("zmax", "zmin", "count", "voxels")

#: Below every other stage's (0): a worker takes a wall task only when no other task waits.
LOWEST_PRIORITY = -10


@dataclass(frozen=True)
class WallTask:
    """Fit the walls and group the vertical holes of one cell core, with its halo as context."""

    cell: Cell
    grid: Grid
    statistics_path: str
    params: HoleParams


@dataclass(frozen=True)
class WallResult:
    cell_id: str
    vertical_holes: list[dict]  # records with a "wkb" polygon (:func:`~pipeline.holes.vertical.vertical_hole_records`)
    walls: list[Wall]
    jump_px: int  # height-jump pixels of the core ([UAS] eq. 1)


def wall_tasks(state: RunState) -> list[WallTask]:
    """One task per merged cell, in plan order."""
    plan = state.plan
    cells = plan.cell_by_id()
    return [WallTask(cells[r.cell_id], plan.grid, r.statistics_path, plan.hole_params) for r in state[MERGE_CELLS]]


def find_cell_walls(task: WallTask) -> WallResult:
    """The walls whose middle lies in the cell core, and the core's vertical-hole groups."""
    cell, grid, params = task.cell, task.grid, task.params
    stats = load_cell_statistics(task.statistics_path, NEEDED)
    core_rows, core_cols = cell.window.slices_within(stats.window)
    # float64 once, as find_walls compares heights: one jump raster serves the count and the walls
    zmax = stats.zmax.astype(np.float64)
    jumps = height_jumps(zmax, stats.zmin, jump_threshold=params.jump_threshold)
    vertical = vertical_holes(
        stats.zmax, stats.zmin, stats.voxels, voxel_height=params.voxel_height, jump_threshold=params.jump_threshold
    )[core_rows, core_cols]
    walls = find_walls(
        zmax,
        stats.zmin,
        jump_threshold=params.jump_threshold,
        count=stats.count,
        transform=grid.window_transform(stats.window),
        region=(core_rows, core_cols),
        params=WallParams(min_length_px=params.wall_min_length_px),
        jumps=jumps,
    )
    return WallResult(
        cell_id=cell.id,
        vertical_holes=vertical_hole_records(
            vertical,
            stats.crop(cell.window),
            grid.window_transform(cell.window),
            voxel_height=params.voxel_height,
            min_px=params.vertical_min_px,
        ),
        walls=walls,
        jump_px=int(jumps[core_rows, core_cols].sum()),
    )


#: One task per merged cell, fitted while the client and the other stages leave workers idle.
FIND_WALLS: Stage[WallTask, tuple[WallResult, ...]] = Stage(
    name="find_walls",
    recipes=wall_tasks,
    worker=find_cell_walls,
    key=lambda task: f"walls-{task.cell.id}",
    label=lambda task: f"cell {task.cell.id} (fit walls)",
    gather=lambda state, results: in_plan_order(state.plan, results),
    bar="fit walls",
    runs=finds_holes,
    priority=lambda task: LOWEST_PRIORITY,
    deferred=True,
    lap="walls",
)
