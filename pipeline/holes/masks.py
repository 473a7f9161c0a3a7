"""Full-raster masks: hole pixels, height jumps ([UAS] eq. 1), vertical holes ([UAS] eq. 2)."""

from __future__ import annotations

import numpy as np

__all__ = ["height_jumps", "hole_mask", "vertical_holes"]


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


def _check_same_shape(**arrays: np.ndarray) -> None:
    shapes = {name: np.shape(a) for name, a in arrays.items()}
    first = next(iter(shapes.values()))
    if any(s != first for s in shapes.values()) or len(first) != 2:
        raise ValueError(
            "arrays must be 2-dimensional and of the same shape: " + ", ".join(f"{k} {v}" for k, v in shapes.items())
        )
