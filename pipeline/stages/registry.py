"""The stages of a run in the order they run, and the record of what they gathered.

:mod:`pipeline.run` walks :data:`STAGES`: a stage that does not run in this
configuration is passed over, a stage without a worker runs on the client, and the
stages that stream (stage 1, the merge) are submitted with the next one and gathered
in the same loop, so that a cell runs as soon as its tiles are done.
A new stage is one module in ``pipeline/stages/`` with its :class:`~.stage.Stage`
record, and one entry here, after the stages whose results it reads.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..plan import SurveyPlan
from ..survey.ground_level import GroundLevel
from .bin_tiles import BIN_TILES, READ_TASKS, TileResult
from .detect_holes import COVERAGE, DETECT_HOLES, GAP_VOIDS, DetectResult
from .fill_holes import FILL_HOLES, PLAN_FILLS, HoleFill
from .find_walls import FIND_WALLS, WallResult
from .link_holes import LINK_HOLES, HoleSet
from .merge_cells import MERGE_CELLS, CellResult
from .stage import RunState, Stage
from .write_points import WRITE_POINTS
from .write_rasters import WRITE_FILLED, WRITE_MERGED, WriteResult

#: Every stage, in the order it runs (a stage reads only the results of stages before it).
STAGES: tuple[Stage[Any, Any], ...] = (
    READ_TASKS,  # client: stage 1's recipes
    BIN_TILES,  # per read task: decode once, bin; the file's SHA-256    } one graph, one gather loop
    MERGE_CELLS,  # per cell: merge the tiles touching it               }
    WRITE_MERGED,  # per cell: the rasters, when nothing is filled      }
    FIND_WALLS,  # per cell: walls, vertical holes (deferred: gathered last, while the workers are idle)
    COVERAGE,  # client: footprint, flight lines, coverage gaps
    GAP_VOIDS,  # per cell a gap reaches: is the gap empty?
    DETECT_HOLES,  # per cell: hole parts
    LINK_HOLES,  # client: holes linked across cells, causes
    PLAN_FILLS,  # client: the fill's recipes
    FILL_HOLES,  # per cell owning holes: fill each hole whole
    WRITE_FILLED,  # per cell: the rasters with the fills
    WRITE_POINTS,  # per tile: the repaired point clouds (output.points)
)


@dataclass(frozen=True)
class RunResults:
    """What a run's stages gathered, in plan order: :mod:`pipeline.outputs` writes the products from it."""

    tiles: tuple[TileResult, ...]  # one per file decoded, in tile order
    failed: tuple[dict[str, str], ...]  # {"path", "reason"}: files stage 1 skipped or used no point of
    cells: tuple[CellResult, ...]
    written: tuple[WriteResult, ...]  # the raster tiles written, per cell
    inputs: Mapping[str, dict[str, Any]]  # path -> size, time and checksum
    detected: tuple[DetectResult, ...] = ()
    walls: tuple[WallResult, ...] = ()  # walls and vertical holes per cell (hole detection on)
    holes: HoleSet | None = None  # None: holes.enabled is off
    fills: tuple[HoleFill, ...] | None = None  # None: nothing was filled
    points: tuple[str, ...] = ()  # the repaired point clouds (output.points), relative to the run folder
    resumed_tasks: int = 0  # tasks an interrupted run had finished, not run again
    reused_tasks: int = 0  # results of unchanged tiles and cells taken from the previous run (incremental)

    @property
    def ground(self) -> GroundLevel:
        """The ground-class points of every tile, and those at z = 0 (heights above the ground?)."""
        return sum((r.ground for r in self.tiles), GroundLevel())

    def skipped(self, plan: SurveyPlan) -> list[dict[str, str]]:
        """Every input left out: at the scan (bad headers), and in stage 1."""
        return [*plan.survey.skipped, *self.failed]


def run_results(state: RunState, *, resumed_tasks: int = 0, reused_tasks: int = 0) -> RunResults:
    """The record of a walked run's results."""
    decoded = state[BIN_TILES]
    return RunResults(
        tiles=decoded.tiles,
        failed=decoded.failed,
        cells=state[MERGE_CELLS],
        written=state.get(WRITE_FILLED, state[WRITE_MERGED]),
        inputs=decoded.inputs,
        detected=state.get(DETECT_HOLES, ()),
        walls=state.get(FIND_WALLS, ()),
        holes=state.get(LINK_HOLES, None),
        fills=state.get(FILL_HOLES, None),
        points=state.get(WRITE_POINTS, ()),
        resumed_tasks=resumed_tasks,
        reused_tasks=reused_tasks,
    )
