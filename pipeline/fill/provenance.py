"""Provenance of filled heights: how far from data, and how wrong they are likely to be."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import scipy.ndimage as ndi

from .region import fill_region
from .settings import FillSettings

__all__ = ["fill_distance", "leave_boundary_out_error"]


def fill_distance(measured: np.ndarray, *, pixel_size: float = 1.0) -> np.ndarray:
    """Distance from every pixel to the nearest measured pixel, in survey units.

    Parameters
    ----------
    measured : ndarray of bool, shape (M, N)
        True where the height was measured (not filled).
    pixel_size : float
        Pixel size in survey units.

    Returns
    -------
    ndarray of float32, shape (M, N)
        0 on measured pixels; ``inf`` everywhere when nothing was measured.
    """
    measured = np.asarray(measured, bool)
    if not (np.isfinite(pixel_size) and pixel_size > 0):
        raise ValueError(f"`pixel_size` must be a finite number > 0, got {pixel_size!r}")
    if not measured.any():
        return np.full(measured.shape, np.inf, np.float32)
    return (ndi.distance_transform_edt(~measured) * pixel_size).astype(np.float32)


def leave_boundary_out_error(
    heights: np.ndarray,
    region: np.ndarray,
    *,
    method: str = "auto",
    pixel_size: float = 1.0,
    settings: FillSettings | None = None,
    support: np.ndarray | None = None,
    barriers: np.ndarray | None = None,
    labels: np.ndarray | None = None,
) -> np.ndarray:
    """Leave-boundary-out RMSE of each component's fill (height units).

    A quarter of the rim (``holdout_every``-th of ``holdout_sectors`` angular sectors
    around the component's centroid) is withheld, the enlarged hole is refilled with
    the same method, and the refilled heights are compared with the withheld ones. It
    measures the error near the rim, so it is a lower bound for the middle of a big
    hole; it ranks methods and flags bad fills. Same arguments as :func:`fill_region`.

    Returns
    -------
    ndarray of float64, shape (n_components + 1,)
        RMSE per label (NaN for index 0 and for components that could not be tested).
    """
    settings = replace(FillSettings() if settings is None else settings, estimate_error=True)
    outcome = fill_region(
        heights,
        region,
        method=method,
        pixel_size=pixel_size,
        settings=settings,
        support=support,
        barriers=barriers,
        labels=labels,
    )
    errors = np.full(int(outcome.labels.max(initial=0)) + 1, np.nan)
    for rec in outcome.components:
        errors[rec.label] = rec.error_estimate
    return errors
