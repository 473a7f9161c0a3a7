"""Hole detection, per-cell classification, cross-cell hierarchy and hole causes.

A *hole* is a connected set of empty pixels (no point, ``count == 0``) inside the
area of interest (AOI). Everything here is a pure array kernel: arrays and
:mod:`pipeline.grid` geometry in, arrays and frozen dataclasses out; no I/O, no
Dask, no configuration objects. The per-cell functions see one cell (its core
plus halo) at a time; the cross-cell functions see only the small per-cell
results, never a survey-sized array. See ``docs/holes.md`` for the decisions.

Sources (``DESIGN.md`` seeds)
-----------------------------
[UAS]
    Fiolka, Rouatbi, Bender, "Automated detection and closing of holes in aerial
    point clouds using an UAS": height map (section 3.1), height jumps (eq. 1),
    vertical holes (eq. 2), inner boundaries in 4-connectivity and the count of
    height jumps around each hole (section 3.2, "Detection of inner boundaries").
[OPEN]
    Wang, Liu, Zhu, Wu, "A parallel method for open hole filling in large-scale
    3D automatic modeling based on oblique photography", Remote Sens. 2021, 13,
    3512: closed/open holes per cell, types I/II and shapes A-D (section 3.1),
    hierarchy of open holes, layers outer-to-inner (section 3.2).

Pipeline contract
-----------------
1. Per cell (a Dask task): :func:`detect_cell_holes` on the cell's halo arrays
   -> :class:`CellHoles` (call :meth:`CellHoles.without_labels` before sending
   it to the client).
2. On the client: :func:`link_holes` on every cell's result -> :class:`HoleCatalog`
   (global hole ids, layers, merged statistics), then :func:`classify_causes`
   on ``catalog.stats``.
3. Per cell again (fill): ``catalog.hole_id_lookup(cell_id)[labels]`` turns the
   cell's part labels into global hole ids.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numba
import numpy as np
import scipy.ndimage as ndi
from scipy import sparse
from scipy.sparse import csgraph

from .grid import Cell, PixelWindow

__all__ = [
    "CAUSES",
    "CellHoles",
    "EdgeStrip",
    "HoleCatalog",
    "HoleStats",
    "PartRecord",
    "classify_causes",
    "data_footprint",
    "detect_cell_holes",
    "height_jumps",
    "hole_mask",
    "link_holes",
    "merge_hole_stats",
    "ring_metrics",
    "shape_metrics",
    "vertical_holes",
]

# --------------------------------------------------------------------------------------
# constants and table layouts
# --------------------------------------------------------------------------------------

#: Cell sides, in the order of :attr:`CellHoles.edges`, and their bits in ``sides`` masks.
SIDES: tuple[str, ...] = ("north", "east", "south", "west")
SIDE_BITS: dict[str, int] = {"north": 1, "east": 2, "south": 4, "west": 8}

#: Causes :func:`classify_causes` can return.
CAUSES: tuple[str, ...] = ("occlusion", "water", "missed_coverage", "unknown")

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

#: Mergeable statistics, one column each, one row per part or per hole, and how rows
#: merge. Coordinates are global grid rows/columns. "Ring" = the measured pixels
#: 4-adjacent to the hole ([UAS] section 3.2, "Detection of inner boundaries"). The
#: height of a ring pixel is its ``zmin``, the lowest return: the ground under trees
#: (so vegetation does not hide a flat water rim) and the roof of a solid roof (so a
#: taller neighbour still shows).
STATS_COLUMNS: dict[str, tuple[type, str, str]] = {
    "area_px": (np.int64, "sum", "hole pixels"),
    "row_min": (np.int64, "min", "bounding box"),
    "row_max": (np.int64, "max", "bounding box"),
    "col_min": (np.int64, "min", "bounding box"),
    "col_max": (np.int64, "max", "bounding box"),
    "first_row": (np.int64, "first", "first pixel in raster order (row, then column)"),
    "first_col": (np.int64, "first", "first pixel in raster order"),
    "mean_row": (np.float64, "hole_moment", "mean row index of the hole pixels (pixel centre = index + 0.5)"),
    "mean_col": (np.float64, "hole_moment", "mean column index"),
    "m2_rr": (np.float64, "hole_moment", "sum of squared row deviations from the centroid"),
    "m2_cc": (np.float64, "hole_moment", "sum of squared column deviations"),
    "m2_rc": (np.float64, "hole_moment", "sum of row x column deviations"),
    "edge_len_px": (np.int64, "sum", "pixel edges between the hole and anything else"),
    "aoi_edge_px": (np.int64, "sum", "hole pixels neighbouring a pixel outside the AOI/grid"),
    "ring_px": (np.int64, "sum", "measured pixels 4-adjacent to the hole"),
    "ring_jump_px": (np.int64, "sum", "ring pixels that are height jumps ([UAS] eq. 1)"),
    "ring_low_px": (np.int64, "sum", "ring pixels at the local minimum height"),
    "ring_water_px": (np.int64, "sum", "ring pixels holding water-class points"),
    "ring_z_min": (np.float64, "min", "lowest ring height (ring heights are zmin)"),
    "ring_z_max": (np.float64, "max", "highest ring height"),
    "ring_mean_row": (np.float64, "ring_moment", "mean row index of the ring pixels"),
    "ring_mean_col": (np.float64, "ring_moment", "mean column index of the ring pixels"),
    "ring_mean_z": (np.float64, "ring_moment", "mean ring height"),
    "ring_m2_rr": (np.float64, "ring_moment", "ring: sum of squared row deviations"),
    "ring_m2_cc": (np.float64, "ring_moment", "ring: sum of squared column deviations"),
    "ring_m2_rc": (np.float64, "ring_moment", "ring: sum of row x column deviations"),
    "ring_m2_rz": (np.float64, "ring_moment", "ring: sum of row x height deviations"),
    "ring_m2_cz": (np.float64, "ring_moment", "ring: sum of column x height deviations"),
    "ring_m2_zz": (np.float64, "ring_moment", "ring: sum of squared height deviations"),
    "ring_jump_span_sum": (np.float64, "sum", "sum of zmax - zmin over ring jump pixels"),
    "hole_water_px": (np.int64, "sum", "hole pixels with water-class points (if count excludes them)"),
    "water_mask_px": (np.int64, "sum", "hole pixels inside the given water mask"),
    "touches_data": (np.bool_, "any", "a measured pixel is 4-adjacent somewhere"),
}
#: Groups of columns merged as centroids and co-moments (Chan, Golub and LeVeque):
#: (weight column, mean columns, {co-moment column: (mean index, mean index)}).
_MOMENT_GROUPS = (
    ("area_px", ("mean_row", "mean_col"), {"m2_rr": (0, 0), "m2_cc": (1, 1), "m2_rc": (0, 1)}),
    (
        "ring_px",
        ("ring_mean_row", "ring_mean_col", "ring_mean_z"),
        {"ring_m2_rr": (0, 0), "ring_m2_cc": (1, 1), "ring_m2_rc": (0, 1), "ring_m2_rz": (0, 2),
         "ring_m2_cz": (1, 2), "ring_m2_zz": (2, 2)},
    ),
)

HEIGHT_HIST_DTYPE = np.dtype([("row", np.int64), ("bin", np.int64), ("count", np.int64)])
LINE_HIST_DTYPE = np.dtype([("row", np.int64), ("line", np.int64), ("count", np.int64)])

#: Ring pixels whose hole side the cell cannot resolve alone: pixels touching two or more
#: parts, or a hole pixel of a neighbouring cell. :func:`link_holes` resolves them.
SHARED_RING_DTYPE = np.dtype(
    [
        ("row", np.int64),  # the ring pixel (global)
        ("col", np.int64),
        ("label", np.int32),  # > 0: the adjacent part of this cell; 0: see ref_row/ref_col
        ("ref_row", np.int64),  # the adjacent hole pixel in a neighbouring cell (global), else -1
        ("ref_col", np.int64),
        ("z", np.float64),
        ("span", np.float64),
        ("jump", np.bool_),
        ("low", np.bool_),
        ("water", np.bool_),
        ("line", np.int64),
    ]
)

_BIG = np.int64(1) << 40  # row stride of packed (row, column) keys; grids are far smaller
_NO_LINE = -1


# --------------------------------------------------------------------------------------
# small full-raster kernels
# --------------------------------------------------------------------------------------


def hole_mask(count: np.ndarray, aoi: np.ndarray | None = None) -> np.ndarray:
    """Empty pixels inside the area of interest.

    Parameters
    ----------
    count : ndarray of shape (M, N)
        Points per pixel.
    aoi : ndarray of bool, shape (M, N), optional
        True inside the survey area; None means everywhere.

    Returns
    -------
    ndarray of bool, shape (M, N)
    """
    empty = np.asarray(count) == 0
    if aoi is not None:
        _check_same_shape(count=count, aoi=aoi)
        empty &= np.asarray(aoi, dtype=bool)
    return empty


def height_jumps(zmax: np.ndarray, zmin: np.ndarray, *, jump_threshold: float) -> np.ndarray:
    """Height-jump pixels, [UAS] eq. 1, extended to neighbouring pixels.

    A pixel is a jump where its own points span more than the threshold
    (``zmax - zmin > jump_threshold``, eq. 1) or where its ``zmax`` differs from a
    4-neighbour's by more than the threshold; then both pixels of the pair are
    marked (the wall lies between them: one is the roof edge, one the wall foot).

    Parameters
    ----------
    zmax, zmin : ndarray of shape (M, N)
        Highest and lowest point height per pixel, NaN where empty.
    jump_threshold : float
        In z units.

    Returns
    -------
    ndarray of bool, shape (M, N)
    """
    _check_same_shape(zmax=zmax, zmin=zmin)
    zmax = np.asarray(zmax)
    jump = (zmax - np.asarray(zmin)) > jump_threshold
    step = np.abs(np.diff(zmax, axis=0)) > jump_threshold
    jump[:-1] |= step
    jump[1:] |= step
    step = np.abs(np.diff(zmax, axis=1)) > jump_threshold
    jump[:, :-1] |= step
    jump[:, 1:] |= step
    return jump


def vertical_holes(
    zmax: np.ndarray,
    zmin: np.ndarray,
    voxels: np.ndarray,
    *,
    voxel_height: float,
    jump_threshold: float = 0.0,
) -> np.ndarray:
    """Pixels with a vertical hole, [UAS] eq. 2.

    A pixel whose points span ``zmax - zmin`` should occupy about
    ``(zmax - zmin) / voxel_height`` voxels; fewer occupied voxels mean a gap in a
    vertical surface (a wall that was not lit). [UAS] applies the test to pixels
    with a height jump only: pass ``jump_threshold`` to require
    ``zmax - zmin > jump_threshold`` as well (0 applies eq. 2 alone).

    Parameters
    ----------
    zmax, zmin : ndarray of shape (M, N)
        NaN where empty.
    voxels : ndarray of shape (M, N)
        Occupied voxels per pixel.
    voxel_height : float
        Voxel height in z units.
    jump_threshold : float
        Minimum span in z units.

    Returns
    -------
    ndarray of bool, shape (M, N)
    """
    _check_same_shape(zmax=zmax, zmin=zmin, voxels=voxels)
    if not voxel_height > 0:
        raise ValueError(f"voxel_height must be > 0, got {voxel_height!r}")
    span = np.asarray(zmax, dtype=np.float64) - np.asarray(zmin, dtype=np.float64)
    return (span > jump_threshold) & (span / voxel_height > np.asarray(voxels))


def data_footprint(occupied: np.ndarray, *, closing_px: int) -> np.ndarray:
    """The area covered by the survey: the default AOI when no polygon is given.

    The occupied pixels are closed with a Euclidean disc of radius ``closing_px``
    (gaps narrower than about ``2 * closing_px`` between data are bridged, so
    missed flight lines and scan gaps stay inside), then every void enclosed by
    data is filled. What remains outside is the empty area that opens to the
    raster's border, e.g. the corners of a rectangular tile around a diagonal
    flight strip: those are not holes.

    Parameters
    ----------
    occupied : ndarray of bool, shape (M, N)
        True where there is at least one point. Give a coarse raster for a whole
        survey (e.g. occupancy in 4-16 m blocks): the closing is not local to a cell.
    closing_px : int
        Radius of the closing disc, in pixels of ``occupied``; 0 only fills
        enclosed voids.

    Returns
    -------
    ndarray of bool, shape (M, N)
        True inside the footprint.
    """
    occ = np.asarray(occupied, dtype=bool)
    if occ.ndim != 2:
        raise ValueError(f"occupied must be a 2-dimensional array, got shape {occ.shape}")
    closing_px = int(closing_px)
    if closing_px < 0:
        raise ValueError(f"closing_px must be >= 0, got {closing_px}")
    pad = closing_px + 1
    work = np.pad(occ, pad)  # outside the raster counts as empty
    if closing_px > 0 and work.any():
        dilated = ndi.distance_transform_edt(~work) <= closing_px
        work = ndi.distance_transform_edt(dilated) > closing_px
    work = ndi.binary_fill_holes(work)
    return work[pad:-pad, pad:-pad]


# --------------------------------------------------------------------------------------
# results
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class HoleStats:
    """Mergeable statistics of hole parts or of whole holes (column-wise).

    Attributes
    ----------
    columns : dict of str to ndarray
        One array per name of ``STATS_COLUMNS``, all of length K: one row per part
        (in a :class:`CellHoles`) or per hole (after :func:`merge_hole_stats`).
    height_hist : ndarray of HEIGHT_HIST_DTYPE
        Sparse histogram of ring-pixel heights (``zmin``, see ``STATS_COLUMNS``) per row: bin ``b`` holds
        heights in ``[b * height_bin, (b + 1) * height_bin)``. Sorted by (row, bin).
    line_hist : ndarray of LINE_HIST_DTYPE
        Ring pixels per flight-line id per row (empty without flight-line evidence).
    height_bin : float
        Bin width of ``height_hist`` in z units.
    """

    columns: dict[str, np.ndarray]
    height_hist: np.ndarray
    line_hist: np.ndarray
    height_bin: float

    def __len__(self) -> int:
        return len(self.columns["area_px"])

    def __getitem__(self, name: str) -> np.ndarray:
        return self.columns[name]

    @property
    def table(self) -> np.ndarray:
        """The columns as one structured array (for display and export)."""
        out = np.zeros(len(self), [(k, v[0]) for k, v in STATS_COLUMNS.items()])
        for k in STATS_COLUMNS:
            out[k] = self.columns[k]
        return out

    @classmethod
    def empty(cls, rows: int = 0, *, height_bin: float) -> HoleStats:
        """Rows of neutral statistics (merging them changes nothing)."""
        return cls(_empty_columns(rows), np.zeros(0, HEIGHT_HIST_DTYPE), np.zeros(0, LINE_HIST_DTYPE),
                   float(height_bin))

    def take(self, rows: np.ndarray) -> HoleStats:
        """The given rows, in that order (histogram rows renumbered)."""
        rows = np.asarray(rows, dtype=np.int64)
        new_row = np.full(len(self), -1, np.int64)
        new_row[rows] = np.arange(len(rows))
        hists = []
        for hist, key in ((self.height_hist, "bin"), (self.line_hist, "line")):
            hist = hist[new_row[hist["row"]] >= 0] if len(hist) else hist.copy()
            hist["row"] = new_row[hist["row"]]
            hists.append(hist[np.lexsort((hist[key], hist["row"]))])
        return HoleStats({k: v[rows] for k, v in self.columns.items()}, hists[0], hists[1], self.height_bin)


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

    @property
    def n_parts(self) -> int:
        return len(self.parts)

    def without_labels(self) -> CellHoles:
        """The same result without the label raster (what the client needs)."""
        return replace(self, labels=None)


@dataclass(frozen=True)
class PartRecord:
    """One part of a global hole: a row of the hierarchy table ([OPEN] section 3.2)."""

    hole_id: int
    cell_id: str
    part_label: int
    layer: int
    neighbours: tuple[tuple[str, int], ...]  # (cell_id, part_label) of linked parts in other cells
    area_px: int
    category: str
    shape: str


@dataclass(frozen=True)
class HoleCatalog:
    """Global holes linked across cells, with their parts and layers.

    Attributes
    ----------
    holes : ndarray, shape (H,)
        One row per hole, ordered by hole id (``1..H``, by first pixel in raster
        order): ``hole_id``, ``area_px``, ``n_parts``, ``n_cells``, ``max_layer``,
        ``touches_aoi_boundary``, ``is_small`` (area below ``min_area_px``: a small
        void, counted but not listed).
    stats : HoleStats
        Merged statistics, rows aligned with ``holes``.
    parts : ndarray, shape (P,)
        One row per part of every cell: ``hole_id``, ``cell`` (index into the
        cells given to :func:`link_holes`), ``cell_id``, ``index_x``, ``index_y``,
        ``label``, ``layer`` (1 = touches measured data, n + 1 = linked to a
        layer-n part, 0 = no path to data), ``area_px``, ``category``, ``shape``.
    neighbour_ptr, neighbour_idx : ndarray of int64
        CSR adjacency: the parts linked to part ``i`` across cell edges are rows
        ``neighbour_idx[neighbour_ptr[i]:neighbour_ptr[i + 1]]`` of ``parts``.
    connectivity : int
        The connectivity used.
    min_area_px : int
        Holes with fewer pixels are small voids.
    settled_small_voids, settled_small_void_px : int
        Small closed voids the cells settled themselves (``detect_cell_holes(...,
        min_area_px=...)``): counted here, absent from ``holes`` and ``parts``.
    """

    holes: np.ndarray
    stats: HoleStats
    parts: np.ndarray
    neighbour_ptr: np.ndarray
    neighbour_idx: np.ndarray
    connectivity: int
    min_area_px: int
    settled_small_voids: int = 0
    settled_small_void_px: int = 0

    @property
    def listed(self) -> np.ndarray:
        """Rows of ``holes`` that are reported (not small voids)."""
        return self.holes[~self.holes["is_small"]]

    @property
    def small_void_count(self) -> int:
        """Holes below ``min_area_px``, including those the cells settled."""
        return int(self.holes["is_small"].sum()) + self.settled_small_voids

    @property
    def small_void_px(self) -> int:
        return int(self.holes["area_px"][self.holes["is_small"]].sum()) + self.settled_small_void_px

    def hole_id_lookup(self, cell_id: str) -> np.ndarray:
        """Array mapping a cell's part labels to hole ids.

        ``catalog.hole_id_lookup(cell.id)[labels]`` is the cell's hole-id raster:
        0 where there is no hole, -1 on small voids the cell settled (label -1).
        """
        rows = np.flatnonzero(self.parts["cell_id"] == cell_id)
        n = int(self.parts["label"][rows].max()) if len(rows) else 0
        lookup = np.zeros(n + 2, dtype=np.int64)  # the extra last entry serves label -1
        lookup[self.parts["label"][rows]] = self.parts["hole_id"][rows]
        lookup[-1] = -1
        return lookup

    def part_records(self) -> list[PartRecord]:
        """The hierarchy as records: hole, cell, part, layer, linked parts."""
        p = self.parts
        out = []
        for i in range(len(p)):
            nb = self.neighbour_idx[self.neighbour_ptr[i] : self.neighbour_ptr[i + 1]]
            out.append(
                PartRecord(
                    hole_id=int(p["hole_id"][i]),
                    cell_id=str(p["cell_id"][i]),
                    part_label=int(p["label"][i]),
                    layer=int(p["layer"][i]),
                    neighbours=tuple((str(p["cell_id"][j]), int(p["label"][j])) for j in nb),
                    area_px=int(p["area_px"][i]),
                    category=str(p["category"][i]),
                    shape=str(p["shape"][i]),
                )
            )
        return out


# --------------------------------------------------------------------------------------
# per-cell detection
# --------------------------------------------------------------------------------------


def detect_cell_holes(
    count: np.ndarray,
    zmax: np.ndarray,
    zmin: np.ndarray,
    aoi: np.ndarray | None = None,
    *,
    cell: Cell,
    grid_window: PixelWindow,
    jump_threshold: float,
    connectivity: int = 4,
    local_radius_px: int = 8,
    low_tolerance: float = 0.5,
    height_bin: float = 0.25,
    water_points: np.ndarray | None = None,
    water_mask: np.ndarray | None = None,
    flight_line: np.ndarray | None = None,
    min_area_px: int = 0,
) -> CellHoles:
    """Find, classify and measure the hole parts of one cell.

    A part is a connected set of empty AOI pixels of the cell core. Parts are
    classified per [OPEN] section 3.1 (closed / open type I / open type II,
    shapes A-D, see ``docs/holes.md``) and measured with statistics that merge
    exactly across cells (:func:`merge_hole_stats`, :func:`link_holes`): the
    results do not depend on the cell size.

    Parameters
    ----------
    count : ndarray of shape ``cell.halo_window.shape``
        Points per pixel over the cell's halo window.
    zmax, zmin : ndarray of float, same shape
        Highest and lowest point per pixel, NaN where empty.
    aoi : ndarray of bool, same shape, optional
        True inside the area of interest; None: the whole grid.
    cell : Cell
        The cell; the arrays cover ``cell.halo_window``.
    grid_window : PixelWindow
        The survey grid (``Grid.window``): beyond it is outside the AOI.
    jump_threshold : float
        Height-jump threshold in z units ([UAS] eq. 1).
    connectivity : {4, 8}
        Connectivity of hole pixels. 4 (default) follows [UAS] section 3.2 and
        gives outlines whose polygons are always valid; see ``docs/holes.md``.
    local_radius_px : int
        A ring pixel is "low" when its height (``zmin``) is within ``low_tolerance``
        of the lowest ``zmin`` within this many pixels (square window; 0 disables).
        The halo must reach this far (and at least 1 pixel) on every side that is
        not the grid's edge.
    low_tolerance : float
        In z units.
    height_bin : float
        Bin width (z units) of the ring-height histogram.
    water_points : ndarray, same shape, optional
        Water-class points per pixel (e.g. ASPRS class 9).
    water_mask : ndarray of bool, same shape, optional
        True inside known water polygons.
    flight_line : ndarray of int, same shape, optional
        An id of a flight line covering each pixel (e.g. a point_source_id), < 0: unknown.
    min_area_px : int
        Closed parts (complete holes: they touch neither the core edge nor the AOI
        boundary) smaller than this are settled here as small voids: counted in
        ``small_void_count``/``small_void_px``, labelled -1, and not listed. Open
        parts are always kept, whatever their size: their hole's area is only
        known after linking. 0 (default) keeps every part.

    Returns
    -------
    CellHoles

    Raises
    ------
    ValueError
        On arrays of the wrong shape, a bad parameter, or a halo narrower than needed.
    """
    core, halo = cell.window, cell.halo_window
    arrays = {"count": count, "zmax": zmax, "zmin": zmin, "aoi": aoi, "water_points": water_points,
              "water_mask": water_mask, "flight_line": flight_line}
    for name, arr in arrays.items():
        if arr is not None and np.shape(arr) != halo.shape:
            raise ValueError(
                f"{name} has shape {np.shape(arr)}; expected the cell's halo window shape {halo.shape}"
            )
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

    # -- the work window: core + R pixels, padded beyond the grid ----------------------------
    h, w = core.shape
    W2 = w + 2 * R
    count_w = _work_view(np.asarray(count), cell, work, 0)
    if aoi is None:
        aoi_w = _work_view(np.ones(halo.shape, dtype=bool), cell, work, False)
    else:
        aoi_w = _work_view(np.asarray(aoi, dtype=bool), cell, work, False)
    data_w = count_w > 0
    hole_w = ~data_w & aoi_w

    def around(arr: np.ndarray, dr: int, dc: int) -> np.ndarray:
        """The (h, w) view of ``arr`` shifted by (dr, dc) relative to the core."""
        return arr[R + dr : R + dr + h, R + dc : R + dc + w]

    hole_core = around(hole_w, 0, 0)
    data_core = around(data_w, 0, 0)
    structure = ndi.generate_binary_structure(2, 1 if connectivity == 4 else 2)
    labels, n = ndi.label(hole_core, structure=structure)
    labels = labels.astype(np.int32, copy=False)
    core_has_data = bool(data_core.any())
    edges = _edge_strips(labels, core)
    if n == 0:
        return CellHoles(cell, connectivity, labels, np.zeros(0, PART_DTYPE),
                         HoleStats.empty(0, height_bin=height_bin), edges,
                         np.zeros(0, SHARED_RING_DTYPE), core_has_data, 0, 0)

    cols = _empty_columns(n)
    # -- every hole pixel once: area, moments, box; its borders; evidence inside it -----------
    wp_w = wm_w = line_w = None
    if water_points is not None:
        wp_w = _work_view(np.asarray(water_points), cell, work, 0)
    if water_mask is not None:
        wm_w = _work_view(np.asarray(water_mask, dtype=bool), cell, work, False)
    if flight_line is not None:
        line_w = _work_view(np.asarray(flight_line, dtype=np.int64), cell, work, _NO_LINE)
    no_flag = np.zeros((1, 1), bool)
    _pixel_statistics(
        cols, labels, n, core, hole_w, aoi_w, data_w,
        no_flag if wp_w is None else wp_w > 0, no_flag if wm_w is None else wm_w, R, connectivity,
    )

    # -- closed parts are complete holes: settle the small ones here --------------------------
    on_edge = np.zeros(n + 1, bool)
    for strip in edges:
        on_edge[strip.labels] = True
    closed = ~on_edge[1:] & (cols["aoi_edge_px"] == 0)
    small = closed & (cols["area_px"] < min_area_px)
    small_void_count = int(small.sum())
    small_void_px = int(cols["area_px"][small].sum())
    if small_void_count:
        keep = np.flatnonzero(~small)
        relabel = np.full(n + 1, -1, np.int32)
        relabel[0] = 0
        relabel[keep + 1] = np.arange(1, len(keep) + 1, dtype=np.int32)
        labels = relabel[labels]
        cols = {k: v[keep] for k, v in cols.items()}
        closed = closed[keep]
        n = len(keep)
        edges = _edge_strips(labels, core)

    # -- the ring: measured core pixels 4-adjacent to a hole pixel ([UAS] 3.2) ----------------
    # A ring pixel counts here for every closed part it touches (a closed part is a whole
    # hole, distinct from all others) and for the single open part it touches; when it
    # touches several open parts, or a hole pixel of a neighbouring cell, it becomes one
    # shared row per such part/pixel, which the client resolves once parts are linked, so
    # that each ring pixel counts once per hole whatever the cell size.
    zmax_w = _work_view(np.asarray(zmax), cell, work, np.nan)
    zmin_w = _work_view(np.asarray(zmin), cell, work, np.nan)
    lr = int(local_radius_px)
    if lr > 0:
        zmin_data = np.where(data_w, zmin_w, np.inf).astype(np.float32)
        row_min = ndi.minimum_filter1d(zmin_data, 2 * lr + 1, axis=1, mode="constant", cval=np.inf)
    else:
        row_min = np.zeros((1, 1), np.float32)
    no_water = np.zeros((1, 1), bool)
    no_line = np.zeros((1, 1), np.int64)
    ring = _ring_kernel(
        labels, hole_w, data_w, zmax_w, zmin_w, row_min,
        no_water if wp_w is None else wp_w > 0, no_line if line_w is None else line_w,
        np.concatenate([[False], closed]), R, lr, float(jump_threshold), float(low_tolerance), n,
        wp_w is not None, line_w is not None,
    )
    (ring_px, ring_jump, ring_low, ring_water, ring_sums, span_sum, z_lo, z_hi,
     s_part, s_z, s_line, sh_r, sh_c, sh_key, sh_z, sh_span, sh_flags, sh_line) = ring
    cols["ring_px"] = ring_px[1:]
    cols["ring_jump_px"] = ring_jump[1:]
    cols["ring_low_px"] = ring_low[1:]
    cols["ring_water_px"] = ring_water[1:]
    _ring_moments(cols, ring_px[1:], ring_sums[:, 1:], core)
    cols["ring_jump_span_sum"] = span_sum[1:]
    cols["ring_z_min"] = z_lo[1:]
    cols["ring_z_max"] = z_hi[1:]
    finite = np.isfinite(s_z)
    height_hist = _coo_counts(s_part[finite] - 1, np.floor(s_z[finite] / height_bin).astype(np.int64),
                              HEIGHT_HIST_DTYPE)
    known = s_line >= 0
    line_hist = _coo_counts(s_part[known] - 1, s_line[known], LINE_HIST_DTYPE)

    shared = np.zeros(len(sh_r), SHARED_RING_DTYPE)
    if len(sh_r):
        shared["row"] = sh_r + core.row_off
        shared["col"] = sh_c + core.col_off
        foreign = sh_key < 0
        shared["label"] = np.where(foreign, 0, sh_key)
        fr, fc = np.divmod(np.where(foreign, -1 - sh_key, 0), W2)
        shared["ref_row"] = np.where(foreign, fr - R + core.row_off, -1)
        shared["ref_col"] = np.where(foreign, fc - R + core.col_off, -1)
        shared["z"] = sh_z
        shared["span"] = sh_span
        shared["jump"] = (sh_flags & 1) != 0
        shared["low"] = (sh_flags & 2) != 0
        shared["water"] = (sh_flags & 4) != 0
        shared["line"] = sh_line

    # -- topology per part: cell edges, AOI boundary, islands, [OPEN] category and shape -----
    parts = _part_topology(labels, n, hole_w, data_core, R, cols, core_has_data, connectivity)
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
    )


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
    cols: dict[str, np.ndarray],
    labels: np.ndarray,
    n: int,
    core: PixelWindow,
    hole_w: np.ndarray,
    aoi_w: np.ndarray,
    data_w: np.ndarray,
    water_w: np.ndarray,
    mask_w: np.ndarray,
    R: int,
    connectivity: int,
) -> None:
    """Area, box, first pixel, moments, edge length, AOI contact, data contact, evidence."""
    (area, sr, sc, srr, scc, src, rmin, rmax, cmin, cmax, fcol, edge_len, aoi_edge, near_data, wet,
     masked) = _hole_pixel_kernel(labels, n, hole_w, aoi_w, data_w, water_w, mask_w, R, connectivity == 8,
                                  water_w.shape == hole_w.shape, mask_w.shape == hole_w.shape)
    area, sr, sc = area[1:], sr[1:], sc[1:]
    mr, mc = sr / area, sc / area
    cols["area_px"] = area
    cols["mean_row"] = mr + core.row_off
    cols["mean_col"] = mc + core.col_off
    cols["m2_rr"] = srr[1:] - sr * mr  # local coordinates (< cell size): no cancellation
    cols["m2_cc"] = scc[1:] - sc * mc
    cols["m2_rc"] = src[1:] - sr * mc
    cols["row_min"] = rmin[1:] + core.row_off
    cols["row_max"] = rmax[1:] + core.row_off
    cols["col_min"] = cmin[1:] + core.col_off
    cols["col_max"] = cmax[1:] + core.col_off
    cols["first_row"] = cols["row_min"].copy()
    cols["first_col"] = fcol[1:] + core.col_off
    cols["edge_len_px"] = edge_len[1:]
    cols["aoi_edge_px"] = aoi_edge[1:]
    cols["touches_data"] = near_data[1:] > 0
    cols["hole_water_px"] = wet[1:]
    cols["water_mask_px"] = masked[1:]


@numba.njit(cache=True, nogil=True)
def _hole_pixel_kernel(labels, n, hole_w, aoi_w, data_w, water_w, mask_w, R, eight, has_water,
                       has_mask):  # pragma: no cover - compiled
    """One raster-order pass over the hole pixels of the core (work arrays: core grown by R).

    Per label: area, coordinate sums, bounding box and first column; pixel edges to
    non-hole pixels (4-neighbours); pixels next to the outside of the AOI/grid (by the
    connectivity); pixels 4-adjacent to measured data; pixels with water points or
    inside the water mask.
    """
    h, w = labels.shape
    area = np.zeros(n + 1, np.int64)
    sr = np.zeros(n + 1)
    sc = np.zeros(n + 1)
    srr = np.zeros(n + 1)
    scc = np.zeros(n + 1)
    src = np.zeros(n + 1)
    rmin = np.zeros(n + 1, np.int64)
    rmax = np.zeros(n + 1, np.int64)
    cmin = np.full(n + 1, w, np.int64)
    cmax = np.zeros(n + 1, np.int64)
    fcol = np.zeros(n + 1, np.int64)
    edge_len = np.zeros(n + 1, np.int64)
    aoi_edge = np.zeros(n + 1, np.int64)
    near_data = np.zeros(n + 1, np.int64)
    wet = np.zeros(n + 1, np.int64)
    masked = np.zeros(n + 1, np.int64)
    for r in range(h):
        for c in range(w):
            lab = labels[r, c]
            if lab <= 0:
                continue
            if area[lab] == 0:
                rmin[lab] = r
                fcol[lab] = c
            area[lab] += 1
            sr[lab] += r
            sc[lab] += c
            srr[lab] += r * r
            scc[lab] += c * c
            src[lab] += r * c
            rmax[lab] = r
            if c < cmin[lab]:
                cmin[lab] = c
            if c > cmax[lab]:
                cmax[lab] = c
            y = r + R
            x = c + R
            edges = 0
            outside = False
            data = False
            for dy, dx in ((-1, 0), (0, 1), (1, 0), (0, -1)):
                if not hole_w[y + dy, x + dx]:
                    edges += 1
                if not aoi_w[y + dy, x + dx]:
                    outside = True
                if data_w[y + dy, x + dx]:
                    data = True
            if eight and not outside:
                for dy, dx in ((-1, -1), (-1, 1), (1, -1), (1, 1)):
                    if not aoi_w[y + dy, x + dx]:
                        outside = True
            edge_len[lab] += edges
            aoi_edge[lab] += outside
            near_data[lab] += data
            if has_water and water_w[y, x]:
                wet[lab] += 1
            if has_mask and mask_w[y, x]:
                masked[lab] += 1
    return (area, sr, sc, srr, scc, src, rmin, rmax, cmin, cmax, fcol, edge_len, aoi_edge, near_data, wet,
            masked)


def _ring_moments(cols: dict[str, np.ndarray], count: np.ndarray, sums: np.ndarray, core: PixelWindow) -> None:
    """Centroid and co-moments of (row, column, height) of the ring from raw sums."""
    k = np.maximum(count, 1).astype(np.float64)
    means = sums[:3] / k
    cols["ring_mean_row"] = np.where(count > 0, means[0] + core.row_off, 0.0)
    cols["ring_mean_col"] = np.where(count > 0, means[1] + core.col_off, 0.0)
    cols["ring_mean_z"] = np.where(count > 0, means[2], 0.0)
    for name, (i, j), raw in (("ring_m2_rr", (0, 0), 3), ("ring_m2_cc", (1, 1), 4), ("ring_m2_rc", (0, 1), 5),
                              ("ring_m2_rz", (0, 2), 6), ("ring_m2_cz", (1, 2), 7), ("ring_m2_zz", (2, 2), 8)):
        cols[name] = np.where(count > 0, sums[raw] - sums[i] * means[j], 0.0)


@numba.njit(cache=True, nogil=True)
def _ring_kernel(labels, hole_w, data_w, zmax_w, zmin_w, row_min, water_w, line_w, settled, R, lr,
                 jump_threshold, low_tolerance, n, has_water, has_line):  # pragma: no cover - compiled
    """Ring pixels of the core: sums per part where the part is known here, rows for the rest.

    Work-window arrays are the core grown by ``R`` pixels. A ring pixel's hole keys are
    the labels of its 4-neighbours in the core (> 0; settled small voids, -1, are
    ignored) or ``-1 - index`` of a hole pixel of the 1-pixel frame around the core (a
    neighbouring cell's hole), each kept once. The pixel is added here to every
    ``settled`` (closed) part it touches, and to the one open part it touches if that
    is its only other key; otherwise each other key becomes a shared row.
    Its values: height ``zmin`` (the lowest return: the ground under vegetation, the
    roof of a solid roof); span ``zmax - zmin``; jump (span or a ``zmax`` step to a
    4-neighbour above ``jump_threshold``, [UAS] eq. 1); low (height within
    ``low_tolerance`` of the lowest ``zmin`` in the (2 lr + 1)^2 window; ``row_min``
    is the row-wise minimum); water; flight line.
    """
    h, w = labels.shape
    W2 = hole_w.shape[1]
    hole = hole_w.ravel()
    data = data_w.ravel()
    zmx = zmax_w.ravel()
    zmn = zmin_w.ravel()
    rmin = row_min.ravel()
    wat = water_w.ravel()
    lin = line_w.ravel()
    steps = np.array([-W2, 1, W2, -1])
    drs = np.array([-1, 0, 1, 0])
    dcs = np.array([0, 1, 0, -1])
    ring_px = np.zeros(n + 1, np.int64)
    ring_jump = np.zeros(n + 1, np.int64)
    ring_low = np.zeros(n + 1, np.int64)
    ring_water = np.zeros(n + 1, np.int64)
    sums = np.zeros((9, n + 1))  # r, c, z, rr, cc, rc, rz, cz, zz (core coordinates)
    span_sum = np.zeros(n + 1)
    z_lo = np.full(n + 1, np.inf)
    z_hi = np.full(n + 1, -np.inf)
    local = np.zeros(4, np.int64)  # keys counted here
    other = np.zeros(4, np.int64)  # keys left to the client
    n_local_rows = 0
    n_shared_rows = 0
    s_part = np.zeros(0, np.int64)
    s_z = np.zeros(0)
    s_line = np.zeros(0, np.int64)
    sh_r = np.zeros(0, np.int64)
    sh_c = np.zeros(0, np.int64)
    sh_key = np.zeros(0, np.int64)
    sh_z = np.zeros(0)
    sh_span = np.zeros(0)
    sh_flags = np.zeros(0, np.int8)
    sh_line = np.zeros(0, np.int64)
    i_local = 0
    i_shared = 0
    for fill in range(2):  # pass 0 counts the output rows, pass 1 fills them
        if fill == 1:
            s_part = np.zeros(n_local_rows, np.int64)
            s_z = np.zeros(n_local_rows)
            s_line = np.full(n_local_rows, -1, np.int64)
            sh_r = np.zeros(n_shared_rows, np.int64)
            sh_c = np.zeros(n_shared_rows, np.int64)
            sh_key = np.zeros(n_shared_rows, np.int64)
            sh_z = np.zeros(n_shared_rows)
            sh_span = np.zeros(n_shared_rows)
            sh_flags = np.zeros(n_shared_rows, np.int8)
            sh_line = np.full(n_shared_rows, -1, np.int64)
        for r in range(h):
            for c in range(w):
                p = (r + R) * W2 + (c + R)
                if not data[p]:
                    continue
                n_local = 0
                n_other = 0
                for d in range(4):
                    q = p + steps[d]
                    if not hole[q]:
                        continue
                    r2 = r + drs[d]
                    c2 = c + dcs[d]
                    if 0 <= r2 < h and 0 <= c2 < w:
                        key = np.int64(labels[r2, c2])
                        if key <= 0:
                            continue
                    else:
                        key = -1 - np.int64(q)
                    dup = False
                    for j in range(n_local):
                        if local[j] == key:
                            dup = True
                    for j in range(n_other):
                        if other[j] == key:
                            dup = True
                    if dup:
                        continue
                    if key > 0 and settled[key]:
                        local[n_local] = key
                        n_local += 1
                    else:
                        other[n_other] = key
                        n_other += 1
                if n_other == 1 and other[0] > 0:
                    local[n_local] = other[0]
                    n_local += 1
                    n_other = 0
                if n_local == 0 and n_other == 0:
                    continue
                if fill == 0:
                    n_local_rows += n_local
                    n_shared_rows += n_other
                    continue
                top = np.float64(zmx[p])
                z = np.float64(zmn[p])  # the ring height: ground under vegetation, a solid roof
                if z != z:  # points without heights (inconsistent input): use what there is
                    z = top
                if top != top:
                    top = z
                span = top - z
                jump = span > jump_threshold
                for d in range(4):
                    if abs(top - zmx[p + steps[d]]) > jump_threshold:
                        jump = True
                low = True
                if lr > 0:
                    m = rmin[p]
                    for k in range(1, lr + 1):
                        m = min(m, rmin[p - k * W2], rmin[p + k * W2])
                    low = z <= m + low_tolerance
                water = has_water and wat[p]
                line = lin[p] if has_line else -1
                for j in range(n_local):
                    lab = local[j]
                    ring_px[lab] += 1
                    ring_jump[lab] += jump
                    ring_low[lab] += low
                    ring_water[lab] += water
                    sums[0, lab] += r
                    sums[1, lab] += c
                    sums[2, lab] += z
                    sums[3, lab] += r * r
                    sums[4, lab] += c * c
                    sums[5, lab] += r * c
                    sums[6, lab] += r * z
                    sums[7, lab] += c * z
                    sums[8, lab] += z * z
                    if jump:
                        span_sum[lab] += span
                    z_lo[lab] = min(z_lo[lab], z)
                    z_hi[lab] = max(z_hi[lab], z)
                    s_part[i_local] = lab
                    s_z[i_local] = z
                    s_line[i_local] = line
                    i_local += 1
                for j in range(n_other):
                    sh_r[i_shared] = r
                    sh_c[i_shared] = c
                    sh_key[i_shared] = other[j]
                    sh_z[i_shared] = z
                    sh_span[i_shared] = span
                    sh_flags[i_shared] = jump + 2 * low + 4 * water
                    sh_line[i_shared] = line
                    i_shared += 1
    return (ring_px, ring_jump, ring_low, ring_water, sums, span_sum, z_lo, z_hi,
            s_part, s_z, s_line, sh_r, sh_c, sh_key, sh_z, sh_span, sh_flags, sh_line)


def _coo_counts(rows: np.ndarray, keys: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """Counts of (row, key) pairs as a table sorted by (row, key)."""
    if not len(rows):
        return np.zeros(0, dtype)
    k0 = int(keys.min())
    span = int(keys.max()) - k0 + 1
    if span * (int(rows.max()) + 1) >= 2**62:
        return _sum_coo([(rows, keys, np.ones(len(rows), np.int64))], dtype)
    packed = np.sort(rows.astype(np.int64) * span + (keys - k0))
    new = np.ones(len(packed), bool)
    new[1:] = packed[1:] != packed[:-1]
    starts = np.flatnonzero(new)
    out = np.zeros(len(starts), dtype)
    out[dtype.names[0]], key = np.divmod(packed[starts], span)
    out[dtype.names[1]] = key + k0
    out["count"] = np.diff(np.append(starts, len(packed)))
    return out


def _sum_coo(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]], dtype: np.dtype) -> np.ndarray:
    """Sum of sparse (row, key, count) tables, sorted by (row, key)."""
    if not parts:
        return np.zeros(0, dtype)
    rows = np.concatenate([np.asarray(p[0], np.int64) for p in parts])
    keys = np.concatenate([np.asarray(p[1], np.int64) for p in parts])
    counts = np.concatenate([np.asarray(p[2], np.int64) for p in parts])
    if not len(rows):
        return np.zeros(0, dtype)
    order = np.lexsort((keys, rows))
    rows, keys, counts = rows[order], keys[order], counts[order]
    new = np.ones(len(rows), bool)
    new[1:] = (rows[1:] != rows[:-1]) | (keys[1:] != keys[:-1])
    starts = np.flatnonzero(new)
    out = np.zeros(len(starts), dtype)
    out[dtype.names[0]] = rows[starts]
    out[dtype.names[1]] = keys[starts]
    out["count"] = np.add.reduceat(counts, starts)
    return out


def _perimeter_flat(h: int, w: int) -> np.ndarray:
    """Flat indices of a (h, w) array's outermost pixels, once each, in cyclic order."""
    top = np.arange(w)
    right = np.arange(1, h) * w + (w - 1)
    bottom = (h - 1) * w + np.arange(w - 2, -1, -1) if h > 1 else np.zeros(0, np.int64)
    left = np.arange(h - 2, 0, -1) * w if w > 1 else np.zeros(0, np.int64)
    return np.concatenate([top, right, bottom, left]).astype(np.int64)


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


# --------------------------------------------------------------------------------------
# merging statistics
# --------------------------------------------------------------------------------------


def _empty_columns(rows: int) -> dict[str, np.ndarray]:
    big = np.iinfo(np.int64).max
    neutral = {"row_min": big, "col_min": big, "first_row": big, "first_col": big, "row_max": -1,
               "col_max": -1, "ring_z_min": np.inf, "ring_z_max": -np.inf}
    return {
        name: (np.full(rows, neutral[name], dtype) if name in neutral else np.zeros(rows, dtype))
        for name, (dtype, _, _) in STATS_COLUMNS.items()
    }


def merge_hole_stats(stats: Sequence[HoleStats], groups: Sequence[np.ndarray], n_groups: int) -> HoleStats:
    """Combine rows of several statistics into ``n_groups`` rows.

    Counts and sums add, minima and maxima combine, the first pixel is the
    lexicographic minimum, centroids and second moments combine exactly (the
    pairwise form of Chan, Golub and LeVeque), histograms add. Row ``i`` of
    ``stats[k]`` goes to row ``groups[k][i]`` of the result.

    Parameters
    ----------
    stats : sequence of HoleStats
    groups : sequence of ndarray of int
        Target row of each input row, one array per element of ``stats``.
    n_groups : int
        Rows of the result.

    Returns
    -------
    HoleStats
    """
    if len(stats) != len(groups):
        raise ValueError("stats and groups must have the same length")
    if not stats:
        raise ValueError("merge_hole_stats needs at least one HoleStats")
    height_bin = stats[0].height_bin
    if any(s.height_bin != height_bin for s in stats):
        raise ValueError("cannot merge statistics with different height_bin")
    g = np.concatenate([np.asarray(x, dtype=np.int64) for x in groups])
    if len(g) != sum(len(s) for s in stats):
        raise ValueError("each groups array must have one entry per statistics row")
    t = {name: np.concatenate([s.columns[name] for s in stats]) for name in STATS_COLUMNS}
    out = _empty_columns(n_groups)
    for name, (dtype, rule, _) in STATS_COLUMNS.items():
        if rule == "sum":
            total = np.bincount(g, t[name], minlength=n_groups)
            out[name] = np.rint(total).astype(dtype) if dtype is np.int64 else total
        elif rule in ("min", "max"):
            (np.minimum if rule == "min" else np.maximum).at(out[name], g, t[name])
        elif rule == "any":
            out[name] = np.bincount(g, t[name], minlength=n_groups) > 0
    big = np.iinfo(np.int64).max
    has = t["area_px"] > 0
    key = np.where(has, t["first_row"] * _BIG + t["first_col"], big)
    best = np.full(n_groups, big)
    np.minimum.at(best, g, key)
    ok = best != big
    out["first_row"][ok] = best[ok] // _BIG
    out["first_col"][ok] = best[ok] % _BIG
    for weight, mean_names, co_moments in _MOMENT_GROUPS:
        wt = t[weight].astype(np.float64)
        total = np.maximum(out[weight].astype(np.float64), 1.0)
        means = [np.bincount(g, wt * t[m], minlength=n_groups) / total for m in mean_names]
        devs = [np.where(wt > 0, t[m] - mu[g], 0.0) for m, mu in zip(mean_names, means)]
        for m, mu in zip(mean_names, means):
            out[m] = mu
        for name, (i, j) in co_moments.items():
            out[name] = np.bincount(g, t[name] + wt * devs[i] * devs[j], minlength=n_groups)
    hh = [(np.asarray(gr, np.int64)[s.height_hist["row"]], s.height_hist["bin"], s.height_hist["count"])
          for s, gr in zip(stats, groups)]
    lh = [(np.asarray(gr, np.int64)[s.line_hist["row"]], s.line_hist["line"], s.line_hist["count"])
          for s, gr in zip(stats, groups)]
    return HoleStats(out, _sum_coo(hh, HEIGHT_HIST_DTYPE), _sum_coo(lh, LINE_HIST_DTYPE), height_bin)


def _shared_ring_stats(entries: np.ndarray, height_bin: float) -> HoleStats:
    """One statistics row per shared ring pixel (area 0: a ring contribution only)."""
    k = len(entries)
    cols = _empty_columns(k)
    cols["ring_px"][:] = 1
    cols["ring_jump_px"] = entries["jump"].astype(np.int64)
    cols["ring_low_px"] = entries["low"].astype(np.int64)
    cols["ring_water_px"] = entries["water"].astype(np.int64)
    z = entries["z"].astype(np.float64)
    cols["ring_z_min"] = z.copy()
    cols["ring_z_max"] = z.copy()
    cols["ring_mean_row"] = entries["row"].astype(np.float64)
    cols["ring_mean_col"] = entries["col"].astype(np.float64)
    cols["ring_mean_z"] = z.copy()
    cols["ring_jump_span_sum"] = np.where(entries["jump"], entries["span"], 0.0)
    cols["touches_data"][:] = True
    rows = np.arange(k, dtype=np.int64)
    finite = np.isfinite(z)
    hh = _coo_counts(rows[finite], np.floor(z[finite] / height_bin).astype(np.int64), HEIGHT_HIST_DTYPE)
    known = entries["line"] >= 0
    lh = _coo_counts(rows[known], entries["line"][known], LINE_HIST_DTYPE)
    return HoleStats(cols, hh, lh, float(height_bin))


# --------------------------------------------------------------------------------------
# cross-cell linking and hierarchy
# --------------------------------------------------------------------------------------

_ACROSS = {"north": (-1, 0), "east": (0, 1), "south": (1, 0), "west": (0, -1)}


def link_holes(cells: Sequence[CellHoles], *, min_area_px: int = 1) -> HoleCatalog:
    """Link hole parts across cell edges into global holes and layer them.

    Parts of adjacent cells whose edge pixels touch (4-adjacency across the
    shared edge; with 8-connectivity also diagonally, including across cell
    corners) belong to one hole: the connected components of that contact graph
    (a union-find) are the global holes. Layers follow [OPEN] section 3.2:
    layer 1 = parts that touch measured data (a measured pixel 4-adjacent, in
    the core or the halo), layer n + 1 = parts linked to a layer-n part.

    Only the small per-cell results are used (edge strips, part tables,
    statistics, shared ring pixels); no survey-sized array is built.

    Parameters
    ----------
    cells : sequence of CellHoles
        Every cell of the survey (labels may have been dropped).
    min_area_px : int
        Holes with fewer pixels are small voids (flagged ``is_small``).

    Returns
    -------
    HoleCatalog
    """
    if not cells:
        raise ValueError("link_holes needs at least one cell")
    connectivity = cells[0].connectivity
    if any(c.connectivity != connectivity for c in cells):
        raise ValueError("all cells must use the same connectivity")
    height_bin = cells[0].stats.height_bin
    sizes = np.array([c.n_parts for c in cells], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    n_nodes = int(offsets[-1])

    # every hole pixel on a cell edge, by global position
    empty = np.zeros(0, np.int64)
    e_rows, e_cols, e_nodes, e_side = [empty], [empty], [empty], [empty]
    for k, c in enumerate(cells):
        for strip in c.edges:
            m = strip.labels > 0
            e_rows.append(strip.rows[m])
            e_cols.append(strip.cols[m])
            e_nodes.append(offsets[k] + strip.labels[m].astype(np.int64) - 1)
            e_side.append(np.full(int(m.sum()), SIDES.index(strip.side), np.int64))
    e_rows, e_cols, e_nodes, e_side = (np.concatenate(x) for x in (e_rows, e_cols, e_nodes, e_side))
    table_key, first_index = np.unique((e_rows + 1) * _BIG + (e_cols + 1), return_index=True)
    table_node = e_nodes[first_index]

    def node_at(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """The part (node) holding the edge hole pixel at (rows, cols); -1 where none."""
        key = (rows + 1) * _BIG + (cols + 1)
        if not len(table_key):
            return np.full(len(key), -1, np.int64)
        i = np.minimum(np.searchsorted(table_key, key), len(table_key) - 1)
        return np.where(table_key[i] == key, table_node[i], -1)

    # contacts across edges -> contact graph -> components
    a_list, b_list = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for s, side in enumerate(SIDES):
        m = e_side == s
        dr, dc = _ACROSS[side]
        steps = [(dr, dc)]
        if connectivity == 8:
            steps += [(dr, -1), (dr, 1)] if dr else [(-1, dc), (1, dc)]
        for sr, sc in steps:
            other = node_at(e_rows[m] + sr, e_cols[m] + sc)
            ok = other >= 0
            a_list.append(e_nodes[m][ok])
            b_list.append(other[ok])
    a, b = np.concatenate(a_list), np.concatenate(b_list)
    keep = a != b
    a, b = a[keep], b[keep]
    graph = sparse.coo_matrix(
        (np.ones(2 * len(a), np.int8), (np.concatenate([a, b]), np.concatenate([b, a]))),
        shape=(n_nodes, n_nodes),
    ).tocsr()
    graph.sum_duplicates()
    graph.data[:] = 1
    n_comp, comp = csgraph.connected_components(graph, directed=False)

    # shared ring pixels: find the hole on the other side, count each pixel once per hole
    ent_all, ent_comp = [np.zeros(0, SHARED_RING_DTYPE)], [np.zeros(0, np.int64)]
    for k, c in enumerate(cells):
        e = c.shared_ring
        if not len(e):
            continue
        node = np.where(e["label"] > 0, offsets[k] + e["label"].astype(np.int64) - 1, -1)
        foreign = e["label"] == 0
        if foreign.any():
            node[foreign] = node_at(e["ref_row"][foreign], e["ref_col"][foreign])
        ok = node >= 0  # a neighbour cell that was not given leaves its side unresolved
        ent_all.append(e[ok])
        ent_comp.append(comp[node[ok]])
    entries, e_comp = np.concatenate(ent_all), np.concatenate(ent_comp)
    if len(entries):
        pixel = (entries["row"] + 1) * _BIG + (entries["col"] + 1)
        _, uniq = np.unique(np.stack([pixel, e_comp], axis=1), axis=0, return_index=True)
        entries, e_comp = entries[uniq], e_comp[uniq]

    merged = merge_hole_stats(
        [c.stats for c in cells] + [_shared_ring_stats(entries, height_bin)],
        [comp[offsets[k] : offsets[k + 1]] for k in range(len(cells))] + [e_comp],
        n_comp,
    )
    # hole ids 1..H in raster order of first pixels
    order = np.lexsort((merged["first_col"], merged["first_row"]))
    hole_id_of_comp = np.empty(n_comp, np.int64)
    hole_id_of_comp[order] = np.arange(1, n_comp + 1)
    stats = merged.take(order)

    # layers: breadth-first distance from the parts that touch measured data
    touches = np.concatenate([c.parts["touches_data"] for c in cells])
    layer = np.zeros(n_nodes, np.int64)
    sources = np.flatnonzero(touches)
    if len(sources):
        dist = csgraph.dijkstra(graph, directed=False, indices=sources, unweighted=True, min_only=True)
        finite = np.isfinite(dist)
        layer[finite] = dist[finite].astype(np.int64) + 1

    id_len = max([len(c.cell.id) for c in cells] + [1])
    parts = np.zeros(
        n_nodes,
        [("hole_id", np.int64), ("cell", np.int64), ("cell_id", f"U{id_len}"), ("index_x", np.int64),
         ("index_y", np.int64), ("label", np.int32), ("layer", np.int64), ("area_px", np.int64),
         ("category", "U6"), ("shape", "U1")],
    )
    for k, c in enumerate(cells):
        sl = slice(offsets[k], offsets[k + 1])
        parts["cell"][sl] = k
        parts["cell_id"][sl] = c.cell.id
        parts["index_x"][sl] = c.cell.index_x
        parts["index_y"][sl] = c.cell.index_y
        parts["label"][sl] = c.parts["label"]
        parts["area_px"][sl] = c.stats["area_px"]
        parts["category"][sl] = c.parts["category"]
        parts["shape"][sl] = c.parts["shape"]
    parts["hole_id"] = hole_id_of_comp[comp]
    parts["layer"] = layer
    graph.sort_indices()

    holes = np.zeros(
        n_comp,
        [("hole_id", np.int64), ("area_px", np.int64), ("n_parts", np.int64), ("n_cells", np.int64),
         ("max_layer", np.int64), ("touches_aoi_boundary", np.bool_), ("is_small", np.bool_)],
    )
    hid = parts["hole_id"] - 1
    holes["hole_id"] = np.arange(1, n_comp + 1)
    holes["area_px"] = stats["area_px"]
    holes["n_parts"] = np.bincount(hid, minlength=n_comp)
    hole_cells = np.unique(hid * (len(cells) + 1) + parts["cell"])
    holes["n_cells"] = np.bincount(hole_cells // (len(cells) + 1), minlength=n_comp)
    max_layer = np.zeros(n_comp, np.int64)
    np.maximum.at(max_layer, hid, layer)
    holes["max_layer"] = max_layer
    holes["touches_aoi_boundary"] = stats["aoi_edge_px"] > 0
    holes["is_small"] = holes["area_px"] < min_area_px
    return HoleCatalog(
        holes=holes,
        stats=stats,
        parts=parts,
        neighbour_ptr=graph.indptr.astype(np.int64),
        neighbour_idx=graph.indices.astype(np.int64),
        connectivity=connectivity,
        min_area_px=int(min_area_px),
        settled_small_voids=sum(c.small_void_count for c in cells),
        settled_small_void_px=sum(c.small_void_px for c in cells),
    )


# --------------------------------------------------------------------------------------
# shape and cause
# --------------------------------------------------------------------------------------

SHAPE_DTYPE = np.dtype(
    [
        ("length_px", np.float64),  # sqrt(12 * larger variance): a rectangle's long side
        ("width_px", np.float64),  # sqrt(12 * smaller variance): a rectangle's short side
        ("elongation", np.float64),  # length / width
        ("fill", np.float64),  # area / (length * width): ~1 for a straight strip or a rectangle
        ("thickness_px", np.float64),  # 2 * area / edge length: the width of a long strip
    ]
)


def shape_metrics(stats: HoleStats) -> np.ndarray:
    """Size and shape of each row, from its moments (exact for merged holes).

    Parameters
    ----------
    stats : HoleStats

    Returns
    -------
    ndarray of SHAPE_DTYPE
    """
    area = stats["area_px"].astype(np.float64)
    n = np.maximum(area, 1.0)
    vr = stats["m2_rr"] / n + 1.0 / 12.0  # + the variance of a pixel's own extent
    vc = stats["m2_cc"] / n + 1.0 / 12.0
    cov = stats["m2_rc"] / n
    mid = 0.5 * (vr + vc)
    rad = np.sqrt(np.maximum(0.25 * (vr - vc) ** 2 + cov * cov, 0.0))
    out = np.zeros(len(area), SHAPE_DTYPE)
    out["length_px"] = np.sqrt(12.0 * (mid + rad))
    out["width_px"] = np.sqrt(12.0 * np.maximum(mid - rad, 1e-12))
    out["elongation"] = out["length_px"] / out["width_px"]
    out["fill"] = area / (out["length_px"] * out["width_px"])
    out["thickness_px"] = 2.0 * area / np.maximum(stats["edge_len_px"], 1)
    return out


RING_DTYPE = np.dtype(
    [
        ("mean_z", np.float64),  # mean ring height
        ("std_z", np.float64),  # standard deviation of ring heights
        ("plane_slope", np.float64),  # gradient of the least-squares plane through the ring (z per pixel)
        ("plane_residual_std", np.float64),  # scatter of ring heights about that plane
    ]
)


def ring_metrics(stats: HoleStats) -> np.ndarray:
    """Height statistics of each row's ring, from its (mergeable) co-moments.

    Parameters
    ----------
    stats : HoleStats

    Returns
    -------
    ndarray of RING_DTYPE
        NaN for rows without ring pixels.
    """
    n = stats["ring_px"].astype(np.float64)
    k = np.maximum(n, 1.0)
    rr, cc, rc = stats["ring_m2_rr"] / k, stats["ring_m2_cc"] / k, stats["ring_m2_rc"] / k
    rz, cz, zz = stats["ring_m2_rz"] / k, stats["ring_m2_cz"] / k, stats["ring_m2_zz"] / k
    det = rr * cc - rc * rc
    ok = det > 1e-9 * np.maximum(rr * cc, 1e-300)
    safe = np.where(ok, det, 1.0)
    gr = np.where(ok, (cc * rz - rc * cz) / safe, 0.0)  # dz/drow
    gc = np.where(ok, (rr * cz - rc * rz) / safe, 0.0)  # dz/dcol
    out = np.zeros(len(n), RING_DTYPE)
    out["mean_z"] = np.where(n > 0, stats["ring_mean_z"], np.nan)
    out["std_z"] = np.where(n > 0, np.sqrt(np.maximum(zz, 0.0)), np.nan)
    out["plane_slope"] = np.where(n > 0, np.hypot(gr, gc), np.nan)
    residual = zz - gr * rz - gc * cz
    out["plane_residual_std"] = np.where(n > 0, np.sqrt(np.maximum(residual, 0.0)), np.nan)
    return out


CAUSE_DTYPE = np.dtype([("cause", "U16"), ("rule", "U16")])


def classify_causes(
    stats: HoleStats,
    *,
    pixel_size: float,
    jump_threshold: float,
    occlusion_min_jump_fraction: float = 0.5,
    shadow_min_high_fraction: float = 0.15,
    shadow_min_residual_ratio: float = 0.35,
    max_terrain_slope: float = 1.0,
    max_shadow_ratio: float = 0.8,
    water_min_mask_fraction: float = 0.5,
    water_min_point_fraction: float = 0.1,
    water_flat_tolerance: float = 0.5,
    water_min_flat_fraction: float = 0.7,
    water_min_low_fraction: float = 0.5,
    strip_min_elongation: float = 4.0,
    strip_min_fill: float = 0.7,
    strip_min_length_px: float = 20.0,
    strip_min_line_share: float = 0.2,
    strip_two_line_share: float = 0.8,
    strip_min_elongation_with_lines: float = 2.0,
    low_quantile: float = 0.05,
    high_quantile: float = 0.95,
) -> np.ndarray:
    """Why each hole is there: occlusion, water, missed coverage or unknown.

    The first rule that holds wins (heights in z units; the reasoning is in
    ``docs/holes.md``). From the ring-height histogram: low level = the
    ``low_quantile`` of ring heights; step = the larger of
    (``high_quantile`` - ``low_quantile``) and the mean span ``zmax - zmin`` of
    the ring's jump pixels (a wall seen from above). From the ring's co-moments
    (:func:`ring_metrics`): the slope of the plane through the ring and the
    scatter about it.

    1. ``water`` / ``water_mask``: at least ``water_min_mask_fraction`` of the
       hole lies inside the given water mask.
    2. ``water`` / ``water_points``: at least ``water_min_point_fraction`` of the
       ring (or of the hole) holds water-class points.
    3. ``occlusion`` ([UAS] 3.2), if the step exceeds ``jump_threshold`` and the
       hole is thin enough to lie in its shadow
       (``thickness_px * pixel_size <= max_shadow_ratio * step``), and either
       ``jumps``: at least ``occlusion_min_jump_fraction`` of the ring pixels
       are height jumps; or ``shadow``: a taller neighbour stands on one side, i.e.
       at least ``shadow_min_high_fraction`` of the ring is more than
       ``jump_threshold`` above the low level, and that is no terrain slope
       (the ring's plane is steeper than ``max_terrain_slope``, or the ring
       scatters about it by at least ``shadow_min_residual_ratio *
       jump_threshold``).
    4. ``missed_coverage`` / ``strip``: a long straight strip
       (``elongation >= strip_min_elongation``, ``fill >= strip_min_fill``,
       ``length_px >= strip_min_length_px``); where flight-line ids were given,
       its ring must also come from two or more flight lines each holding at
       least ``strip_min_line_share`` of it, and the two most common lines must
       hold at least ``strip_two_line_share`` of it (a gap *between two* lines; a
       river crossing the lines is rimmed by all of them). That evidence lowers
       the elongation needed to ``strip_min_elongation_with_lines``: a gap left by
       one missed line is about a swath wide, so a short survey gives a squat strip.
    5. ``water`` / ``flat_low_rim``: at least ``water_min_flat_fraction`` of the
       ring lies within ``water_flat_tolerance`` above the low level, at least
       ``water_min_low_fraction`` of it is at the local minimum (``ring_low_px``).
    6. ``unknown`` / ``none`` (``no_ring`` when no measured pixel borders the hole).

    Parameters
    ----------
    stats : HoleStats
        Per-hole (merged) statistics; per-part statistics work too.
    pixel_size : float
        Pixel side, in z units.
    jump_threshold : float
        As used for detection (z units).

    Returns
    -------
    ndarray of CAUSE_DTYPE
        ``cause`` (one of ``CAUSES``) and ``rule`` (the rule that decided).
    """
    k = len(stats)
    out = np.zeros(k, CAUSE_DTYPE)
    if k == 0:
        return out
    shape = shape_metrics(stats)
    ring_fit = ring_metrics(stats)
    ring = stats["ring_px"].astype(np.float64)
    has_ring = ring > 0
    ring1 = np.maximum(ring, 1.0)
    area1 = np.maximum(stats["area_px"].astype(np.float64), 1.0)
    jump_frac = stats["ring_jump_px"] / ring1
    low_frac = stats["ring_low_px"] / ring1
    q_lo, q_hi = _hist_quantiles(stats, (low_quantile, high_quantile))
    hist = stats.height_hist
    centres = (hist["bin"] + 0.5) * stats.height_bin
    hrow = hist["row"]
    hcount = hist["count"].astype(np.float64)
    high = np.where(centres > q_lo[hrow] + jump_threshold, hcount, 0.0)
    flat = np.where(centres <= q_lo[hrow] + water_flat_tolerance, hcount, 0.0)
    high_frac = np.bincount(hrow, high, minlength=k) / ring1
    flat_frac = np.bincount(hrow, flat, minlength=k) / ring1
    mean_jump_span = stats["ring_jump_span_sum"] / np.maximum(stats["ring_jump_px"], 1)
    step = np.fmax(np.nan_to_num(q_hi - q_lo, nan=0.0), mean_jump_span)

    water_mask = stats["water_mask_px"] / area1 >= water_min_mask_fraction
    water_points = (has_ring & (stats["ring_water_px"] / ring1 >= water_min_point_fraction)) | (
        stats["hole_water_px"] / area1 >= water_min_point_fraction
    )
    shadow_like = (
        has_ring & (step > jump_threshold) & (shape["thickness_px"] * pixel_size <= max_shadow_ratio * step)
    )
    not_terrain = (np.nan_to_num(ring_fit["plane_slope"]) / pixel_size > max_terrain_slope) | (
        np.nan_to_num(ring_fit["plane_residual_std"]) >= shadow_min_residual_ratio * jump_threshold
    )
    occluded_jumps = shadow_like & (jump_frac >= occlusion_min_jump_fraction)
    occluded_shadow = shadow_like & (high_frac >= shadow_min_high_fraction) & not_terrain
    strip_shape = (shape["fill"] >= strip_min_fill) & (shape["length_px"] >= strip_min_length_px)
    strip = strip_shape & (shape["elongation"] >= strip_min_elongation)
    if len(stats.line_hist):
        lrow = stats.line_hist["row"]
        share = stats.line_hist["count"] / ring1[lrow]
        n_lines = np.bincount(lrow, share >= strip_min_line_share, minlength=k)
        has_lines = np.bincount(lrow, minlength=k) > 0
        # share of the ring held by each row's two most common lines
        order = np.lexsort((-share, lrow))
        ranked_rows = lrow[order]
        starts = np.r_[True, ranked_rows[1:] != ranked_rows[:-1]]
        position = np.arange(len(order))
        rank = position - np.maximum.accumulate(np.where(starts, position, 0))
        top_two = np.bincount(ranked_rows[rank < 2], share[order][rank < 2], minlength=k)
        between_two_lines = (n_lines >= 2) & (top_two >= strip_two_line_share)
        strip_with_lines = strip_shape & between_two_lines & (shape["elongation"] >= strip_min_elongation_with_lines)
        strip = np.where(has_lines, strip_with_lines, strip)
    flat_low = has_ring & (flat_frac >= water_min_flat_fraction) & (low_frac >= water_min_low_fraction)
    conditions = [water_mask, water_points, occluded_jumps, occluded_shadow, strip, flat_low]
    out["cause"] = np.select(conditions, ["water", "water", "occlusion", "occlusion", "missed_coverage", "water"],
                             default="unknown")
    out["rule"] = np.select(conditions, ["water_mask", "water_points", "jumps", "shadow", "strip", "flat_low_rim"],
                            default="none")
    out["rule"][~has_ring & (out["cause"] == "unknown")] = "no_ring"
    return out


def _hist_quantiles(stats: HoleStats, qs: Sequence[float]) -> list[np.ndarray]:
    """Per-row quantiles (bin centres) of the ring-height histogram; NaN for rows without ring."""
    k = len(stats)
    hist = stats.height_hist
    if not len(hist):
        return [np.full(k, np.nan) for _ in qs]
    rows = hist["row"]
    counts = hist["count"].astype(np.int64)
    totals = np.bincount(rows, counts, minlength=k).astype(np.int64)
    row_start = np.concatenate([[0], np.cumsum(totals)[:-1]])
    within = np.cumsum(counts) - row_start[rows]  # running count within each row
    packed = rows * _BIG + within
    centres = (hist["bin"] + 0.5) * stats.height_bin
    out = []
    for q in qs:
        need = np.maximum(np.ceil(q * totals).astype(np.int64), 1)
        i = np.minimum(np.searchsorted(packed, np.arange(k) * _BIG + need), len(hist) - 1)
        out.append(np.where(totals > 0, centres[i], np.nan))
    return out


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


def _check_same_shape(**arrays: np.ndarray) -> None:
    shapes = {name: np.shape(a) for name, a in arrays.items()}
    first = next(iter(shapes.values()))
    if any(s != first for s in shapes.values()) or len(first) != 2:
        raise ValueError(
            "arrays must be 2-dimensional and of the same shape: "
            + ", ".join(f"{k} {v}" for k, v in shapes.items())
        )
