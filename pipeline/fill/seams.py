"""Seam smoothing between independently filled cells ([OPEN] 3.4)."""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi

__all__ = ["smooth_seams"]


def smooth_seams(
    heights: np.ndarray,
    filled: np.ndarray,
    seam: np.ndarray,
    *,
    gamma: float = 0.5,
    iterations: int = 10,
    width_px: float = 3.0,
) -> np.ndarray:
    """Laplacian smoothing of filled pixels near seam lines ([OPEN] 3.4, eqs. 5-6).

    Each pass moves every smoothed pixel towards the mean of its finite 4-neighbours,
    ``p_new = p + gamma * delta_p``, ``delta_p = sum_i (s_i - p) / m`` (all pixels
    updated together, from the previous pass's heights).

    Parameters
    ----------
    heights : ndarray of shape (M, N)
        Heights after filling. Not modified.
    filled : ndarray of bool, shape (M, N)
        Pixels that were filled (only they may change; measured pixels never do).
    seam : ndarray of bool, shape (M, N)
        Seam pixels (e.g. the first row/column of a cell on each side of the edge).
    gamma : float
        Step, ``0 < gamma < 1``. Default 0.5.
    iterations : int
        Number of passes. Default 10.
    width_px : float
        Filled pixels within this distance (pixels) of the seam are smoothed. Default 3.

    Returns
    -------
    ndarray of shape (M, N)
        Smoothed heights, same dtype as a float input (float64 otherwise).
    """
    heights = np.asarray(heights)
    filled, seam = np.asarray(filled, bool), np.asarray(seam, bool)
    if filled.shape != heights.shape or seam.shape != heights.shape:
        raise ValueError("`heights`, `filled` and `seam` must have the same shape")
    if not 0 < gamma < 1:
        raise ValueError(f"`gamma` must be in (0, 1), got {gamma!r}")
    if iterations < 0 or width_px < 0:
        raise ValueError("`iterations` and `width_px` must be >= 0")
    z = heights.astype(np.float64, copy=True)
    if seam.any():
        near = ndi.distance_transform_edt(~seam) <= width_px
    else:
        near = np.zeros_like(seam)
    move = near & filled & np.isfinite(z)
    rows, cols = np.nonzero(move)
    if len(rows):
        pad = np.pad(z, 1, constant_values=np.nan)
        for _ in range(iterations):
            total = np.zeros(len(rows))
            count = np.zeros(len(rows))
            for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                nb = pad[rows + 1 + dr, cols + 1 + dc]
                ok = np.isfinite(nb)
                total += np.where(ok, nb, 0.0)
                count += ok
            p = pad[rows + 1, cols + 1]
            delta = np.where(count > 0, total / np.maximum(count, 1) - p, 0.0)
            pad[rows + 1, cols + 1] = p + gamma * delta
        z = pad[1:-1, 1:-1]
    dtype = heights.dtype if np.issubdtype(heights.dtype, np.floating) else np.float64
    return z.astype(dtype, copy=False)
