"""Vertical holes of a cell core as records: groups of [UAS] eq. 2 pixels, their heights and outlines (pure).

:func:`~pipeline.holes.masks.vertical_holes` marks the pixels whose points span more
voxels than they occupy (a wall that was not lit); :func:`vertical_hole_records`
groups them (8-connected, at least ``min_px`` pixels) into the rows of the
``vertical_holes`` layer.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi
import shapely
from affine import Affine

from ..rasterize import PixelStatistics
from .outlines import label_polygons

__all__ = ["vertical_hole_records"]


def vertical_hole_records(
    mask: np.ndarray, core: PixelStatistics, transform: Affine, *, voxel_height: float, min_px: int
) -> list[dict]:
    """One record per connected group of vertical-hole pixels (UAS eq. 2) in a cell core.

    Parameters
    ----------
    mask : ndarray of bool, shape (M, N)
        The vertical-hole pixels of the core (:func:`~pipeline.holes.masks.vertical_holes`).
    core : PixelStatistics
        The core's statistics (``zmax``, ``zmin``, ``voxels``), the shape of ``mask``.
    transform : Affine
        The core's affine transform: the outlines are in its coordinates.
    voxel_height : float
        Voxel height in z units.
    min_px : int
        Groups of fewer pixels are left out.

    Returns
    -------
    list of dict
        ``pixels``, ``max_height_range`` (z units), ``missing_voxels``, ``top`` (the
        highest point) and ``wkb`` (the outline), one per group in label order.
    """
    labels, n = ndi.label(mask, structure=np.ones((3, 3), bool))
    if n == 0:
        return []
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    keep = sizes >= max(1, min_px)
    keep[0] = False
    labels = np.where(keep[labels], np.cumsum(keep)[labels], 0)
    n = int(keep.sum())
    if n == 0:
        return []
    mask = labels > 0
    span = core.zmax.astype(np.float64) - core.zmin
    expected = np.floor(span / voxel_height)
    missing = np.where(mask, np.maximum(expected - core.voxels, 0), 0)
    # per-group sums and maxima over the group pixels only (ndimage.maximum sorts the whole array)
    group = labels[mask] - 1
    pixels = np.bincount(group, minlength=n)
    missing_voxels = np.bincount(group, weights=missing[mask], minlength=n)
    max_span = np.zeros(n)
    np.maximum.at(max_span, group, span[mask])
    top = np.full(n, -np.inf)
    np.maximum.at(top, group, core.zmax[mask].astype(np.float64))
    polygons = label_polygons(labels, transform, connectivity=8)
    found = [i for i in range(n) if (i + 1) in polygons]
    # every outline's WKB in one call (a call per outline: 0.13 s of a 42 M-point survey's 9,000)
    outlines = shapely.to_wkb(np.array([polygons[i + 1] for i in found], dtype=object)) if found else []
    return [
        {
            "pixels": int(pixels[i]),
            "max_height_range": float(max_span[i]),
            "missing_voxels": int(missing_voxels[i]),
            "top": float(top[i]),
            "wkb": wkb,
        }
        for i, wkb in zip(found, outlines, strict=True)
    ]
