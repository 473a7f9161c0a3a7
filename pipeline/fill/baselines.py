"""Baseline fills: ``nearest``, ``idw`` and ``flat`` (water hydro-flattening).

They are cheap, never overshoot the rim heights, and give a reference for the
accuracy of ``tin`` and ``mls``.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi
from scipy.spatial import cKDTree

from ._problem import Problem, padded_box, support_points
from ._problem import rims_by_label as _rims
from .settings import ComponentFill

__all__ = ["fill_flat", "fill_idw", "fill_nearest"]


def _none(k: int, size: int) -> ComponentFill:
    return ComponentFill(label=k, n_pixels=size, method="none", filled=False)


def fill_nearest(problem: Problem, labels: np.ndarray, out: np.ndarray) -> list[ComponentFill]:
    """Each pixel takes the height of the nearest rim pixel of its component
    (``distance_transform_edt`` indices on the component's box)."""
    sizes, slices, rims = problem.sizes(), problem.slices(), _rims(problem, labels)
    h, w = problem.labels.shape
    recs = []
    for k in labels:
        k = int(k)
        rim = rims[k]
        if len(rim) == 0:
            recs.append(_none(k, int(sizes[k])))
            continue
        box = padded_box(slices[k - 1], 1, (h, w))
        not_rim = np.ones((box[0].stop - box[0].start, box[1].stop - box[1].start), bool)
        rr, rc = np.divmod(rim, w)
        not_rim[rr - box[0].start, rc - box[1].start] = False
        idx = ndi.distance_transform_edt(not_rim, return_distances=False, return_indices=True)
        pr, pc = np.nonzero(problem.labels[box] == k)
        src_r, src_c = idx[0][pr, pc] + box[0].start, idx[1][pr, pc] + box[1].start
        out[pr + box[0].start, pc + box[1].start] = problem.heights[src_r, src_c]
        recs.append(ComponentFill(label=k, n_pixels=int(sizes[k]), method="nearest", filled=True, n_support=len(rim)))
    return recs


def fill_idw(problem: Problem, labels: np.ndarray, out: np.ndarray) -> list[ComponentFill]:
    """Inverse distance weighting, ``z = sum(z_i d_i^-p) / sum(d_i^-p)`` over the
    ``idw_k`` nearest support points (rim plus neighbours) of the component."""
    st = problem.settings
    sizes, slices, rims = problem.sizes(), problem.slices(), _rims(problem, labels)
    h, w = problem.labels.shape
    recs = []
    for k in labels:
        k = int(k)
        pts = support_points(problem, k, rims[k], st.mls_k)
        if len(pts) == 0:
            recs.append(_none(k, int(sizes[k])))
            continue
        sr, sc = np.divmod(pts, w)
        sl = slices[k - 1]
        pr, pc = np.nonzero(problem.labels[sl] == k)
        pr, pc = pr + sl[0].start, pc + sl[1].start
        kk = min(st.idw_k, len(pts))
        dist, nn = cKDTree(np.column_stack([sr, sc])).query(np.column_stack([pr, pc]), k=kk)
        dist, nn = dist.reshape(len(pr), kk), nn.reshape(len(pr), kk)
        wgt = np.maximum(dist, 1e-12) ** -st.idw_power
        out[pr, pc] = (wgt * problem.heights[sr[nn], sc[nn]]).sum(axis=1) / wgt.sum(axis=1)
        recs.append(ComponentFill(label=k, n_pixels=int(sizes[k]), method="idw", filled=True, n_support=len(pts)))
    return recs


def fill_flat(problem: Problem, labels: np.ndarray, out: np.ndarray) -> list[ComponentFill]:
    """Every pixel of a component at one level: ``flat_level`` if set, else the
    ``flat_percentile`` of the component's rim heights (see :func:`rim_level`)."""
    st = problem.settings
    sizes, slices, rims = problem.sizes(), problem.slices(), _rims(problem, labels)
    recs = []
    for k in labels:
        k = int(k)
        rim = rims[k]
        if st.flat_level is None and len(rim) == 0:
            recs.append(_none(k, int(sizes[k])))
            continue
        if st.flat_level is not None:
            level = float(st.flat_level)
        else:
            level = float(np.percentile(problem.heights.ravel()[rim], st.flat_percentile))
        sl = slices[k - 1]
        sub = out[sl]
        sub[problem.labels[sl] == k] = level
        recs.append(
            ComponentFill(label=k, n_pixels=int(sizes[k]), method="flat", filled=True, n_support=len(rim), level=level)
        )
    return recs
