"""Mergeable statistics of hole parts and holes: the table layouts and their algebra.

Each cell measures its parts into :class:`HoleStats` rows
(:func:`pipeline.holes.detect.detect_cell_holes`); the client merges the rows of the
parts of one hole exactly (:func:`merge_hole_stats`, used by
:func:`pipeline.holes.link.link_holes`), whatever the cell size; shape and ring
metrics are derived from the merged rows. This module defines the layouts the
detection fills, so it comes before ``detect`` in the package's data flow.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ._kernels import _BIG, _coo_counts, _sum_coo

__all__ = [
    "HEIGHT_HIST_DTYPE",
    "LINE_HIST_DTYPE",
    "RING_DTYPE",
    "SHAPE_DTYPE",
    "SHARED_RING_DTYPE",
    "STATS_COLUMNS",
    "HoleStats",
    "merge_hole_stats",
    "ring_metrics",
    "shape_metrics",
]

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
    "gap_px": (np.int64, "sum", "hole pixels inside a coverage gap (no flight line's swath)"),
    "swath_px": (np.int64, "sum", "hole pixels inside a flight line's swath"),
    "missing_tile_px": (np.int64, "sum", "hole pixels inside the square of a missing tile (counted in gap_px too)"),
    "blocked_px": (np.int64, "sum", "hole pixels swept by a swath but hidden from every line that swept them"),
    "seen_px": (np.int64, "sum", "hole pixels some line saw unobstructed (it returned nothing)"),
    "covered_px": (np.int64, "sum", "hole pixels under points the class filter left out (a ground-only model)"),
    "touches_data": (np.bool_, "any", "a measured pixel is 4-adjacent somewhere"),
}


#: Groups of columns merged as centroids and co-moments (Chan, Golub and LeVeque):
#: (weight column, mean columns, {co-moment column: (mean index, mean index)}).
_MOMENT_GROUPS = (
    ("area_px", ("mean_row", "mean_col"), {"m2_rr": (0, 0), "m2_cc": (1, 1), "m2_rc": (0, 1)}),
    (
        "ring_px",
        ("ring_mean_row", "ring_mean_col", "ring_mean_z"),
        {
            "ring_m2_rr": (0, 0),
            "ring_m2_cc": (1, 1),
            "ring_m2_rc": (0, 1),
            "ring_m2_rz": (0, 2),
            "ring_m2_cz": (1, 2),
            "ring_m2_zz": (2, 2),
        },
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
        return cls(
            _empty_columns(rows), np.zeros(0, HEIGHT_HIST_DTYPE), np.zeros(0, LINE_HIST_DTYPE), float(height_bin)
        )

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


def _empty_columns(rows: int) -> dict[str, np.ndarray]:
    big = np.iinfo(np.int64).max
    neutral = {
        "row_min": big,
        "col_min": big,
        "first_row": big,
        "first_col": big,
        "row_max": -1,
        "col_max": -1,
        "ring_z_min": np.inf,
        "ring_z_max": -np.inf,
    }
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
    hh = [
        (np.asarray(gr, np.int64)[s.height_hist["row"]], s.height_hist["bin"], s.height_hist["count"])
        for s, gr in zip(stats, groups)
    ]
    lh = [
        (np.asarray(gr, np.int64)[s.line_hist["row"]], s.line_hist["line"], s.line_hist["count"])
        for s, gr in zip(stats, groups)
    ]
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
        ("along_slope", np.float64),  # |gradient| along the hole's long axis (z per pixel): a river's fall
        ("cross_slope", np.float64),  # |gradient| across it: banks at one height have none
    ]
)


def ring_metrics(stats: HoleStats) -> np.ndarray:
    """Height statistics of each row's ring, from its (mergeable) co-moments.

    The least-squares plane through the ring heights gives the slope and the scatter;
    its gradient split along and across the hole's long axis (from the hole's own
    moments) tells a river, whose rim falls along its course and matches across its
    banks, from a slope the hole merely lies on.

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
    # the hole's long axis: the major eigenvector of its pixel covariance, at angle phi from the row axis
    phi = 0.5 * np.arctan2(2.0 * stats["m2_rc"], stats["m2_rr"] - stats["m2_cc"])
    out["along_slope"] = np.where(n > 0, np.abs(gr * np.cos(phi) + gc * np.sin(phi)), np.nan)
    out["cross_slope"] = np.where(n > 0, np.abs(gc * np.cos(phi) - gr * np.sin(phi)), np.nan)
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
