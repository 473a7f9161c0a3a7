"""What a stage is, for the engine that walks the stages: one :class:`Stage` record per stage.

A record names the stage's slots (recipe builder, worker, key, label, gather) and how
its tasks are scheduled; :mod:`pipeline.stages.registry` lists the records in the order
they run, and :mod:`pipeline.run` walks that list (the only module that knows Dask). A
stage's recipe builder and gather step read a :class:`RunState`: the plan, the
configuration, the staging folder and what the stages before it gathered.

Nothing here imports a stage: a stage module imports this one, and reads the results of
the stages before it by their records (``state[merge_cells.MERGE_CELLS]``), so the results are
typed without any module knowing the ones after it.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

from ..config import Config
from ..plan import SurveyPlan
from ..staging import Staging

T = TypeVar("T")  # a stage's task record
R = TypeVar("R")  # a stage's gathered result
R_co = TypeVar("R_co", covariant=True)

#: A task another task takes the result of: (the stage's name, the task's ident in it).
Dependency = tuple[str, Hashable]


@dataclass(frozen=True)
class RunState:
    """What a stage's recipe builder and gather step read: the run's plan, configuration and
    staging folder, the known water, and the gathered results of the stages before it."""

    plan: SurveyPlan
    config: Config
    staging: Staging
    water: Any = None  # the known water's polygons in the survey CRS (shapely), or None
    results: Mapping[str, Any] = field(default_factory=dict)  # stage name -> its gathered result

    def __getitem__(self, stage: Stage[Any, R]) -> R:
        return self.results[stage.name]

    def get(self, stage: Stage[Any, R], default: R) -> R:
        """The stage's result, or ``default`` when the stage did not run."""
        return self.results.get(stage.name, default)

    def with_result(self, stage: Stage[Any, R], result: R) -> RunState:
        return RunState(self.plan, self.config, self.staging, self.water, {**self.results, stage.name: result})


def _no_tasks(state: RunState) -> Sequence[Any]:
    return ()


def _always(state: RunState) -> bool:
    return True


def _nothing(task: Any) -> tuple[Dependency, ...]:
    return ()


def _normal(task: Any) -> int:
    return 0


def _unnamed(task: Any) -> str:
    return repr(task)


@dataclass(frozen=True, kw_only=True)
class Stage(Generic[T, R_co]):
    """One stage: its slots, and how the engine schedules its tasks.

    A stage without a worker runs on the client only: its gather step (called with no
    results) is all its work (planning the read tasks, linking the holes).
    """

    name: str  # unique; names the stage's result in the run state
    recipes: Callable[[RunState], Sequence[T]] = _no_tasks  # recipe builder: the task records, in plan order
    worker: Callable[..., Any] | None = None  # module level, picklable: worker(task, *results of its `after`)
    key: Callable[[T], str] = _unnamed  # the task's stable name: its kept result (resume, incremental)
    label: Callable[[T], str] = _unnamed  # how a failure names the task ("cell 500_1000 (merge)")
    gather: Callable[[RunState, list[Any]], R_co]  # the workers' results (completion order) -> the stage's result
    bar: str = ""  # the progress bar's label
    runs: Callable[[RunState], bool] = _always  # whether this run has the stage
    ident: Callable[[T], Hashable] | None = None  # how later tasks name a task of this stage (default: its key)
    after: Callable[[T], tuple[Dependency, ...]] = _nothing  # tasks of the same batch whose results it takes
    priority: Callable[[T], int] = _normal  # Dask priority: higher runs first
    adopt: Callable[[T, Any], Any] | None = None  # a previous run's result of the same key -> this run's
    on_result: Callable[[Any], int] | None = None  # as each result arrives: tell the user; its points (bar rate)
    streams: bool = False  # submitted with the next stage and gathered in the same loop (its tasks wait for ours)
    deferred: bool = False  # submitted when reached, gathered after every other stage (no stage reads its result)
    lap: str | None = None  # the timer lap taken when the stage is done (manifest ``stage_seconds``)

    def ident_of(self, task: T) -> Hashable:
        return self.key(task) if self.ident is None else self.ident(task)


def in_plan_order(plan: SurveyPlan, results: Sequence[R], cell_id: Callable[[R], str] | None = None) -> tuple[R, ...]:
    """Per-cell results in the plan's order of cells, whatever order their tasks finished in."""
    order = {cell.id: i for i, cell in enumerate(plan.cells)}
    of = cell_id or (lambda result: result.cell_id)  # type: ignore[attr-defined]
    return tuple(sorted(results, key=lambda result: order[of(result)]))
