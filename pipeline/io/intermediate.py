"""Stage results kept under the run's work folder: the formats of intermediate files.

Every file is written under a temporary name and renamed when complete, so a
task killed midway never leaves a file that looks finished, and a task run twice
writes the same file again. The layout of the work folder (which file belongs to
which tile or cell) is decided by :mod:`pipeline.staging`; this module only
knows how each kind of result is stored:

- stage 1, per tile: raw binaries of known shape (the tile's window), one per
  statistic, memory-mapped by the cells that need a slice of them (parsing a
  header cost more than the merge itself);
- stage 2, per cell: the merged statistics of the cell and its halo (``.npz``);
- detection, per cell: the part-label raster of the cell core (``.npz``);
- linking, per survey: the hole catalog, and every task's small result: data-only files
  (:mod:`pipeline.io.plain_data`, never a pickle);
- filling, per fill task: the filled pixels' hole ids, heights, method codes and
  distances, apart for each cell they fall in (``.npz``, a member each).
"""

from __future__ import annotations

import collections
import hashlib
import os
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..grid import PixelWindow
from ..rasterize import STATISTIC_DTYPES, STATISTIC_NAMES, GroundSums, PixelStatistics
from . import plain_data

#: Bumped whenever the layout of a kept result changes, so stale files are never read.
FORMAT_VERSION = 4


#: The longest name holefill gives an internal file or folder (a file system allows 255 bytes,
#: and suffixes such as ``.tmp.npz`` are added to it).
INTERNAL_NAME_MAX = 96


def internal_name(name: str, limit: int = INTERNAL_NAME_MAX) -> str:
    """``name`` itself when short, else its head and a hash of the whole: internal paths never grow too long.

    An input's file stem goes into internal names; a stem of 245 characters would
    otherwise make ``File name too long`` once holefill adds its own parts.
    """
    if len(name.encode()) <= limit:
        return name
    digest = hashlib.sha1(name.encode()).hexdigest()[:16]
    head = name.encode()[: limit - len(digest) - 1].decode(errors="ignore")
    return f"{head}~{digest}"


def save_tile_statistics(folder: str | os.PathLike, statistics: PixelStatistics, shared_keys: np.ndarray) -> None:
    """Store one tile's stage-1 statistics (its window) and the voxel keys of its shared pixels."""
    out = Path(folder)
    out.mkdir(exist_ok=True)  # never parents: a cancelled run's staging folder must stay deleted
    for name in STATISTIC_NAMES:
        save_raw(out / f"{name}.bin", getattr(statistics, name))
    save_raw(out / "shared_keys.bin", shared_keys.astype(np.int64))


def load_tile_statistics(folder: str | os.PathLike, tile_window: PixelWindow, window: PixelWindow) -> PixelStatistics:
    """Read the part of a tile's stage-1 statistics inside ``window`` (memory-mapped)."""
    rows, cols = window.slices_within(tile_window)
    arrays = {}
    for name in STATISTIC_NAMES:
        mapped = np.memmap(
            Path(folder) / f"{name}.bin", dtype=STATISTIC_DTYPES[name], mode="r", shape=tile_window.shape
        )
        arrays[name] = np.array(mapped[rows, cols])
    return PixelStatistics(window=window, **arrays)


def save_tile_ground(folder: str | os.PathLike, ground: GroundSums) -> None:
    """Store one tile's ground sums (its window), beside its statistics."""
    save_raw(Path(folder) / "ground_sum.bin", ground.height_sum)
    save_raw(Path(folder) / "ground_count.bin", ground.count)


def load_tile_ground(folder: str | os.PathLike, tile_window: PixelWindow, window: PixelWindow) -> GroundSums | None:
    """The part of a tile's ground sums inside ``window``; None where the tile kept none."""
    folder = Path(folder)
    if not (folder / "ground_count.bin").exists():
        return None
    rows, cols = window.slices_within(tile_window)
    arrays = [
        np.array(np.memmap(folder / f"{name}.bin", dtype=dtype, mode="r", shape=tile_window.shape)[rows, cols])
        for name, dtype in (("ground_sum", np.float64), ("ground_count", np.uint32))
    ]
    return GroundSums(window, *arrays)


def load_tile_shared_keys(folder: str | os.PathLike) -> np.ndarray:
    """The voxel keys a tile wrote for the pixels it shares with other tiles."""
    return np.fromfile(Path(folder) / "shared_keys.bin", dtype=np.int64)


def save_cell_statistics(
    path: str | os.PathLike, statistics: PixelStatistics, ground: GroundSums | None = None
) -> None:
    """Store a cell's merged statistics (core + halo) for the later stages, and its core's ground sums if kept."""
    extra = {}
    if ground is not None:
        extra = {
            "ground_window": _window_array(ground.window),
            "ground_sum": ground.height_sum,
            "ground_count": ground.count,
        }
    _save_npz(
        path,
        window=_window_array(statistics.window),
        **{name: getattr(statistics, name) for name in STATISTIC_NAMES},
        **extra,
    )


def load_cell_ground(path: str | os.PathLike) -> tuple[GroundSums, np.ndarray] | None:
    """A cell's ground sums and its water-class points per pixel over the same window; None where none were kept."""
    with np.load(path) as data:
        if "ground_sum" not in data.files:
            return None
        window = PixelWindow(*(int(v) for v in data["ground_window"]))
        ground = GroundSums(window, data["ground_sum"], data["ground_count"])
        if ground.height_sum.shape != window.shape or ground.count.shape != window.shape:
            raise ValueError(f"{path}: ground sums of shape {ground.height_sum.shape}, not the window's {window.shape}")
        cell_window = PixelWindow(*(int(v) for v in data["window"]))
        rows, cols = window.slices_within(cell_window)
        return ground, np.array(data["water"][rows, cols])


def load_cell_statistics(path: str | os.PathLike, names: tuple[str, ...] = STATISTIC_NAMES) -> PixelStatistics:
    """A cell's merged statistics as :func:`save_cell_statistics` stored them.

    ``names``: the statistics to read (the others come back empty, shape (0, 0)): the
    DSM writer needs only ``zmax`` and ``count``, and reading is most of its work.
    """
    with np.load(path) as data:
        window = PixelWindow(*(int(v) for v in data["window"]))
        empty = np.empty((0, 0), np.float32)
        return PixelStatistics(
            window=window, **{name: data[name] if name in names else empty for name in STATISTIC_NAMES}
        )


#: Bytes of cells' statistics a worker keeps read: about 60 cells of the default size (a cell of
#: 250 x 250 pixels and its halo, four statistics: 1 MB), fewer of larger cells.
SHARED_CELL_BYTES = 64 << 20


class _SharedCells:
    """The cells' statistics a process read last, least recently used first out, within a byte budget."""

    def __init__(self, budget: int) -> None:
        self.budget = budget
        self.kept: collections.OrderedDict[tuple, tuple[PixelStatistics, int]] = collections.OrderedDict()  # and bytes
        self.total = 0
        self.lock = threading.Lock()  # a threaded cluster's tasks share the process

    def get(self, key: tuple) -> PixelStatistics | None:
        with self.lock:
            found = self.kept.get(key)
            if found is None:
                return None
            self.kept.move_to_end(key)
            return found[0]

    def put(self, key: tuple, statistics: PixelStatistics, size: int) -> None:
        with self.lock:
            if key in self.kept:
                return
            self.kept[key] = (statistics, size)
            self.total += size
            while self.total > self.budget and len(self.kept) > 1:
                _, (_, freed) = self.kept.popitem(last=False)
                self.total -= freed


_SHARED = _SharedCells(SHARED_CELL_BYTES)


def load_shared_cell_statistics(path: str | os.PathLike, names: tuple[str, ...]) -> PixelStatistics:
    """:func:`load_cell_statistics` through a cache of the calling process, with read-only arrays.

    A cell's statistics are read by the tasks of each of its neighbours (the lines of sight
    reach beyond a cell's halo), and a worker runs neighbouring cells one after another: with
    the cells of the row above and below held (:data:`SHARED_CELL_BYTES`), one worker read
    the 42 M-point bench survey's cell files 235 times for 64 cells with 12 kept, 128 with 40.
    The file's size and modification time are part of the key: a file written again is read again.
    """
    stat = os.stat(path)
    key = (os.fspath(path), tuple(names), stat.st_mtime_ns, stat.st_size)
    if (found := _SHARED.get(key)) is not None:
        return found
    statistics = load_cell_statistics(path, names)
    for name in names:
        getattr(statistics, name).setflags(write=False)
    _SHARED.put(key, statistics, sum(getattr(statistics, name).nbytes for name in names))
    return statistics


def save_labels(
    path: str | os.PathLike, labels: np.ndarray, window: PixelWindow, *, seen_voids: np.ndarray | None = None
) -> None:
    """Store a cell core's part labels (0 no hole, -1 a settled small void, n > 0 part n).

    ``seen_voids``: the settled small voids' pixels the sensor saw unobstructed (where the
    lines of sight were judged), kept beside the labels.
    """
    arrays = {"window": _window_array(window), "labels": labels.astype(np.int32)}
    if seen_voids is not None:
        arrays["seen_voids"] = np.asarray(seen_voids, bool)
    _save_npz(path, **arrays)


def load_labels(path: str | os.PathLike) -> tuple[np.ndarray, PixelWindow]:
    """A cell core's part labels and the window they cover."""
    with np.load(path) as data:
        return data["labels"], PixelWindow(*(int(v) for v in data["window"]))


def load_seen_voids(path: str | os.PathLike) -> np.ndarray | None:
    """The settled small voids' pixels the sensor saw unobstructed (None: not judged)."""
    with np.load(path) as data:
        return data["seen_voids"] if "seen_voids" in data.files else None


@dataclass(frozen=True)
class TaskFill:
    """A fill task's result over one window, at the pixels of the cell that asked for it.

    ``hole_ids`` is the hole each pixel was filled for (0: none); ``heights``, ``codes``
    and ``distance`` (to measured data, survey units) hold where it is > 0.
    """

    window: PixelWindow
    hole_ids: np.ndarray
    heights: np.ndarray
    codes: np.ndarray
    distance: np.ndarray


def save_task_fill(
    path: str | os.PathLike,
    window: PixelWindow,
    hole_ids: np.ndarray,
    heights: np.ndarray,
    codes: np.ndarray,
    distance: np.ndarray,
    *,
    cells: Sequence[tuple[str, PixelWindow]],
    factor: int = 1,
) -> None:
    """Store a fill task's holes over its window: which hole each pixel filled, heights, method codes, distances.

    With ``factor`` > 1 the arrays are over coarse pixels of ``factor`` x ``factor`` from the window's corner.
    Only the pixels a hole filled are kept, with their place on that lattice, and apart for each
    of ``cells`` (id, core window) they fall in: each cell's writer reads its own part alone
    (a member of the ``.npz``). A fill's window spans many cells (a water surface, a missed
    strip); read whole by each of them, the 211 M-point bench survey's writers read 4.5 GB of
    fills for 1 M filled pixels. A coarse pixel across a cell's edge is kept in both cells.
    """
    pieces: dict[str, np.ndarray] = {}
    kept_cells: list[str] = []
    for cell_id, core in cells:
        overlap = window.intersection(core)
        if overlap.is_empty:
            continue
        first_row, last_row, first_col, last_col = _lattice_range(window, overlap, factor)
        r, c = np.nonzero(hole_ids[first_row : last_row + 1, first_col : last_col + 1] > 0)
        if not len(r):
            continue
        r, c = r + first_row, c + first_col
        prefix = f"p{len(kept_cells)}_"
        pieces |= {
            prefix + "rows": r.astype(np.int32),
            prefix + "cols": c.astype(np.int32),
            prefix + "hole_ids": hole_ids[r, c].astype(np.int64),
            prefix + "heights": heights[r, c].astype(np.float32),
            prefix + "codes": codes[r, c].astype(np.uint8),
            prefix + "distance": distance[r, c].astype(np.float32),
        }
        kept_cells.append(cell_id)
    _save_npz(
        path,
        window=_window_array(window),
        factor=np.array(int(factor)),
        shape=np.array(hole_ids.shape),
        cells=np.array(kept_cells, dtype=np.str_),
        **pieces,
    )


def load_task_fill(path: str | os.PathLike, cell_id: str, within: PixelWindow) -> TaskFill | None:
    """The part of a fill task's result in cell ``cell_id`` (core window ``within``), one value a pixel.

    None where the task filled nothing in that cell. A coarse result (``factor`` > 1) gives each
    pixel the values of the coarse pixel it lies in.
    """
    with np.load(path) as data:
        window = PixelWindow(*(int(v) for v in data["window"]))
        factor = int(data["factor"])
        lattice = tuple(int(v) for v in data["shape"])
        kept_cells = data["cells"].tolist()
        if cell_id not in kept_cells:
            return None
        prefix = f"p{kept_cells.index(cell_id)}_"
        rows, cols = data[prefix + "rows"], data[prefix + "cols"]
        values = [data[prefix + name] for name in ("hole_ids", "heights", "codes", "distance")]
    if factor < 1 or lattice != (-(-window.height // factor), -(-window.width // factor)):
        raise ValueError(f"{path}: a fill lattice of {lattice} at factor {factor} does not match its window")
    n = len(rows)
    if len(cols) != n or any(len(v) != n for v in values):
        raise ValueError(f"{path}: fill arrays of unequal lengths")
    if n and (rows.min() < 0 or cols.min() < 0 or rows.max() >= lattice[0] or cols.max() >= lattice[1]):
        raise ValueError(f"{path}: filled pixels outside the fill's window")
    overlap = window.intersection(within)
    if overlap.is_empty:
        return None
    first_row, last_row, first_col, last_col = _lattice_range(window, overlap, factor)
    inside = (rows >= first_row) & (rows <= last_row) & (cols >= first_col) & (cols <= last_col)
    at = (rows[inside] - first_row, cols[inside] - first_col)
    dense = []
    for value, empty in zip(values, (0, np.nan, 0, np.nan)):
        array = np.full((last_row - first_row + 1, last_col - first_col + 1), empty, value.dtype)
        array[at] = value[inside]
        dense.append(array)
    if factor > 1:
        pick_rows = (np.arange(overlap.row_off, overlap.row_end) - window.row_off) // factor - first_row
        pick_cols = (np.arange(overlap.col_off, overlap.col_end) - window.col_off) // factor - first_col
        dense = [array[np.ix_(pick_rows, pick_cols)] for array in dense]
    return TaskFill(overlap, *dense)


def _lattice_range(window: PixelWindow, overlap: PixelWindow, factor: int) -> tuple[int, int, int, int]:
    """The first and last rows and columns of the lattice of ``factor`` x ``factor`` pixels from
    ``window``'s corner that ``overlap`` (a part of ``window``) meets."""
    return (
        (overlap.row_off - window.row_off) // factor,
        (overlap.row_end - 1 - window.row_off) // factor,
        (overlap.col_off - window.col_off) // factor,
        (overlap.col_end - 1 - window.col_off) // factor,
    )


def save_object(path: str | os.PathLike, value: Any) -> None:
    """Keep a task's result or a survey-wide one (dataclasses of numpy arrays, scalars, strings) as data only.

    Never a pickle: the output folder may be written by others, and reading a kept
    result must not run code (:mod:`pipeline.io.plain_data`).
    """
    plain_data.dump(path, value, version=FORMAT_VERSION)


def load_object(path: str | os.PathLike) -> Any:
    """What :func:`save_object` stored; raises ``ValueError`` for anything else (another version, other content)."""
    return plain_data.load(path, version=FORMAT_VERSION)


def save_raw(path: Path, array: np.ndarray) -> None:
    """An array as raw bytes (its shape and type are known to the reader)."""
    tmp = path.with_name(path.name + ".tmp")
    np.ascontiguousarray(array).tofile(tmp)
    os.replace(tmp, path)


def _window_array(window: PixelWindow) -> np.ndarray:
    return np.array([window.row_off, window.col_off, window.height, window.width])


def _save_npz(path: str | os.PathLike, **arrays: np.ndarray) -> None:
    plain_data.write_npz_atomically(path, arrays)
