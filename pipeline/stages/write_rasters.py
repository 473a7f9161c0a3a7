"""The writer stage, one task per cell: the cell's DSM tile as a Cloud-optimized GeoTIFF.

It runs after every stage that changes a cell's heights, so the products are
written once, from the kept stage results, not inside the merge.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..config import Config
from ..grid import Cell, Grid
from ..io.intermediate import load_cell_statistics
from ..io.raster import RasterOptions, write_cog
from ..plan import SurveyPlan
from ..staging import Staging
from .merge_cells import CellResult


@dataclass(frozen=True)
class WriteTask:
    """Write the rasters of one cell core."""

    cell: Cell
    grid: Grid
    statistics_path: str
    dsm_path: str
    raster_options: RasterOptions


@dataclass(frozen=True)
class WriteResult:
    cell_id: str
    dsm_path: str | None  # None: the cell holds no point, no tile is written


def raster_options(config: Config) -> RasterOptions:
    out = config.output
    return RasterOptions(
        compress=out.compress,
        compress_level=out.compress_level,
        blocksize=out.blocksize,
        overview_resampling=out.overview_resampling,
    )


def write_tasks(plan: SurveyPlan, config: Config, merged_cell_ids: list[str], staging: Staging) -> list[WriteTask]:
    """One task per merged cell."""
    cells = plan.cell_by_id()
    options = raster_options(config)
    return [
        WriteTask(
            cell=cells[cell_id],
            grid=plan.grid,
            statistics_path=str(staging.cell_statistics(cell_id)),
            dsm_path=str(staging.dsm_tile(cell_id)),
            raster_options=options,
        )
        for cell_id in merged_cell_ids
    ]


def write_cell_rasters(task: WriteTask, merged: CellResult | None = None) -> WriteResult:
    """Write the DSM tile of a cell core from its kept statistics.

    ``merged`` is the cell's stage-2 result, passed only so that the task runs after it.
    """
    cell, grid = task.cell, task.grid
    core = load_cell_statistics(task.statistics_path).crop(cell.window)
    if not core.count.any():
        return WriteResult(cell.id, None)
    write_cog(
        task.dsm_path,
        core.zmax,
        transform=grid.window_transform(cell.window),
        crs_wkt=grid.crs_wkt,
        options=task.raster_options,
        description="DSM: highest point per pixel",
    )
    return WriteResult(cell.id, task.dsm_path)
