"""``mls``: the improved moving least squares fill of [MLS] (orthogonal basis, no matrix inverse).

Per component ([MLS] 2.3.2):

1. Support points: the rim pixels of the hole and the ``mls_k`` nearest measured
   neighbours of each (pixel centres, x = col * pixel_size, y = -row * pixel_size, z).
2. Local frame (steps 1-2): origin O = centroid of the support points; the normal n is
   the eigenvector of the smallest eigenvalue of their covariance matrix (eq. 10); the
   U axis points from O to the support point whose projection on the plane is
   farthest, V = n x U. With ``mls_frame="horizontal"`` (default) n is replaced by the
   vertical, so S is a height above a horizontal UV plane (see FillSettings).
3. Fit (step 3, eqs. 6-9, 11): at each evaluated pixel the quadratic basis
   ``q = (1, u, v, u^2, uv, v^2)`` (coordinates centred on the pixel and divided by the
   support radius h) is made orthogonal for the weighted inner product
   ``(f, g) = sum_i w_i f(x_i) g(x_i)`` by Gram-Schmidt, so each coefficient is a
   quotient ``a_j = (phi_j, s) / (phi_j, phi_j)`` (eq. 8) and no matrix is inverted.
   The inner products come from one pass over the points (the 6x6 weighted moments);
   Gram-Schmidt then runs on the coefficient vectors. A basis function whose
   orthogonal remainder vanishes (too few or collinear points) is dropped: the order
   falls gracefully and the pixel is flagged.
4. Weight: a compact ``w(d / h)`` (Wendland C2 by default), ``h = max(radius_factor *
   D, min_radius)``, D the distance from the pixel to the nearest support point, so a
   pixel deep in a hole sees the rim on all sides. Fewer than ``mls_min_points``
   points inside h widens h in steps of 1.5 (flagged).
5. Height (step 4): the fitted surface is evaluated at every hole pixel centre: in the
   tilted frame the vertical line through the pixel centre is intersected with the
   quadratic surface (a quadratic equation; the root nearest the plane's is taken);
   in the horizontal frame that is simply z = O_z + s(u, v).

Deep inside large holes (farther than ``mls_dense_band_px`` from the support) the
surface is evaluated on a lattice and interpolated with 4x4 Lagrange weights, exact
for quadratics: the MLS surface there is as smooth as h is large.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import scipy.ndimage as ndi
from scipy.spatial import cKDTree

from ._problem import Problem, rims_by_label, support_points
from .settings import ComponentFill

__all__ = ["fill_mls", "local_frame", "mls_surface"]

WIDENED = 1
ORDER_LOWERED = 2


def fill_mls(problem: Problem, labels: np.ndarray, out: np.ndarray) -> list[ComponentFill]:
    """Fill the components ``labels`` of ``problem`` by improved MLS; write into ``out``."""
    st = problem.settings
    sizes, slices, rims = problem.sizes(), problem.slices(), rims_by_label(problem, labels)
    w = problem.labels.shape[1]
    ps = problem.pixel_size
    recs = []
    for k in labels:
        k = int(k)
        reach = int(np.ceil(st.mls_band_fraction * np.sqrt(sizes[k])))
        pts = support_points(problem, k, rims[k], st.mls_k, min_reach=reach)
        if len(pts) == 0:
            recs.append(ComponentFill(label=k, n_pixels=int(sizes[k]), method="none", filled=False))
            continue
        sr, sc = np.divmod(pts, w)
        sl = slices[k - 1]
        pr, pc = np.nonzero(problem.labels[sl] == k)
        pr, pc = pr + sl[0].start, pc + sl[1].start
        dist = _distance_to_support(pr, pc, sr, sc) * ps
        z, order, flags = mls_surface(
            (sc * ps, -sr * ps, problem.heights[sr, sc]),
            pc * ps,
            -pr * ps,
            dist,
            st,
            dense_band=st.mls_dense_band_px * ps,
            step=st.mls_lattice_step_px,
            pixel_size=ps,
            pixels=(pr, pc),
        )
        out[pr, pc] = z
        recs.append(
            ComponentFill(
                label=k,
                n_pixels=int(sizes[k]),
                method="mls",
                filled=True,
                degraded=bool(flags.any()),
                n_support=len(pts),
                order=int(order.min()),
                detail=_describe(flags, order, st.mls_order),
            )
        )
    return recs


def _describe(flags: np.ndarray, order: np.ndarray, wanted: int) -> str:
    parts = []
    if n := int(np.count_nonzero(flags & WIDENED)):
        parts.append(f"support widened for {n} px")
    if n := int(np.count_nonzero(order < wanted)):
        parts.append(f"order lowered to {int(order.min())} for {n} px")
    return "; ".join(parts)


def _distance_to_support(pr, pc, sr, sc) -> np.ndarray:
    """Distance in pixels from each (pr, pc) to the nearest (sr, sc) (EDT on the common box)."""
    r0, c0 = min(pr.min(), sr.min()), min(pc.min(), sc.min())
    shape = (max(pr.max(), sr.max()) - r0 + 1, max(pc.max(), sc.max()) - c0 + 1)
    free = np.ones(shape, bool)
    free[sr - r0, sc - c0] = False
    return ndi.distance_transform_edt(free)[pr - r0, pc - c0]


def local_frame(x: np.ndarray, y: np.ndarray, z: np.ndarray, *, tilted: bool) -> tuple[np.ndarray, np.ndarray]:
    """Origin and axes (rows U, V, S) of the local frame of points ([MLS] 2.3.2 steps 1-2).

    The normal is the eigenvector of the smallest eigenvalue of the covariance (eq. 10),
    oriented upwards; it is replaced by the vertical when ``tilted`` is False, or when
    it is within 72 degrees of horizontal (a wall-like support cannot carry a height
    field). U points to the farthest projected point, V = S x U.
    """
    pts = np.column_stack([x, y, z]).astype(np.float64)
    origin = pts.mean(axis=0)
    d = pts - origin
    normal = np.array([0.0, 0.0, 1.0])
    if tilted and len(pts) >= 3:
        _, vecs = np.linalg.eigh(d.T @ d / len(pts))
        cand = vecs[:, 0] * (1.0 if vecs[2, 0] >= 0 else -1.0)
        if cand[2] > 0.3:
            normal = cand
    proj = d - np.outer(d @ normal, normal)
    norms = np.linalg.norm(proj, axis=1)
    far = int(np.argmax(norms)) if len(norms) else 0
    if len(norms) and norms[far] > 0:
        u_axis = proj[far] / norms[far]
    else:
        u_axis = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
        u_axis /= np.linalg.norm(u_axis)
    v_axis = np.cross(normal, u_axis)
    return origin, np.vstack([u_axis, v_axis, normal])


def mls_surface(
    support, ex, ey, dist, settings, *, dense_band=0.0, step=4, pixel_size=1.0, pixels=None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Evaluate the improved-MLS surface of support points ``support = (sx, sy, sz)`` at (ex, ey).

    ``dist`` is each evaluation point's distance to the nearest support point (survey
    units). Returns heights, the order reached and the degradation flags per point.
    With ``dense_band > 0`` and ``pixels = (rows, cols)``, the integer rows and columns of
    the evaluated pixels, points farther than ``dense_band`` are interpolated from a
    lattice of spacing ``step`` px.
    """
    sx, sy, sz = support
    st = settings
    origin, axes = local_frame(sx, sy, sz, tilted=st.mls_frame == "tilted")
    d = np.column_stack([sx, sy, sz]) - origin
    su, sv, ss = d @ axes[0], d @ axes[1], d @ axes[2]
    h_min = st.mls_min_radius_px * pixel_size
    cell = _cell_size(su, sv, h_min)
    order_idx, starts, g0, nu, nv = _buckets(su, sv, cell)
    args = (
        su[order_idx],
        sv[order_idx],
        ss[order_idx],
        starts,
        g0[0],
        g0[1],
        cell,
        nu,
        nv,
        origin,
        axes,
        st.mls_order,
        st.weight_code,
        st.mls_min_points,
        st.mls_drop_tolerance,
    )
    lattice = dense_band > 0 and pixels is not None and np.any(dist > dense_band)
    n = len(ex)
    z, order, flags = np.empty(n), np.empty(n, np.int64), np.zeros(n, np.int64)
    near = dist <= dense_band if lattice else np.ones(n, bool)
    h = np.maximum(st.mls_radius_factor * dist[near], h_min)
    z[near], order[near], flags[near] = _mls_eval(ex[near], ey[near], h, *args)
    if lattice:
        far = ~near
        rows, cols = pixels
        z[far], order[far], flags[far] = _lattice_eval(rows[far], cols[far], step, pixel_size, sx, sy, st, h_min, args)
    return z, order, flags


def _lattice_eval(rows, cols, step, ps, sx, sy, st, h_min, args):
    r0, c0 = rows.min() - step, cols.min() - step
    ni = (rows.max() - r0) // step + 3
    nj = (cols.max() - c0) // step + 3
    nr, nc = np.mgrid[0:ni, 0:nj]
    nx, ny = (c0 + nc.ravel() * step) * ps, -(r0 + nr.ravel() * step) * ps
    dist, _ = cKDTree(np.column_stack([sx, sy])).query(np.column_stack([nx, ny]), k=1)
    h = np.maximum(st.mls_radius_factor * dist, h_min)
    zn, on, fn = _mls_eval(nx, ny, h, *args)
    zn, on, fn = zn.reshape(ni, nj), on.reshape(ni, nj), fn.reshape(ni, nj)
    gi, gj = (rows - r0) / step, (cols - c0) / step
    i0, j0 = np.floor(gi).astype(np.int64), np.floor(gj).astype(np.int64)
    wi, wj = _lagrange4(gi - i0), _lagrange4(gj - j0)
    z = np.zeros(len(rows))
    order = np.full(len(rows), 2, np.int64)
    flags = np.zeros(len(rows), np.int64)
    for a in range(4):
        for b in range(4):
            ii, jj = i0 - 1 + a, j0 - 1 + b
            z += wi[a] * wj[b] * zn[ii, jj]
            order = np.minimum(order, on[ii, jj])
            flags |= fn[ii, jj]
    return z, order, flags


def _lagrange4(t: np.ndarray) -> tuple[np.ndarray, ...]:
    """Cubic Lagrange weights of the nodes -1, 0, 1, 2 at offset t in [0, 1)."""
    return (
        -t * (t - 1) * (t - 2) / 6,
        (t + 1) * (t - 1) * (t - 2) / 2,
        -(t + 1) * t * (t - 2) / 2,
        (t + 1) * t * (t - 1) / 6,
    )


def _cell_size(su, sv, h_min) -> float:
    area = max((su.max() - su.min()) * (sv.max() - sv.min()), h_min * h_min)
    return float(max(h_min, 4.0 * math.sqrt(area / len(su))))


def _buckets(su, sv, cell):
    u0, v0 = su.min(), sv.min()
    iu = ((su - u0) / cell).astype(np.int64)
    iv = ((sv - v0) / cell).astype(np.int64)
    nu, nv = int(iu.max()) + 1, int(iv.max()) + 1
    key = iu * nv + iv
    order_idx = np.argsort(key, kind="stable")
    starts = np.searchsorted(key[order_idx], np.arange(nu * nv + 1))
    return order_idx, starts, (u0, v0), nu, nv


@numba.njit(cache=True, nogil=True)
def _weight(r, kind):
    if r >= 1.0:
        return 0.0
    if kind == 0:  # Wendland C2
        return (1.0 - r) ** 4 * (4.0 * r + 1.0)
    if kind == 1:  # cubic B-spline
        if r < 0.5:
            return 2.0 / 3.0 - 4.0 * r * r + 4.0 * r * r * r
        return 4.0 / 3.0 * (1.0 - r) ** 3
    e = math.exp(-6.25)  # Gaussian, sigma 0.4 h, shifted to 0 at r = 1
    return (math.exp(-((r / 0.4) ** 2)) - e) / (1.0 - e)


@numba.njit(cache=True, nogil=True)
def _mls_eval(
    ex, ey, h0, su, sv, ss, starts, u_min, v_min, cell, nu, nv, origin, axes, max_order, wkind, min_points, drop_tol
):
    n = len(ex)
    z = np.empty(n)
    order_out = np.empty(n, np.int64)
    flags = np.zeros(n, np.int64)
    nterm = (1, 3, 6)[max_order]
    gram = np.empty((6, 6))
    rhs = np.empty(6)
    q = np.empty(6)
    coef = np.empty((6, 6))
    norms = np.empty(6)
    kept = np.empty(6, np.bool_)
    poly = np.empty(6)
    nx, ny, nz = axes[2, 0], axes[2, 1], axes[2, 2]
    hmax = 2.0 * (cell * max(nu, nv) + 1.0)
    for p in range(n):
        dx, dy = ex[p] - origin[0], ey[p] - origin[1]
        t0 = -(dx * nx + dy * ny) / nz  # vertical line meets the UV plane at z = O_z + t0
        u0 = dx * axes[0, 0] + dy * axes[0, 1] + t0 * axes[0, 2]
        v0 = dx * axes[1, 0] + dy * axes[1, 1] + t0 * axes[1, 2]
        h = h0[p]
        while True:
            gram[:, :] = 0.0
            rhs[:] = 0.0
            count = 0
            ia, ib = max(int((u0 - h - u_min) / cell), 0), min(int((u0 + h - u_min) / cell), nu - 1)
            ja, jb = max(int((v0 - h - v_min) / cell), 0), min(int((v0 + h - v_min) / cell), nv - 1)
            for i in range(ia, ib + 1):
                for j in range(ja, jb + 1):
                    cidx = i * nv + j
                    for m in range(starts[cidx], starts[cidx + 1]):
                        xi, eta = (su[m] - u0) / h, (sv[m] - v0) / h
                        wgt = _weight(math.sqrt(xi * xi + eta * eta), wkind)
                        if wgt <= 0.0:
                            continue
                        count += 1
                        q[0], q[1], q[2], q[3], q[4], q[5] = 1.0, xi, eta, xi * xi, xi * eta, eta * eta
                        for a in range(nterm):
                            rhs[a] += wgt * q[a] * ss[m]
                            for b in range(a, nterm):
                                gram[a, b] += wgt * q[a] * q[b]
            if count >= min_points or h > hmax:
                break
            h *= 1.5
            flags[p] |= 1
        for a in range(nterm):
            for b in range(a):
                gram[a, b] = gram[b, a]
        # Gram-Schmidt in coefficient space: phi_j = sum_k coef[j, k] q_k ([MLS] eq. 9)
        poly[:] = 0.0
        for j in range(nterm):
            coef[j, :] = 0.0
            coef[j, j] = 1.0
            kept[j] = False
            for _ in range(2):  # re-orthogonalise once for round-off
                for i in range(j):
                    if not kept[i]:
                        continue
                    proj = 0.0
                    for a in range(nterm):
                        for b in range(nterm):
                            proj += coef[j, a] * gram[a, b] * coef[i, b]
                    proj /= norms[i]
                    for a in range(nterm):
                        coef[j, a] -= proj * coef[i, a]
            nrm = 0.0
            for a in range(nterm):
                for b in range(nterm):
                    nrm += coef[j, a] * gram[a, b] * coef[j, b]
            if not nrm > drop_tol * gram[j, j] or gram[j, j] <= 0.0:
                continue
            kept[j] = True
            norms[j] = nrm
            num = 0.0
            for a in range(nterm):
                num += coef[j, a] * rhs[a]
            aj = num / nrm  # [MLS] eq. 8: a_j = (phi_j, s) / (phi_j, phi_j)
            for a in range(nterm):
                poly[a] += aj * coef[j, a]
        reached = -1
        if nterm >= 1 and kept[0]:
            reached = 0
            if nterm >= 3 and kept[1] and kept[2]:
                reached = 1
                if nterm == 6 and kept[3] and kept[4] and kept[5]:
                    reached = 2
        order_out[p] = max(reached, 0)
        if reached < max_order:
            flags[p] |= 2
        # height where the vertical line meets s = f(u, v) (tau measured from t0)
        a_ = axes[0, 2] / h
        b_ = axes[1, 2] / h
        quad = poly[3] * a_ * a_ + poly[4] * a_ * b_ + poly[5] * b_ * b_
        lin = poly[1] * a_ + poly[2] * b_ - nz
        tau = -poly[0] / lin
        disc = lin * lin - 4.0 * quad * poly[0]
        if quad != 0.0 and disc >= 0.0:
            qq = -0.5 * (lin + math.copysign(math.sqrt(disc), lin))
            r1 = qq / quad
            r2 = poly[0] / qq if qq != 0.0 else r1
            tau = r1 if abs(r1 - tau) < abs(r2 - tau) else r2
        z[p] = origin[2] + t0 + tau
    return z, order_out, flags
