"""On the client: hole parts linked across cell edges into global holes, and their layers ([OPEN] 3.2)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

from ..survey.density import void_width
from ._kernels import _BIG
from .detect import SIDES, CellHoles
from .stats import SHARED_RING_DTYPE, HoleStats, _shared_ring_stats, merge_hole_stats, shape_metrics

__all__ = ["HoleCatalog", "PartRecord", "link_holes", "mark_sampling_gaps"]

_ACROSS = {"north": (-1, 0), "east": (0, 1), "south": (1, 0), "west": (0, -1)}


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
        Small closed voids the cells settled themselves (``DetectParams.min_area_px``
        of ``detect_cell_holes``): counted here, absent from ``holes`` and ``parts``.
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


def link_holes(
    cells: Sequence[CellHoles],
    *,
    min_area_px: int = 1,
    joins: Callable[[HoleStats], tuple[np.ndarray, np.ndarray]] | None = None,
) -> HoleCatalog:
    """Link hole parts across cell edges into global holes and layer them.

    Parts of adjacent cells whose edge pixels touch (4-adjacency across the
    shared edge; with 8-connectivity also diagonally, including across cell
    corners), both inside a coverage gap or both outside, belong to one hole: the connected components of that contact graph
    (a union-find) are the global holes. Where ``joins`` is given, holes on the two sides of a
    coverage gap's edge that touch (within a cell, ``CellHoles.contacts``, or across a cell edge)
    are then joined where it says so. Layers follow [OPEN] section 3.2:
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
    joins : callable, optional
        From the statistics of the holes as linked on each side of a gap's edge: per hole, the kind
        of join it takes in from the holes touching it and the kind it joins (two int arrays, 0
        none; bool arrays are one kind): two touching holes join where one takes in what the other joins.
        Joined holes' statistics are merged again from the parts (the same whatever the cells).

    Returns
    -------
    HoleCatalog
    """
    if not cells:
        raise ValueError("link_holes needs at least one cell")
    connectivity = cells[0].connectivity
    if any(c.connectivity != connectivity for c in cells):
        raise ValueError("all cells must use the same connectivity")
    sizes = np.array([c.n_parts for c in cells], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes)])  # parts of cell k are nodes offsets[k]..offsets[k + 1]
    n_nodes = int(offsets[-1])
    edges = _EdgePixels.of(cells, offsets)
    in_gap = np.concatenate([c.stats["gap_px"] > 0 for c in cells])
    a, b = _touching_parts(edges, connectivity)
    same_side = in_gap[a] == in_gap[b]
    graph = _symmetric_graph(a[same_side], b[same_side], n_nodes)
    n_comp, comp = csgraph.connected_components(graph, directed=False)
    merged = _merged_stats(cells, offsets, comp, n_comp, edges)
    if joins is not None and (
        found := _join_across_gaps(cells, offsets, comp, a[~same_side], b[~same_side], joins, merged)
    ):
        comp, n_comp, crossing = found
        merged = _merged_stats(cells, offsets, comp, n_comp, edges)
        # joined parts of neighbouring cells are linked parts (``neighbour_idx``, layers)
        graph = _symmetric_graph(
            np.concatenate([a[same_side], a[~same_side][crossing]]),
            np.concatenate([b[same_side], b[~same_side][crossing]]),
            n_nodes,
        )
    # hole ids 1..H in raster order of first pixels
    order = np.lexsort((merged["first_col"], merged["first_row"]))
    hole_id_of_comp = np.empty(n_comp, np.int64)
    hole_id_of_comp[order] = np.arange(1, n_comp + 1)
    stats = merged.take(order)
    parts = _parts_table(cells, offsets, hole_id_of_comp[comp], _layers(cells, graph))
    graph.sort_indices()
    return HoleCatalog(
        holes=_holes_table(parts, stats, n_cells=len(cells), min_area_px=min_area_px),
        stats=stats,
        parts=parts,
        neighbour_ptr=graph.indptr.astype(np.int64),
        neighbour_idx=graph.indices.astype(np.int64),
        connectivity=connectivity,
        min_area_px=int(min_area_px),
        settled_small_voids=sum(c.small_void_count for c in cells),
        settled_small_void_px=sum(c.small_void_px for c in cells),
    )


def mark_sampling_gaps(catalog: HoleCatalog, gap_px: float | np.ndarray) -> tuple[HoleCatalog, np.ndarray]:
    """Holes no wider across than ``gap_px`` pixels (one value, or one per hole) are sampling gaps: not listed, filled like small voids.

    The width across (:func:`pipeline.survey.density.void_width`, from the area, the edge
    length and the moments) is a strip's width and a compact void's side, so a void
    wider than ``gap_px`` in both directions is never a gap. Merged
    statistics are exact, so the decision does not depend on the cells. Returns the
    catalog with those holes flagged ``is_small`` and which holes were flagged here
    (and were not small already).
    """
    holes = catalog.holes
    stats = catalog.stats
    width = void_width(stats["area_px"], stats["edge_len_px"], shape_metrics(stats)["width_px"])
    limit = np.broadcast_to(np.asarray(gap_px, np.float64), width.shape)
    thin = (limit > 0) & (width <= limit)
    gaps = thin & ~holes["is_small"]
    if not gaps.any():
        return catalog, gaps
    flagged = holes.copy()
    flagged["is_small"] |= gaps
    return replace(catalog, holes=flagged), gaps


def number_listed_first(catalog: HoleCatalog) -> tuple[HoleCatalog, np.ndarray]:
    """The holes renumbered: the listed ones 1..L in raster order of their first pixels, then the others.

    A small void inside one cell is settled by the cell and never linked; one across a cell's
    edge is linked and numbered. Numbered among all in raster order, the listed holes' ids
    followed the cells (the 211 M-point bench survey's 629 holes: 586 ids differed between
    250 m and 500 m cells). The listed holes (not small, not sampling gaps: the same whatever
    the cells, their statistics being exact) come first, each group in raster order, so their
    ids do not depend on the cells. Returns the catalog and, per new row, the row it was.
    """
    order = np.argsort(catalog.holes["is_small"], kind="stable")  # rows are in raster order: kept in each group
    if np.array_equal(order, np.arange(len(order))):
        return catalog, order
    new_id = np.empty(len(order), np.int64)
    new_id[order] = np.arange(1, len(order) + 1)
    holes = catalog.holes[order]
    holes["hole_id"] = np.arange(1, len(order) + 1)
    parts = catalog.parts.copy()
    parts["hole_id"] = new_id[parts["hole_id"] - 1]
    return replace(catalog, holes=holes, parts=parts, stats=catalog.stats.take(order)), order


@dataclass(frozen=True)
class _EdgePixels:
    """Every hole pixel on a cell edge (global row/column), its part (node) and its side."""

    rows: np.ndarray
    cols: np.ndarray
    nodes: np.ndarray
    side: np.ndarray  # index into SIDES
    keys: np.ndarray  # sorted unique packed positions, for node_at
    key_nodes: np.ndarray

    @classmethod
    def of(cls, cells: Sequence[CellHoles], offsets: np.ndarray) -> _EdgePixels:
        empty = np.zeros(0, np.int64)
        row_parts: list[np.ndarray] = [empty]
        col_parts: list[np.ndarray] = [empty]
        node_parts: list[np.ndarray] = [empty]
        side_parts: list[np.ndarray] = [empty]
        for k, c in enumerate(cells):
            for strip in c.edges:
                m = strip.labels > 0
                row_parts.append(strip.rows[m])
                col_parts.append(strip.cols[m])
                node_parts.append(offsets[k] + strip.labels[m].astype(np.int64) - 1)
                side_parts.append(np.full(int(m.sum()), SIDES.index(strip.side), np.int64))
        rows, cols, nodes, side = (np.concatenate(x) for x in (row_parts, col_parts, node_parts, side_parts))
        keys, first_index = np.unique((rows + 1) * _BIG + (cols + 1), return_index=True)
        return cls(rows, cols, nodes, side, keys, nodes[first_index])

    def node_at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """The part (node) holding the edge hole pixel at (rows, cols); -1 where none."""
        key = (rows + 1) * _BIG + (cols + 1)
        if not len(self.keys):
            return np.full(len(key), -1, np.int64)
        i = np.minimum(np.searchsorted(self.keys, key), len(self.keys) - 1)
        return np.where(self.keys[i] == key, self.key_nodes[i], -1)


def _join_across_gaps(
    cells: Sequence[CellHoles],
    offsets: np.ndarray,
    comp: np.ndarray,
    across_a: np.ndarray,
    across_b: np.ndarray,
    joins: Callable[[HoleStats], tuple[np.ndarray, np.ndarray]],
    merged: HoleStats,
) -> tuple[np.ndarray, int, np.ndarray] | None:
    """The holes once those that touch across a gap's edge and ``joins`` says so are joined; None: none are.

    ``across_a[i]``, ``across_b[i]``: parts touching across a cell edge and a gap's edge; the
    cells' own ``contacts`` are the pairs within a cell. Returns the new hole of each part, how
    many holes there are, and which of the cross-cell pairs joined.
    """
    within = [offsets[k] + c.contacts.astype(np.int64) - 1 for k, c in enumerate(cells) if len(c.contacts)]
    ca = comp[np.concatenate([across_a, *(pairs[:, 0] for pairs in within)])]
    cb = comp[np.concatenate([across_b, *(pairs[:, 1] for pairs in within)])]
    if not len(ca):
        return None
    takes_in, joining = (np.asarray(kinds, np.int64) for kinds in joins(merged))
    join = ((takes_in[ca] > 0) & (takes_in[ca] == joining[cb])) | ((joining[ca] > 0) & (joining[ca] == takes_in[cb]))
    if not join.any():
        return None
    n_joined, joined = csgraph.connected_components(_symmetric_graph(ca[join], cb[join], len(merged)), directed=False)
    return joined[comp], int(n_joined), join[: len(across_a)]


def _merged_stats(
    cells: Sequence[CellHoles], offsets: np.ndarray, comp: np.ndarray, n_comp: int, edges: _EdgePixels
) -> HoleStats:
    """The statistics of the holes ``comp`` makes of the parts (one row per component), each ring pixel once per hole."""
    entries, e_comp = _shared_ring_entries(cells, offsets, comp, edges)
    return merge_hole_stats(
        [c.stats for c in cells] + [_shared_ring_stats(entries, cells[0].stats.height_bin)],
        [comp[offsets[k] : offsets[k + 1]] for k in range(len(cells))] + [e_comp],
        n_comp,
    )


def _symmetric_graph(a: np.ndarray, b: np.ndarray, n_nodes: int) -> sparse.csr_matrix:
    """The symmetric 0/1 adjacency of ``n_nodes`` nodes with the edges ``a[i] - b[i]``."""
    graph = sparse.coo_matrix(
        (np.ones(2 * len(a), np.int8), (np.concatenate([a, b]), np.concatenate([b, a]))),
        shape=(n_nodes, n_nodes),
    ).tocsr()
    graph.sum_duplicates()
    graph.data[:] = 1
    return graph


def _touching_parts(edges: _EdgePixels, connectivity: int) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of parts (nodes ``a[i]``, ``b[i]``) whose edge pixels touch across a cell edge.

    Parts inside a coverage gap and parts outside one are among them (detection labels them
    apart within a cell); :func:`link_holes` links those on one side.
    """
    a_list, b_list = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for s, side in enumerate(SIDES):
        m = edges.side == s
        dr, dc = _ACROSS[side]
        steps = [(dr, dc)]
        if connectivity == 8:
            steps += [(dr, -1), (dr, 1)] if dr else [(-1, dc), (1, dc)]
        for sr, sc in steps:
            other = edges.node_at(edges.rows[m] + sr, edges.cols[m] + sc)
            ok = other >= 0
            a_list.append(edges.nodes[m][ok])
            b_list.append(other[ok])
    a, b = np.concatenate(a_list), np.concatenate(b_list)
    keep = a != b
    return a[keep], b[keep]


def _shared_ring_entries(
    cells: Sequence[CellHoles], offsets: np.ndarray, comp: np.ndarray, edges: _EdgePixels
) -> tuple[np.ndarray, np.ndarray]:
    """Shared ring pixels with the hole (component) on their other side, each once per hole."""
    ent_all, ent_comp = [np.zeros(0, SHARED_RING_DTYPE)], [np.zeros(0, np.int64)]
    for k, c in enumerate(cells):
        e = c.shared_ring
        if not len(e):
            continue
        node = np.where(e["label"] > 0, offsets[k] + e["label"].astype(np.int64) - 1, -1)
        foreign = e["label"] == 0
        if foreign.any():
            node[foreign] = edges.node_at(e["ref_row"][foreign], e["ref_col"][foreign])
        ok = node >= 0  # a neighbour cell that was not given leaves its side unresolved
        ent_all.append(e[ok])
        ent_comp.append(comp[node[ok]])
    entries, e_comp = np.concatenate(ent_all), np.concatenate(ent_comp)
    if len(entries):
        pixel = (entries["row"] + 1) * _BIG + (entries["col"] + 1)
        _, uniq = np.unique(np.stack([pixel, e_comp], axis=1), axis=0, return_index=True)
        entries, e_comp = entries[uniq], e_comp[uniq]
    return entries, e_comp


def _layers(cells: Sequence[CellHoles], graph: sparse.csr_matrix) -> np.ndarray:
    """[OPEN] 3.2: 1 + the breadth-first distance from the parts that touch measured data (0: none reached)."""
    touches = np.concatenate([c.parts["touches_data"] for c in cells])
    layer = np.zeros(graph.shape[0], np.int64)
    sources = np.flatnonzero(touches)
    if len(sources):
        dist = csgraph.dijkstra(graph, directed=False, indices=sources, unweighted=True, min_only=True)
        finite = np.isfinite(dist)
        layer[finite] = dist[finite].astype(np.int64) + 1
    return layer


def _parts_table(cells: Sequence[CellHoles], offsets: np.ndarray, hole_id: np.ndarray, layer: np.ndarray) -> np.ndarray:
    """One row per part of every cell (see :attr:`HoleCatalog.parts`)."""
    id_len = max([len(c.cell.id) for c in cells] + [1])
    parts = np.zeros(
        len(hole_id),
        [
            ("hole_id", np.int64),
            ("cell", np.int64),
            ("cell_id", f"U{id_len}"),
            ("index_x", np.int64),
            ("index_y", np.int64),
            ("label", np.int32),
            ("layer", np.int64),
            ("area_px", np.int64),
            ("category", "U6"),
            ("shape", "U1"),
        ],
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
    parts["hole_id"] = hole_id
    parts["layer"] = layer
    return parts


def _holes_table(parts: np.ndarray, stats: HoleStats, *, n_cells: int, min_area_px: int) -> np.ndarray:
    """One row per hole (see :attr:`HoleCatalog.holes`)."""
    n_comp = len(stats)
    holes = np.zeros(
        n_comp,
        [
            ("hole_id", np.int64),
            ("area_px", np.int64),
            ("n_parts", np.int64),
            ("n_cells", np.int64),
            ("max_layer", np.int64),
            ("touches_aoi_boundary", np.bool_),
            ("is_small", np.bool_),
        ],
    )
    hid = parts["hole_id"] - 1
    holes["hole_id"] = np.arange(1, n_comp + 1)
    holes["area_px"] = stats["area_px"]
    holes["n_parts"] = np.bincount(hid, minlength=n_comp)
    hole_cells = np.unique(hid * (n_cells + 1) + parts["cell"])
    holes["n_cells"] = np.bincount(hole_cells // (n_cells + 1), minlength=n_comp)
    max_layer = np.zeros(n_comp, np.int64)
    np.maximum.at(max_layer, hid, parts["layer"])
    holes["max_layer"] = max_layer
    holes["touches_aoi_boundary"] = stats["aoi_edge_px"] > 0
    holes["is_small"] = holes["area_px"] < min_area_px
    return holes
