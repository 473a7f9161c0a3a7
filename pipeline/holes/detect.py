"""Per cell: hole parts, their [OPEN] classification and mergeable statistics.

[OPEN] section 3.1 on a raster (closed / open type I / open type II, shapes A-D);
the ring of measured pixels around each part ([UAS] section 3.2); edge strips and
shared ring rows for linking on the client. See ``docs/holes.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
import scipy.ndimage as ndi

from ..grid import Cell, PixelWindow
from ..sensor.sight import BLOCKED, SEEN
from ._kernels import _NO_LINE, RingSums, _coo_counts, _perimeter_flat, hole_pixel_sums, ring_sums
from .stats import HEIGHT_HIST_DTYPE, LINE_HIST_DTYPE, SHARED_RING_DTYPE, HoleStats, _empty_columns

__all__ = [
    "PART_DTYPE",
    "SIDE_BITS",
    "SIDES",
    "CellEvidence",
    "CellHoles",
    "DetectParams",
    "EdgeStrip",
    "detect_cell_holes",
]

#: Cell sides, in the order of :attr:`CellHoles.edges`, and their bits in ``sides`` masks.
SIDES: tuple[str, ...] = ("north", "east", "south", "west")

SIDE_BITS: dict[str, int] = {"north": 1, "east": 2, "south": 4, "west": 8}

#: Per-part topology and classification within one cell ([OPEN] section 3.1).
PART_DTYPE = np.dtype(
    [
        ("label", np.int32),  # the part's label in CellHoles.labels (1..n)
        ("category", "U6"),  # "closed", "I" (open, internal) or "II" (open, on the AOI boundary)
        ("shape", "U1"),  # open parts: "A" hollow, "B" semi-enclosed, "C" crossing, "D" island
        ("touches_edge", np.bool_),  # has a pixel on the cell core's outermost rows/columns
        ("touches_aoi_boundary", np.bool_),  # neighbours (by `connectivity`) a pixel outside the AOI/grid
        ("touches_data", np.bool_),  # 4-neighbours a measured pixel (core or halo): layer-1 candidate
        ("sides", np.uint8),  # SIDE_BITS of the core edges it touches
        ("continues", np.uint8),  # SIDE_BITS of the edges across which the hole goes on (4-adjacency)
        ("edge_runs", np.int32),  # separate stretches of the core perimeter it occupies
        ("data_sides", np.int32),  # stretches of perimeter between those that hold measured data
        ("islands", np.int32),  # pieces of data inside the core that it surrounds completely
    ]
)


@dataclass(frozen=True)
class EdgeStrip:
    """Part labels along one edge of a cell core, for linking with the neighbour.

    Attributes
    ----------
    side : str
        One of ``SIDES``.
    rows, cols : ndarray of int64
        Global grid row and column of each pixel of the strip.
    labels : ndarray of int32
        Part label of each pixel (0: not a hole).
    """

    side: str
    rows: np.ndarray
    cols: np.ndarray
    labels: np.ndarray


@dataclass(frozen=True)
class CellHoles:
    """The hole parts of one cell: what :func:`detect_cell_holes` returns.

    Attributes
    ----------
    cell : Cell
        The cell.
    connectivity : int
        4 or 8, the connectivity of hole pixels used.
    labels : ndarray of int32, shape ``cell.window.shape``, or None
        Part label per core pixel (0: not a hole, -1: a settled small void).
        Drop it with :meth:`without_labels` before sending the result to the client.
    parts : ndarray of PART_DTYPE, shape (n,)
        Topology and [OPEN] classification of parts ``1..n`` (row ``i`` is label ``i + 1``).
    stats : HoleStats
        Mergeable statistics, rows aligned with ``parts``.
    edges : tuple of EdgeStrip
        The labels along the four core edges, in ``SIDES`` order.
    shared_ring : ndarray of SHARED_RING_DTYPE
        Ring pixels of this core whose hole must be resolved across cells.
    core_has_data : bool
        Whether any pixel of the core holds a point.
    small_void_count, small_void_px : int
        Closed parts below ``min_area_px`` settled in the cell (labelled -1).
    contacts : ndarray of int32, shape (K, 2)
        Pairs of part labels ``(a, b)``, ``a < b``, whose pixels touch within the core: a part in
        a coverage gap and one outside it, labelled apart (:func:`pipeline.holes.link_holes` may
        join them, ``joins``).
    """

    cell: Cell
    connectivity: int
    labels: np.ndarray | None
    parts: np.ndarray
    stats: HoleStats
    edges: tuple[EdgeStrip, ...]
    shared_ring: np.ndarray
    core_has_data: bool
    small_void_count: int = 0
    small_void_px: int = 0
    contacts: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int32))

    @property
    def n_parts(self) -> int:
        return len(self.parts)

    def without_labels(self) -> CellHoles:
        """The same result without the label raster (what the client needs)."""
        return replace(self, labels=None)


@dataclass(frozen=True)
class DetectParams:
    """The thresholds of :func:`detect_cell_holes` (see its parameters there).

    Attributes
    ----------
    jump_threshold, height_bin : float
        Height-jump threshold ([UAS] eq. 1) and bin width of the ring-height histogram, in z units.
    connectivity : {4, 8}
        Of hole pixels: 4 (default, [UAS] section 3.2) gives outlines whose polygons are always valid.
    local_radius_px, low_tolerance : int, float
        A ring pixel is "low" when its ``zmin`` is within ``low_tolerance`` (z units) of the
        lowest ``zmin`` within ``local_radius_px`` pixels (square window; 0 disables).
    min_area_px : int
        Closed parts smaller than this are settled in the cell as small voids; 0 keeps all.
    """

    jump_threshold: float
    connectivity: int = 4
    local_radius_px: int = 8
    low_tolerance: float = 0.5
    height_bin: float = 0.25
    min_area_px: int = 0


@dataclass(frozen=True)
class CellEvidence:
    """What else is known of each pixel of a cell's halo window, each optional (None: unknown).

    Attributes
    ----------
    water_points : ndarray of int
        Water-class points per pixel (``hole_water_px``, the ring's ``ring_water_px``).
    water_mask : ndarray of bool
        True inside known water (``water_mask_px``).
    flight_line : ndarray of int
        A flight-line id per pixel, < 0 unknown (the ring's line histogram).
    coverage : ndarray of int
        Coverage classes: 2 in a coverage gap, 3 in a missing tile's square, 1 in a swath,
        0 unknown (``gap_px``, ``missing_tile_px``, ``swath_px``: hole pixels in and out of a
        gap are labelled apart, a river crossing a missed strip is two holes).
    sight : ndarray of int
        The sensor's view, :func:`pipeline.sensor.sight.sight_classes` (``blocked_px``, ``seen_px``).
    covered : ndarray of bool
        Points the class filter left out (``covered_px``).
    """

    water_points: np.ndarray | None = None
    water_mask: np.ndarray | None = None
    flight_line: np.ndarray | None = None
    coverage: np.ndarray | None = None
    sight: np.ndarray | None = None
    covered: np.ndarray | None = None


_NO_EVIDENCE = CellEvidence()


def detect_cell_holes(
    count: np.ndarray,
    zmax: np.ndarray,
    zmin: np.ndarray,
    aoi: np.ndarray | None = None,
    *,
    cell: Cell,
    grid_window: PixelWindow,
    params: DetectParams,
    evidence: CellEvidence = _NO_EVIDENCE,
) -> CellHoles:
    """Find, classify and measure the hole parts of one cell.

    A part is a connected set of empty AOI pixels of the cell core. Parts are classified per
    [OPEN] section 3.1 (closed / open type I / open type II, shapes A-D, see ``docs/holes.md``)
    and measured with statistics that merge exactly across cells (:func:`merge_hole_stats`,
    :func:`link_holes`): the results do not depend on the cell size.

    Parameters
    ----------
    count, zmax, zmin : ndarray of shape ``cell.halo_window.shape``
        Points per pixel over the cell's halo window; highest and lowest point per pixel (float, NaN where empty).
    aoi : ndarray of bool, same shape, optional
        True inside the area of interest; None: the whole grid.
    cell : Cell
        The cell; the arrays cover ``cell.halo_window``.
    grid_window : PixelWindow
        The survey grid (``Grid.window``): beyond it is outside the AOI.
    params : DetectParams
        The thresholds. The halo must reach ``local_radius_px`` (and at least 1 pixel) on
        every side that is not the grid's edge. Closed parts (touching neither the core edge
        nor the AOI boundary) smaller than ``min_area_px`` are settled here as small voids:
        counted in ``small_void_count``/``small_void_px``, labelled -1, not listed. Open
        parts are always kept (their hole's area is only known after linking).
    evidence : CellEvidence, arrays of the same shape
        Counted per part (see :class:`CellEvidence`); by default none.

    Returns a :class:`CellHoles`; raises ``ValueError`` on arrays of the wrong shape, a bad
    parameter, or a halo narrower than needed.
    """
    arrays = {"count": count, "zmax": zmax, "zmin": zmin, "aoi": aoi}
    arrays.update((f.name, getattr(evidence, f.name)) for f in fields(CellEvidence))
    p = params
    work = _checked_work(
        arrays,
        cell,
        grid_window,
        connectivity=p.connectivity,
        local_radius_px=p.local_radius_px,
        height_bin=p.height_bin,
    )
    return _find_parts(
        work,
        cell,
        connectivity=p.connectivity,
        local_radius_px=p.local_radius_px,
        jump_threshold=p.jump_threshold,
        low_tolerance=p.low_tolerance,
        height_bin=p.height_bin,
        min_area_px=p.min_area_px,
    )


def _find_parts(
    work: _Work,
    cell: Cell,
    *,
    connectivity: int,
    local_radius_px: int,
    jump_threshold: float,
    low_tolerance: float,
    height_bin: float,
    min_area_px: int,
) -> CellHoles:
    """Label, classify and measure the hole parts of a cell core from its checked work arrays."""
    R = work.R
    core = cell.window
    labels, n, split = _label_holes(work, connectivity)
    data_core = work.core(work.data)
    core_has_data = bool(data_core.any())
    edges = _edge_strips(labels, core)
    if n == 0:
        return CellHoles(
            cell,
            connectivity,
            labels,
            np.zeros(0, PART_DTYPE),
            HoleStats.empty(0, height_bin=height_bin),
            edges,
            np.zeros(0, SHARED_RING_DTYPE),
            core_has_data,
            0,
            0,
        )

    cols = _empty_columns(n)
    _pixel_statistics(cols, labels, n, core, work, connectivity)
    contacts = _part_contacts(labels, connectivity) if split else np.zeros((0, 2), np.int32)
    # a part touching one on the other side of a coverage gap's edge is not a whole hole:
    # linking may join the two (its ring pixels are resolved as an open part's)
    closed = _closed_parts(cols, edges, n) & ~np.isin(np.arange(1, n + 1), contacts)
    small = closed & (cols["area_px"] < min_area_px)  # complete holes: small ones are settled here
    small_void_count, small_void_px = int(small.sum()), int(cols["area_px"][small].sum())
    if small_void_count:
        labels, cols, closed, relabel = _drop_parts(labels, cols, closed, small)
        n = len(closed)
        edges = _edge_strips(labels, core)
        contacts = relabel[contacts]  # parts in contact are never dropped
    height_hist, line_hist, shared = _ring_statistics(
        cols,
        labels,
        closed,
        work,
        core,
        local_radius_px=local_radius_px,
        jump_threshold=jump_threshold,
        low_tolerance=low_tolerance,
        height_bin=height_bin,
    )
    parts = _part_topology(labels, n, work.hole, data_core, R, cols, core_has_data, connectivity)
    return CellHoles(
        cell=cell,
        connectivity=connectivity,
        labels=labels,
        parts=parts,
        stats=HoleStats(cols, height_hist, line_hist, float(height_bin)),
        edges=edges,
        shared_ring=shared,
        core_has_data=core_has_data,
        small_void_count=small_void_count,
        small_void_px=small_void_px,
        contacts=contacts,
    )


def _part_contacts(labels: np.ndarray, connectivity: int) -> np.ndarray:
    """Pairs ``(a, b)``, ``a < b``, of part labels whose pixels touch (by ``connectivity``): sorted, unique, int32.

    Parts of one labelling never touch; parts in a coverage gap and out of it do (``_label_holes``).
    """
    rows, cols = labels.shape
    pairs = [np.zeros((0, 2), np.int32)]
    shifts = [(0, 1), (1, 0)] + ([(1, 1), (1, -1)] if connectivity == 8 else [])
    for dr, dc in shifts:
        here = labels[: rows - dr, max(0, -dc) : cols - max(0, dc)]
        there = labels[dr:, max(0, dc) : cols + min(0, dc)]
        touch = (here > 0) & (there > 0) & (here != there)
        if touch.any():
            a, b = here[touch], there[touch]
            pairs.append(np.column_stack([np.minimum(a, b), np.maximum(a, b)]).astype(np.int32))
    return np.unique(np.concatenate(pairs), axis=0)


def _check_inputs(
    arrays: dict[str, np.ndarray | None],
    cell: Cell,
    grid_window: PixelWindow,
    *,
    connectivity: int,
    local_radius_px: int,
    height_bin: float,
) -> int:
    """Validate :func:`detect_cell_holes`'s arguments; return the work margin R (pixels)."""
    core, halo = cell.window, cell.halo_window
    for name, arr in arrays.items():
        if arr is not None and np.shape(arr) != halo.shape:
            raise ValueError(f"{name} has shape {np.shape(arr)}; expected the cell's halo window shape {halo.shape}")
    if connectivity not in (4, 8):
        raise ValueError(f"connectivity must be 4 or 8, got {connectivity!r}")
    if local_radius_px < 0:
        raise ValueError(f"local_radius_px must be >= 0, got {local_radius_px}")
    if not height_bin > 0:
        raise ValueError(f"height_bin must be > 0, got {height_bin!r}")
    if core.is_empty:
        raise ValueError(f"cell {cell.id} has an empty core window")
    R = max(1, int(local_radius_px))
    work = core.expand(R)
    if work.intersection(grid_window) != work.intersection(halo):
        raise ValueError(
            f"cell {cell.id}: the halo must reach {R} pixel(s) beyond the core wherever the grid "
            f"continues (local_radius_px={local_radius_px}); got halo {halo} for core {core}"
        )
    return R


class _Work(NamedTuple):
    """A cell's arrays over the work window: the core grown by ``R`` pixels, padded beyond the grid."""

    R: int
    hole: np.ndarray  # empty and inside the AOI
    aoi: np.ndarray
    data: np.ndarray  # count > 0
    zmax: np.ndarray
    zmin: np.ndarray
    water: np.ndarray | None  # holds water-class points
    mask: np.ndarray | None  # inside the water mask
    line: np.ndarray | None  # flight line id, < 0 unknown
    gap: np.ndarray | None  # inside a coverage gap (or a missing tile's square)
    swath: np.ndarray | None  # inside a flight line's swath
    missing_tile: np.ndarray | None  # inside a missing tile's square
    blocked: np.ndarray | None  # swept by some swath, hidden from every line that swept it
    seen: np.ndarray | None  # seen unobstructed by some line
    covered: np.ndarray | None  # holds points the class filter left out

    def core(self, arr: np.ndarray) -> np.ndarray:
        """The view of a work-window array over the core."""
        R = self.R
        return arr[R : arr.shape[0] - R, R : arr.shape[1] - R]


def _checked_work(
    arrays: dict[str, np.ndarray | None],
    cell: Cell,
    grid_window: PixelWindow,
    *,
    connectivity: int,
    local_radius_px: int,
    height_bin: float,
) -> _Work:
    """:func:`_check_inputs`, then :func:`_work_arrays`: the checked arrays over the work window."""
    R = _check_inputs(
        arrays, cell, grid_window, connectivity=connectivity, local_radius_px=local_radius_px, height_bin=height_bin
    )
    return _work_arrays(arrays, cell, R)


def _work_arrays(arrays: dict[str, np.ndarray | None], cell: Cell, R: int) -> _Work:
    """The arrays of :func:`detect_cell_holes` cut to the work window (see :class:`_Work`)."""
    work = cell.window.expand(R)

    def view(name: str, fill: float | int | bool, dtype: npt.DTypeLike | None = None) -> np.ndarray | None:
        arr = arrays[name]
        return None if arr is None else _work_view(np.asarray(arr, dtype=dtype), cell, work, fill)

    def required(name: str, fill: float | int | bool) -> np.ndarray:
        arr = arrays[name]
        if arr is None:
            raise ValueError(f"detect_cell_holes: {name} is required, got None")
        return _work_view(np.asarray(arr), cell, work, fill)

    count_w = required("count", 0)
    aoi = arrays["aoi"]
    aoi_halo = np.ones(cell.halo_window.shape, dtype=bool) if aoi is None else np.asarray(aoi, dtype=bool)
    aoi_w = _work_view(aoi_halo, cell, work, False)
    data_w = count_w > 0
    water_points = view("water_points", 0)
    coverage_w = view("coverage", 0, np.int8)
    sight_w = view("sight", 0, np.uint8)
    return _Work(
        R=R,
        hole=~data_w & aoi_w,
        aoi=aoi_w,
        data=data_w,
        zmax=required("zmax", np.nan),
        zmin=required("zmin", np.nan),
        water=None if water_points is None else water_points > 0,
        mask=view("water_mask", False, bool),
        line=view("flight_line", _NO_LINE, np.int64),
        gap=None if coverage_w is None else coverage_w >= 2,
        swath=None if coverage_w is None else coverage_w == 1,
        missing_tile=None if coverage_w is None else coverage_w == 3,
        blocked=None if sight_w is None else sight_w == BLOCKED,
        seen=None if sight_w is None else sight_w == SEEN,
        covered=view("covered", False, bool),
    )


def _label_holes(work: _Work, connectivity: int) -> tuple[np.ndarray, int, bool]:
    """Parts of the core's hole pixels, numbered in raster order of their first pixels.

    With a coverage gap, the pixels inside and outside it are labelled apart (the third
    value says whether they were).
    """
    structure = ndi.generate_binary_structure(2, 1 if connectivity == 4 else 2)
    hole = work.core(work.hole)
    if work.gap is None or not (gap := work.core(work.gap) & hole).any():
        labels, n = ndi.label(hole, structure=structure)
        return labels.astype(np.int32, copy=False), int(n), False
    inside, n_in = ndi.label(gap, structure=structure)
    outside, n_out = ndi.label(hole & ~gap, structure=structure)
    merged = np.where(inside > 0, inside, np.where(outside > 0, outside + n_in, 0)).ravel()
    n = int(n_in + n_out)
    values, first = np.unique(merged, return_index=True)
    present = values > 0
    relabel = np.zeros(n + 1, np.int32)
    relabel[values[present][np.argsort(first[present])]] = np.arange(1, n + 1, dtype=np.int32)
    return relabel[merged].reshape(hole.shape), n, True


def _closed_parts(cols: dict[str, np.ndarray], edges: tuple[EdgeStrip, ...], n: int) -> np.ndarray:
    """Parts touching neither the core edge nor the AOI boundary: complete holes."""
    on_edge = np.zeros(n + 1, bool)
    for strip in edges:
        on_edge[strip.labels] = True
    return ~on_edge[1:] & (cols["aoi_edge_px"] == 0)


def _drop_parts(
    labels: np.ndarray, cols: dict[str, np.ndarray], closed: np.ndarray, drop: np.ndarray
) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """Label the dropped parts -1 and number the others 1..k again, in order; also the map from old labels to new."""
    keep = np.flatnonzero(~drop)
    relabel = np.full(len(drop) + 1, -1, np.int32)
    relabel[0] = 0
    relabel[keep + 1] = np.arange(1, len(keep) + 1, dtype=np.int32)
    return relabel[labels], {k: v[keep] for k, v in cols.items()}, closed[keep], relabel


def _ring_statistics(
    cols: dict[str, np.ndarray],
    labels: np.ndarray,
    closed: np.ndarray,
    work: _Work,
    core: PixelWindow,
    *,
    local_radius_px: int,
    jump_threshold: float,
    low_tolerance: float,
    height_bin: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ring: measured core pixels 4-adjacent to a hole pixel ([UAS] 3.2).

    Fills the ring columns of ``cols``; returns the height and flight-line histograms
    and the shared ring rows. A ring pixel counts here for every closed part it
    touches (a closed part is a whole hole, distinct from all others) and for the
    single open part it touches; when it touches several open parts, or a hole pixel
    of a neighbouring cell, it becomes one shared row per such part/pixel, which the
    client resolves once parts are linked, so that each ring pixel counts once per
    hole whatever the cell size.
    """
    lr = int(local_radius_px)
    if lr > 0:
        zmin_data = np.where(work.data, work.zmin, np.inf).astype(np.float32)
        row_min = ndi.minimum_filter1d(zmin_data, 2 * lr + 1, axis=1, mode="constant", cval=np.inf)
    else:
        row_min = np.zeros((1, 1), np.float32)
    ring = ring_sums(
        labels,
        work.hole,
        work.data,
        work.zmax,
        work.zmin,
        row_min,
        work.water,
        work.line,
        np.concatenate([[False], closed]),
        work.R,
        local_radius_px=lr,
        jump_threshold=jump_threshold,
        low_tolerance=low_tolerance,
    )
    cols["ring_px"] = ring.ring_px[1:]
    cols["ring_jump_px"] = ring.ring_jump[1:]
    cols["ring_low_px"] = ring.ring_low[1:]
    cols["ring_water_px"] = ring.ring_water[1:]
    _ring_moments(cols, ring.ring_px[1:], ring.sums[:, 1:], core)
    cols["ring_jump_span_sum"] = ring.span_sum[1:]
    cols["ring_z_min"] = ring.z_min[1:]
    cols["ring_z_max"] = ring.z_max[1:]
    finite = np.isfinite(ring.hist_z)
    height_hist = _coo_counts(
        ring.hist_part[finite] - 1, np.floor(ring.hist_z[finite] / height_bin).astype(np.int64), HEIGHT_HIST_DTYPE
    )
    known = ring.hist_line >= 0
    line_hist = _coo_counts(ring.hist_part[known] - 1, ring.hist_line[known], LINE_HIST_DTYPE)
    return height_hist, line_hist, _shared_rows(ring, core, work.R, work.hole.shape[1])


def _shared_rows(ring: RingSums, core: PixelWindow, R: int, work_width: int) -> np.ndarray:
    """The ring kernel's shared rows as a SHARED_RING_DTYPE table in global coordinates."""
    shared = np.zeros(len(ring.shared_row), SHARED_RING_DTYPE)
    if not len(shared):
        return shared
    key = ring.shared_key
    shared["row"] = ring.shared_row + core.row_off
    shared["col"] = ring.shared_col + core.col_off
    foreign = key < 0
    shared["label"] = np.where(foreign, 0, key)
    fr, fc = np.divmod(np.where(foreign, -1 - key, 0), work_width)
    shared["ref_row"] = np.where(foreign, fr - R + core.row_off, -1)
    shared["ref_col"] = np.where(foreign, fc - R + core.col_off, -1)
    shared["z"] = ring.shared_z
    shared["span"] = ring.shared_span
    shared["jump"] = (ring.shared_flags & 1) != 0
    shared["low"] = (ring.shared_flags & 2) != 0
    shared["water"] = (ring.shared_flags & 4) != 0
    shared["line"] = ring.shared_line
    return shared


def _work_view(arr: np.ndarray, cell: Cell, work: PixelWindow, fill: float | int | bool) -> np.ndarray:
    """``arr`` (over the halo window) cut to ``work``; ``fill`` where ``work`` leaves the grid."""
    halo = cell.halo_window
    have = work.intersection(halo)
    if have == work:
        return arr[work.slices_within(halo)]
    dtype = arr.dtype
    if isinstance(fill, float) and np.isnan(fill) and not np.issubdtype(dtype, np.floating):
        dtype = np.dtype(np.float32)
    out = np.full(work.shape, fill, dtype=dtype)
    out[have.slices_within(work)] = arr[have.slices_within(halo)]
    return out


def _edge_strips(labels: np.ndarray, core: PixelWindow) -> tuple[EdgeStrip, ...]:
    h, w = labels.shape
    cols = np.arange(core.col_off, core.col_end, dtype=np.int64)
    rows = np.arange(core.row_off, core.row_end, dtype=np.int64)
    return (
        EdgeStrip("north", np.full(w, core.row_off, np.int64), cols, labels[0, :].copy()),
        EdgeStrip("east", rows, np.full(h, core.col_end - 1, np.int64), labels[:, w - 1].copy()),
        EdgeStrip("south", np.full(w, core.row_end - 1, np.int64), cols, labels[h - 1, :].copy()),
        EdgeStrip("west", rows, np.full(h, core.col_off, np.int64), labels[:, 0].copy()),
    )


def _first_occurrence(labels_in_order: np.ndarray, n: int) -> np.ndarray:
    """Index of the first occurrence of labels 1..n in a sequence where they appear in order."""
    seen = np.maximum.accumulate(labels_in_order)
    new = np.ones(len(seen), bool)
    new[1:] = seen[1:] > seen[:-1]
    first = np.flatnonzero(new)
    if len(first) != n or not np.array_equal(labels_in_order[first], np.arange(1, n + 1)):
        first = np.unique(labels_in_order, return_index=True)[1]  # not numbered in raster order
    return first


def _pixel_statistics(
    cols: dict[str, np.ndarray], labels: np.ndarray, n: int, core: PixelWindow, work: _Work, connectivity: int
) -> None:
    """Area, box, first pixel, moments, edge length, AOI contact, data contact, evidence."""
    sums = hole_pixel_sums(
        labels, n, work.hole, work.aoi, work.data, work.water, work.mask, work.R, eight=connectivity == 8
    )
    area, sr, sc = sums.area[1:], sums.row_sum[1:], sums.col_sum[1:]
    mr, mc = sr / area, sc / area
    cols["area_px"] = area
    cols["mean_row"] = mr + core.row_off
    cols["mean_col"] = mc + core.col_off
    cols["m2_rr"] = sums.row_sq_sum[1:] - sr * mr  # local coordinates (< cell size): no cancellation
    cols["m2_cc"] = sums.col_sq_sum[1:] - sc * mc
    cols["m2_rc"] = sums.row_col_sum[1:] - sr * mc
    cols["row_min"] = sums.row_min[1:] + core.row_off
    cols["row_max"] = sums.row_max[1:] + core.row_off
    cols["col_min"] = sums.col_min[1:] + core.col_off
    cols["col_max"] = sums.col_max[1:] + core.col_off
    cols["first_row"] = cols["row_min"].copy()
    cols["first_col"] = sums.first_col[1:] + core.col_off
    cols["edge_len_px"] = sums.edge_len[1:]
    cols["aoi_edge_px"] = sums.aoi_edge[1:]
    cols["touches_data"] = sums.near_data[1:] > 0
    cols["hole_water_px"] = sums.water[1:]
    cols["water_mask_px"] = sums.in_mask[1:]
    for name, where in (
        ("gap_px", work.gap),
        ("swath_px", work.swath),
        ("missing_tile_px", work.missing_tile),
        ("blocked_px", work.blocked),
        ("seen_px", work.seen),
        ("covered_px", work.covered),
    ):
        cols[name] = (
            np.zeros(n, np.int64) if where is None else np.bincount(labels[work.core(where)], minlength=n + 1)[1:]
        )


def _ring_moments(cols: dict[str, np.ndarray], count: np.ndarray, sums: np.ndarray, core: PixelWindow) -> None:
    """Centroid and co-moments of (row, column, height) of the ring from raw sums."""
    k = np.maximum(count, 1).astype(np.float64)
    means = sums[:3] / k
    cols["ring_mean_row"] = np.where(count > 0, means[0] + core.row_off, 0.0)
    cols["ring_mean_col"] = np.where(count > 0, means[1] + core.col_off, 0.0)
    cols["ring_mean_z"] = np.where(count > 0, means[2], 0.0)
    for name, (i, j), raw in (
        ("ring_m2_rr", (0, 0), 3),
        ("ring_m2_cc", (1, 1), 4),
        ("ring_m2_rc", (0, 1), 5),
        ("ring_m2_rz", (0, 2), 6),
        ("ring_m2_cz", (1, 2), 7),
        ("ring_m2_zz", (2, 2), 8),
    ):
        cols[name] = np.where(count > 0, sums[raw] - sums[i] * means[j], 0.0)


def _part_topology(
    labels: np.ndarray,
    n: int,
    hole_w: np.ndarray,
    data_core: np.ndarray,
    R: int,
    cols: dict[str, np.ndarray],
    core_has_data: bool,
    connectivity: int,
) -> np.ndarray:
    """[OPEN] section 3.1 on a raster: open/closed, type I/II, shapes A-D (see docs/holes.md)."""
    h, w = labels.shape
    parts = np.zeros(n, PART_DTYPE)
    parts["label"] = np.arange(1, n + 1)
    parts["touches_data"] = cols["touches_data"]

    # core edges touched, and edges across which the hole goes on (4-adjacency)
    sides = np.zeros(n + 1, np.uint8)
    continues = np.zeros(n + 1, np.uint8)
    side_cuts = {
        "north": (labels[0, :], hole_w[R - 1, R : R + w]),
        "east": (labels[:, w - 1], hole_w[R : R + h, R + w]),
        "south": (labels[h - 1, :], hole_w[R + h, R : R + w]),
        "west": (labels[:, 0], hole_w[R : R + h, R - 1]),
    }
    for side, (edge_labels, across_hole) in side_cuts.items():
        bit = np.uint8(SIDE_BITS[side])
        sides[np.bincount(edge_labels, minlength=n + 1) > 0] |= bit
        continues[np.bincount(edge_labels[across_hole], minlength=n + 1) > 0] |= bit
    sides[0] = continues[0] = 0
    parts["sides"] = sides[1:]
    parts["continues"] = continues[1:]
    parts["touches_edge"] = sides[1:] != 0
    parts["touches_aoi_boundary"] = cols["aoi_edge_px"] > 0

    # stretches of the perimeter each part occupies, and the stretches of data between them
    perimeter = _perimeter_flat(h, w)
    ring_lab = labels.ravel()[perimeter]
    ring_data = data_core.ravel()[perimeter]
    run_start = (ring_lab != np.roll(ring_lab, 1)) & (ring_lab > 0)
    runs = np.bincount(ring_lab[run_start], minlength=n + 1)
    on_edge = np.bincount(ring_lab, minlength=n + 1) > 0
    runs[on_edge & (runs == 0)] = 1  # the part covers the whole perimeter
    data_sides = np.where(on_edge, int(ring_data.any()), 0)
    for L in np.flatnonzero(runs >= 2):
        data_sides[L] = _data_gaps(ring_lab == L, ring_data)
    parts["edge_runs"] = runs[1:]
    parts["data_sides"] = data_sides[1:]

    # islands: pieces of the rest of the core (dual connectivity) that touch no core edge and
    # hold data; each is surrounded by exactly one part, the one just above its first pixel
    islands = np.zeros(n + 1, np.int64)
    dual = ndi.generate_binary_structure(2, 2 if connectivity == 4 else 1)
    rest, n_rest = ndi.label(labels <= 0, structure=dual)
    if n_rest:
        touching = np.zeros(n_rest + 1, bool)
        touching[rest.ravel()[perimeter]] = True
        if not touching[1:].all():
            flat = rest.ravel()
            ridx = np.flatnonzero(flat)
            rlab = flat[ridx]
            first = ridx[_first_occurrence(rlab, n_rest)]
            has_data = np.bincount(rest[data_core], minlength=n_rest + 1)[1:] > 0
            sel = first[~touching[1:] & has_data]
            islands += np.bincount(labels.ravel()[sel - w], minlength=n + 1)
    parts["islands"] = islands[1:]

    is_open = parts["touches_edge"] | parts["touches_aoi_boundary"]
    parts["category"] = np.where(~is_open, "closed", np.where(parts["touches_aoi_boundary"], "II", "I"))
    if core_has_data:
        shape = np.where(parts["islands"] > 0, "D", np.where(parts["data_sides"] >= 2, "C", "B"))
    else:
        shape = np.full(n, "A")
    parts["shape"] = np.where(is_open, shape, "")
    return parts


def _data_gaps(mine: np.ndarray, ring_data: np.ndarray) -> int:
    """Cyclic runs of ``~mine`` along the perimeter that hold at least one data pixel."""
    shift = int(np.flatnonzero(mine)[0])  # start the cycle on one of my pixels: no gap wraps
    m = np.roll(mine, -shift)
    d = np.roll(ring_data, -shift)
    gap_id = np.cumsum(m)  # constant along a gap
    return int(len(np.unique(gap_id[~m & d])))
