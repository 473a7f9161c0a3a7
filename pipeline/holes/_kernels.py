"""Compiled passes over a cell's pixels and small sparse-table helpers (pure, numba).

:func:`hole_pixel_sums` and :func:`ring_sums` run the two numba kernels of
:func:`pipeline.holes.detect.detect_cell_holes` (one raster-order pass over the
hole pixels, one over the ring pixels) and return their results as named tuples.
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np

_BIG = np.int64(1) << 40  # row stride of packed (row, column) keys; grids are far smaller


_NO_LINE = -1


class HolePixelSums(NamedTuple):
    """Per-label results of the pass over the hole pixels (index = label; 0 is unused).

    Rows and columns are core coordinates (0 = the core's first row/column).
    """

    area: np.ndarray  # hole pixels
    row_sum: np.ndarray  # sums of row, column, row^2, column^2, row x column
    col_sum: np.ndarray
    row_sq_sum: np.ndarray
    col_sq_sum: np.ndarray
    row_col_sum: np.ndarray
    row_min: np.ndarray  # bounding box
    row_max: np.ndarray
    col_min: np.ndarray
    col_max: np.ndarray
    first_col: np.ndarray  # column of the first pixel in raster order (its row is row_min)
    edge_len: np.ndarray  # pixel edges to non-hole pixels (4-neighbours)
    aoi_edge: np.ndarray  # pixels next to the outside of the AOI/grid (by the connectivity)
    near_data: np.ndarray  # pixels 4-adjacent to measured data
    water: np.ndarray  # pixels with water-class points
    in_mask: np.ndarray  # pixels inside the water mask


def hole_pixel_sums(
    labels: np.ndarray,
    n: int,
    hole_w: np.ndarray,
    aoi_w: np.ndarray,
    data_w: np.ndarray,
    water_w: np.ndarray | None,
    mask_w: np.ndarray | None,
    R: int,
    *,
    eight: bool,
) -> HolePixelSums:
    """One raster-order pass over the hole pixels of the core (see :func:`_hole_pixel_kernel`).

    ``labels`` covers the core; the ``*_w`` arrays cover the core grown by ``R``
    pixels. ``water_w`` (bool: the pixel holds water-class points) and ``mask_w``
    may be None.
    """
    no_flag = np.zeros((1, 1), bool)
    return HolePixelSums(*_hole_pixel_kernel(
        labels, n, hole_w, aoi_w, data_w,
        no_flag if water_w is None else water_w, no_flag if mask_w is None else mask_w, R, eight,
        water_w is not None, mask_w is not None,
    ))  # fmt: skip


@numba.njit(cache=True, nogil=True)
def _hole_pixel_kernel(
    labels, n, hole_w, aoi_w, data_w, water_w, mask_w, R, eight, has_water, has_mask
):  # pragma: no cover - compiled
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
    return (area, sr, sc, srr, scc, src, rmin, rmax, cmin, cmax, fcol, edge_len, aoi_edge, near_data, wet, masked)


class RingSums(NamedTuple):
    """Results of the pass over the ring pixels of the core (see :func:`_ring_kernel`).

    Per-label arrays have index = label (0 unused). ``hist_*`` has one row per (ring
    pixel, part) counted in this cell, for the histograms; ``shared_*`` one row per
    ring pixel and hole key left to the client. Rows and columns are core coordinates.
    """

    ring_px: np.ndarray  # ring pixels per part
    ring_jump: np.ndarray  # ... that are height jumps
    ring_low: np.ndarray  # ... at the local minimum
    ring_water: np.ndarray  # ... with water-class points
    sums: np.ndarray  # (9, n + 1): sums of r, c, z, rr, cc, rc, rz, cz, zz
    span_sum: np.ndarray  # sum of zmax - zmin over the jump pixels
    z_min: np.ndarray  # lowest and highest ring height
    z_max: np.ndarray
    hist_part: np.ndarray
    hist_z: np.ndarray
    hist_line: np.ndarray  # -1: unknown
    shared_row: np.ndarray
    shared_col: np.ndarray
    shared_key: np.ndarray  # > 0: a part label of this cell; < 0: -1 - flat index of a work-window hole pixel
    shared_z: np.ndarray
    shared_span: np.ndarray
    shared_flags: np.ndarray  # 1 jump, 2 low, 4 water
    shared_line: np.ndarray


def ring_sums(
    labels: np.ndarray,
    hole_w: np.ndarray,
    data_w: np.ndarray,
    zmax_w: np.ndarray,
    zmin_w: np.ndarray,
    row_min: np.ndarray,
    water_w: np.ndarray | None,
    line_w: np.ndarray | None,
    settled: np.ndarray,
    R: int,
    *,
    local_radius_px: int,
    jump_threshold: float,
    low_tolerance: float,
) -> RingSums:
    """The ring pixels of the core (see :func:`_ring_kernel`); ``water_w`` and ``line_w`` may be None.

    The Python face of a numba kernel: it only forwards to :func:`_ring_kernel` (numba
    takes no records), so its parameters are the kernel's, one each, and it is exempt
    from the ten-parameter rule.
    """
    return RingSums(*_ring_kernel(
        labels, hole_w, data_w, zmax_w, zmin_w, row_min,
        np.zeros((1, 1), bool) if water_w is None else water_w,
        np.zeros((1, 1), np.int64) if line_w is None else line_w,
        settled, R, local_radius_px, float(jump_threshold), float(low_tolerance), len(settled) - 1,
        water_w is not None, line_w is not None,
    ))  # fmt: skip


@numba.njit(cache=True, nogil=True)
def _ring_kernel(
    labels,
    hole_w,
    data_w,
    zmax_w,
    zmin_w,
    row_min,
    water_w,
    line_w,
    settled,
    R,
    lr,
    jump_threshold,
    low_tolerance,
    n,
    has_water,
    has_line,
):  # pragma: no cover - compiled
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
    return (
        ring_px,
        ring_jump,
        ring_low,
        ring_water,
        sums,
        span_sum,
        z_lo,
        z_hi,
        s_part,
        s_z,
        s_line,
        sh_r,
        sh_c,
        sh_key,
        sh_z,
        sh_span,
        sh_flags,
        sh_line,
    )


def _key_fields(dtype: np.dtype) -> tuple[str, str]:
    """Names of the first two fields of a (row, key, count) table's structured dtype."""
    names = dtype.names
    if names is None or len(names) < 2:
        raise TypeError(f"a (row, key, count) table needs a structured dtype, got {dtype}")
    return names[0], names[1]


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
    row_name, key_name = _key_fields(dtype)
    out[row_name], key = np.divmod(packed[starts], span)
    out[key_name] = key + k0
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
    row_name, key_name = _key_fields(dtype)
    out[row_name] = rows[starts]
    out[key_name] = keys[starts]
    out["count"] = np.add.reduceat(counts, starts)
    return out


def _perimeter_flat(h: int, w: int) -> np.ndarray:
    """Flat indices of a (h, w) array's outermost pixels, once each, in cyclic order."""
    top = np.arange(w)
    right = np.arange(1, h) * w + (w - 1)
    bottom = (h - 1) * w + np.arange(w - 2, -1, -1) if h > 1 else np.zeros(0, np.int64)
    left = np.arange(h - 2, 0, -1) * w if w > 1 else np.zeros(0, np.int64)
    return np.concatenate([top, right, bottom, left]).astype(np.int64)
