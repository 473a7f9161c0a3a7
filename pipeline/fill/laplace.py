"""``tin``: Laplacian fairing of the hole with its rim held fixed ([OPEN] 3.3).

The open-hole paper triangulates a hole, refines the triangles to the density of the
surrounding mesh, moves the new vertices to an inverse-distance average of their
neighbours and finally fairs them with the umbrella operator

    U(v) = -v + sum_i w_i v_i / sum_i w_i                         ([OPEN] eq. 2)

or its second-order form U^2(v) = -U(v) + sum_i w_i U(v_i) / sum_i w_i (eq. 4), the
boundary being fixed. On a raster the refined mesh *is* the pixel lattice of the hole
(triangulated along one diagonal, the cotangent weights of eq. 3 are exactly the
4-neighbour weights 1/4), and the faired positions are the solution of U(v) = 0
(harmonic) or U^2(v) = 0 (biharmonic) at every hole pixel. We solve that sparse
linear system directly instead of sweeping: the start positions (the linear TIN and
the inverse-distance adjustment of the paper) only matter to an iterative smoother,
and the direct solution is the limit those sweeps converge to.

Second order is set up as the minimum of ``sum (L z)^2`` over the hole pixels *and*
its rim pixels (the thin-plate energy), whose normal equations are ``L^T L z = ...``:
symmetric positive definite, exact for every quadratic surface, and each
component's energy only involves that component, so components stay independent
even when they share a rim pixel.

Components without a single rim pixel cannot be solved and are left to the caller.
All components of one call go into one block-diagonal system (one factorization).
Components larger than ``tin_direct_max_px`` are solved on a reduced (Galerkin)
system: full resolution within ``tin_band_px`` of the component's edge, and inside
a bilinear interpolation of a lattice of spacing ``tin_lattice_px``. The reduced
solution is the energy-best surface of that form; it reproduces planes exactly and
differs from the full solution by far less than the fill's own error (a few cm on
100 000-pixel holes of rough terrain, see docs/filling.md).
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi
from scipy import sparse
from scipy.sparse.linalg import spsolve

from ._problem import SHIFTS, Problem, rim_pairs
from .settings import ComponentFill

__all__ = ["fill_tin"]


def fill_tin(problem: Problem, labels: np.ndarray, out: np.ndarray) -> list[ComponentFill]:
    """Fill the components ``labels`` of ``problem`` by fairing; write heights into ``out``.

    Returns one record per component (unsolvable ones with ``filled=False``).
    """
    st = problem.settings
    wanted = np.zeros(problem.n_labels + 1, bool)
    wanted[labels] = True
    rim_l, rim_i = rim_pairs(problem, wanted)
    n_rim = np.bincount(rim_l, minlength=problem.n_labels + 1)
    solvable = wanted & (n_rim > 0)
    sizes = problem.sizes()
    records = []
    large = [int(k) for k in labels if solvable[k] and sizes[k] > st.tin_direct_max_px]
    if solvable.any():
        rows, cols, label = problem.labelled
        chosen = solvable[label]
        rows, cols = rows[chosen], cols[chosen]
        keep = solvable[rim_l]
        values = _solve(problem, rows, cols, rim_l[keep], rim_i[keep], st.tin_order, large)
        out[rows, cols] = values
    for k in labels:
        k = int(k)
        detail = ""
        if k in large:
            detail = f"reduced system: full resolution within {st.tin_band_px} px of the rim, {st.tin_lattice_px} px lattice inside"
        records.append(
            ComponentFill(
                label=k,
                n_pixels=int(sizes[k]),
                method="tin" if solvable[k] else "none",
                filled=bool(solvable[k]),
                n_support=int(n_rim[k]),
                order=st.tin_order if solvable[k] else 0,
                detail=detail,
            )
        )
    return records


def _solve(problem: Problem, rows, cols, rim_l, rim_i, order: int, large: list[int]) -> np.ndarray:
    lab, sup, z = problem.labels, problem.support, problem.heights
    h, w = lab.shape
    n = len(rows)
    index = np.full(h * w, -1, np.int64)
    index[rows * w + cols] = np.arange(n)
    a_mat, b_vec = _umbrella_rows(rows, cols, lab[rows, cols], lab, sup, z, index, np.arange(n))
    if order == 1:
        system, rhs = a_mat, b_vec
        m_mat = None
    else:
        rr, rc = np.divmod(rim_i, w)
        r_mat, r_known = _umbrella_rows(rr, rc, rim_l.astype(lab.dtype), lab, sup, z, index, None)
        m_mat = sparse.vstack([a_mat, r_mat]).tocsr()
        m0 = np.concatenate([-b_vec, r_known])  # the known part of L z, per row
        system, rhs = None, -(m_mat.T @ m0)
    p_mat = _reduction(problem, rows, cols, large) if large else None
    if p_mat is not None:
        if m_mat is not None:
            mp = (m_mat @ p_mat).tocsr()
            system, rhs = (mp.T @ mp), p_mat.T @ rhs
        else:
            system, rhs = (p_mat.T @ (system @ p_mat)), p_mat.T @ rhs
    elif m_mat is not None:
        system = m_mat.T @ m_mat
    sol = spsolve(sparse.csc_matrix(system), rhs, permc_spec="MMD_AT_PLUS_A")
    return p_mat @ sol if p_mat is not None else sol


def _umbrella_rows(rows, cols, row_label, lab, sup, z, index, diag_col):
    """Rows of the graph Laplacian ``L z`` at the pixels (rows, cols).

    Neighbours count when they are support pixels (known, moved to the right-hand
    side) or pixels of the row's own component (unknowns); all others (barriers,
    non-support, other components) are cut from the graph. ``diag_col`` is the unknown
    index of the pixel itself, or None for a known (rim) pixel, whose own height then
    goes to the known part. Returns (sparse unknown part, known part) where
    ``L z = unknown @ u + known`` for rim rows and ``L z = unknown @ u - known`` for hole rows.
    """
    h, w = lab.shape
    n = len(rows)
    deg = np.zeros(n)
    known = np.zeros(n)
    ri, ci, vi = [], [], []
    for dr, dc in SHIFTS:
        r, c = rows + dr, cols + dc
        inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        r, c = np.where(inside, r, 0), np.where(inside, c, 0)
        same = inside & (lab[r, c] == row_label)
        known_nb = inside & sup[r, c]
        deg += same | known_nb
        known += np.where(known_nb, z[r, c], 0.0)
        ri.append(np.nonzero(same)[0])
        ci.append(index[r[same] * w + c[same]])
        vi.append(np.full(int(same.sum()), -1.0))
    if diag_col is not None:
        ri.append(np.arange(n))
        ci.append(diag_col)
        vi.append(deg)
        rhs = known  # deg*u - sum(unknown nb) = sum(known nb)
    else:
        rhs = deg * z[rows, cols] - known  # known part of the rim pixel's Laplacian
    mat = sparse.csr_matrix(
        (np.concatenate(vi), (np.concatenate(ri), np.concatenate(ci))), shape=(n, int(index.max()) + 1)
    )
    return mat, rhs


def _reduction(problem: Problem, rows, cols, large: list[int]) -> sparse.csr_matrix:
    """Prolongation ``P``: reduced unknowns -> pixel unknowns (identity outside the
    interiors of the large components, bilinear lattice interpolation inside)."""
    st = problem.settings
    f, band = st.tin_lattice_px, st.tin_band_px
    lab = problem.labels
    n = len(rows)
    pix_lab = lab[rows, cols]
    interior = np.zeros(n, bool)
    node_cols = np.zeros((n, 4), np.int64)
    node_w = np.zeros((n, 4))
    next_col = 0
    slices = problem.slices()
    for k in large:
        sl = slices[k - 1]
        comp = np.pad(lab[sl] == k, 1)
        dist = ndi.distance_transform_cdt(comp, metric="chessboard")[1:-1, 1:-1]
        sel = np.nonzero(pix_lab == k)[0]
        lr, lc = rows[sel] - sl[0].start, cols[sel] - sl[1].start
        inner = dist[lr, lc] > band
        sel, lr, lc = sel[inner], lr[inner], lc[inner]
        gi, gj = lr / f, lc / f
        i0, j0 = np.floor(gi).astype(np.int64), np.floor(gj).astype(np.int64)
        ncol = int(j0.max(initial=0)) + 2
        # only whole lattice cells go on the lattice: the bilinear functions of whole
        # cells are linearly independent (a lone pixel in a cell would make two
        # lattice nodes indistinguishable and the system singular)
        cell = i0 * ncol + j0
        whole = np.bincount(cell)[cell] == f * f
        sel, i0, j0, gi, gj = sel[whole], i0[whole], j0[whole], gi[whole], gj[whole]
        fi, fj = gi - i0, gj - j0
        for m, (di, dj, wgt) in enumerate(
            ((0, 0, (1 - fi) * (1 - fj)), (1, 0, fi * (1 - fj)), (0, 1, (1 - fi) * fj), (1, 1, fi * fj))
        ):
            node_cols[sel, m] = next_col + (i0 + di) * ncol + (j0 + dj)
            node_w[sel, m] = wgt
        interior[sel] = True
        next_col += (int(i0.max(initial=0)) + 2) * ncol
    n_free = int((~interior).sum())
    free_col = np.full(n, -1, np.int64)
    free_col[~interior] = np.arange(n_free)
    ii = np.nonzero(interior)[0]
    r_idx = np.concatenate([np.nonzero(~interior)[0], np.repeat(ii, 4)])
    c_idx = np.concatenate([free_col[~interior], n_free + node_cols[ii].ravel()])
    v = np.concatenate([np.ones(n_free), node_w[ii].ravel()])
    nonzero = v != 0.0
    r_idx, c_idx, v = r_idx[nonzero], c_idx[nonzero], v[nonzero]
    used, c_idx = np.unique(c_idx, return_inverse=True)
    return sparse.csr_matrix((v, (r_idx, c_idx)), shape=(n, len(used)))
