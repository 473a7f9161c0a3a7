"""Memory a planned run will need, checked before any work starts.

A pixel size far finer than a tile (``grid.resolution_m = 0.01`` on a 1 km tile) or
tiles on two continents (``--target-crs``) make a grid whose arrays cannot exist: the
run would fail late, with ``MemoryError`` on a worker or on the client. The plan says
how large every array will be, so such a run is refused at planning with one line.

The estimates are per pixel (or per footprint block) of what the stages allocate:

* a stage-1 read task holds its window's accumulators (:class:`pipeline.rasterize.
  HeightMapAccumulator`: seven statistics and two voxel masks, :data:`READ_BYTES_PER_PX`, and
  the ground's sums where holes are sought, :data:`GROUND_BYTES_PER_PX`);
* a cell task (merge, detection, filling, writing) holds a few statistics and masks of
  its cell with its halo (:data:`CELL_BYTES_PER_PX`);
* the client holds the survey's footprint map, one byte per block of the data's
  bounding box and its closing's temporaries (:data:`FOOTPRINT_BYTES_PER_BLOCK`).

A task must fit in one worker's memory (``dask.memory_limit``, or the machine's memory
shared among the local workers for ``"auto"``); the footprint map in half the client's
memory.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass

from .config import AUTO, Config
from .errors import ConfigError, InputDataError

#: Bytes per pixel of a read task's accumulators: zmax, zmin, count (4 each), voxels,
#: water, source, covered (2 each), the voxel base and bits (8 each).
READ_BYTES_PER_PX = 36
#: ... and where holes are sought, the ground points' height sums and counts (8 + 4): the take-off's.
GROUND_BYTES_PER_PX = 12
#: Bytes per pixel of a cell task with its halo (statistics, masks, labels, heights).
CELL_BYTES_PER_PX = 64
#: Bytes per footprint block of the survey's footprint map on the client (the map, its
#: closing and filling, the border).
FOOTPRINT_BYTES_PER_BLOCK = 8
#: The share of the client's memory the footprint map may take.
CLIENT_SHARE = 0.5


@dataclass(frozen=True)
class MemoryBudget:
    """Bytes one task may use on a worker, and the survey-wide maps on the client."""

    task_bytes: int
    task_source: str  # what says so, for the message
    client_bytes: int


def memory_budget(config: Config, *, scheduler: str | None = None) -> MemoryBudget:
    """The budget of a run: ``dask.memory_limit`` per worker, else the machine's memory shared by its workers.

    With ``scheduler`` (a remote cluster) and ``"auto"``, this machine's memory stands in
    for a worker's: a task larger than that is absurd anywhere.
    """
    total = _total_memory()
    limit = config.dask.memory_limit
    if limit and limit != AUTO:
        try:
            task_bytes = _parse_memory(limit, total)
        except ValueError:
            raise ConfigError(f"dask.memory_limit = {limit!r}: expected a size such as '4GB' or 'auto'") from None
        source = f"dask.memory_limit = {limit}"
    elif scheduler:
        task_bytes, source = total, "this machine's memory"
    else:
        workers = config.dask.workers or os.cpu_count() or 1
        task_bytes = total // workers
        source = f"the machine's memory shared by {workers} worker(s); dask.memory_limit"
    return MemoryBudget(task_bytes=task_bytes, task_source=source, client_bytes=int(total * CLIENT_SHARE))


def check_plan_memory(plan, config: Config, budget: MemoryBudget) -> None:
    """Refuse a plan whose tasks or survey maps cannot fit in memory, with one line.

    Raises
    ------
    ConfigError
        A task too large for a worker when ``grid.resolution_m`` or ``grid.cell_size_m``
        was set (the fix is a coarser pixel or a smaller cell).
    InputDataError
        The data's extent makes the survey's footprint map absurd (tiles far apart, e.g.
        on two continents), or a task too large with the pixel size chosen automatically.
    """
    _check_footprint(plan, budget)
    _check_tasks(plan, config, budget)


def _check_footprint(plan, budget: MemoryBudget) -> None:
    tiles = plan.survey.tiles
    minx = min(t.bounds[0] for t in tiles)
    miny = min(t.bounds[1] for t in tiles)
    maxx = max(t.bounds[2] for t in tiles)
    maxy = max(t.bounds[3] for t in tiles)
    block = plan.grid.resolution * plan.block_px
    blocks = (int((maxx - minx) // block) + 1) * (int((maxy - miny) // block) + 1)
    need = blocks * FOOTPRINT_BYTES_PER_BLOCK
    if need > budget.client_bytes:
        unit = plan.survey.horizontal_unit_m
        raise InputDataError(
            "INPUT",
            f"the tiles span {(maxx - minx) * unit / 1000:,.0f} x {(maxy - miny) * unit / 1000:,.0f} km in the "
            f"survey CRS: the survey's footprint map would need {_size(need)} (more than half this machine's "
            f"{_size(budget.client_bytes * 2)}); are they one survey? Run each area on its own",
        )


def _check_tasks(plan, config: Config, budget: MemoryBudget) -> None:
    per_px = READ_BYTES_PER_PX + (GROUND_BYTES_PER_PX if config.holes.enabled else 0)
    reads = [
        (w.height * w.width * per_px, plan.survey.tiles[plan.reads[i].tile_index].path, w)
        for i, w in enumerate(plan.read_windows)
    ]
    cells = [
        (c.halo_window.height * c.halo_window.width * CELL_BYTES_PER_PX, f"cell {c.id}", c.halo_window)
        for c in plan.cells[:1]  # every cell has the same size
    ]
    need, what, window = max(reads + cells, key=lambda item: item[0])
    if need <= budget.task_bytes:
        return
    sizing = plan.sizing
    message = (
        f"{what}: a task over it needs about {_size(need)} ({window.height:,} x {window.width:,} pixels of "
        f"{sizing.resolution_m:g} m), more than a worker's {_size(budget.task_bytes)} ({budget.task_source})"
    )
    if what.startswith("cell "):
        hint = "use a smaller grid.cell_size_m or a coarser grid.resolution_m"
    else:
        hint = 'use a coarser grid.resolution_m (or "auto")'
    if sizing.resolution_source == "set" or what.startswith("cell "):
        key = f"grid.resolution_m = {sizing.resolution_m:g}"
        if what.startswith("cell "):
            key += f", grid.cell_size_m = {sizing.cell_size_m:g}"
        raise ConfigError(f"{key}: {message}; {hint}")
    raise InputDataError(what, f"{message}; split the tile or {hint}")


def _total_memory() -> int:
    import psutil

    return int(psutil.virtual_memory().total)


def _parse_memory(limit: str, total: int) -> int:
    """``"4GB"``, ``"500MiB"``, a byte count, or a fraction of the machine's memory (``"0.5"``), as distributed reads it.

    Parsed here (units as ``dask.utils.parse_bytes`` reads them): only run.py and cluster.py import Dask.
    """
    text = str(limit).strip()
    try:
        value = float(text)
    except ValueError:
        return _parse_bytes(text)
    if 0 < value <= 1:
        return int(total * value)
    return int(value)


#: Byte units as Dask reads them: decimal (kB, MB, ...) and binary (KiB, MiB, ...), case-insensitive.
_UNITS = {
    "b": 1, "kb": 10**3, "mb": 10**6, "gb": 10**9, "tb": 10**12, "pb": 10**15,
    "kib": 2**10, "mib": 2**20, "gib": 2**30, "tib": 2**40, "pib": 2**50,
    "k": 10**3, "m": 10**6, "g": 10**9, "t": 10**12, "p": 10**15,
}  # fmt: skip


def _parse_bytes(text: str) -> int:
    """``"4GB"``, ``"4 GiB"``, ``"500MB"`` -> bytes; ValueError for anything else."""
    match = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:e[+-]?[0-9]+)?)\s*([a-zA-Z]*)\s*", text)
    if not match or match.group(2).lower() not in _UNITS | {"": 1}:
        raise ValueError(f"not a size: {text!r}")
    return int(float(match.group(1)) * _UNITS.get(match.group(2).lower(), 1))


def _size(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if n < 1000 or unit == "PB":
            return f"{n:,.0f} {unit}" if unit == "B" else f"{n:,.1f} {unit}"
        n /= 1000
    return f"{n:,.1f} PB"
