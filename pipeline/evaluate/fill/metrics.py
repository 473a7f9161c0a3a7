"""Scoring a fill: the errors on the removed pixels (:class:`ErrorStats`, :func:`fill_errors`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass
class ErrorStats:
    """Errors of a fill on the removed pixels (filled minus reference, z units).

    ``n_px`` counts the scored pixels (filled, and measured in the reference; in the
    benchmark, the removed pixels that every method filled);
    ``n_unfilled`` the removed pixels the method left empty (not scored).
    """

    n_px: int = 0
    n_unfilled: int = 0
    sum_sq: float = 0.0
    sum_abs: float = 0.0
    sum: float = 0.0
    max_abs: float = math.nan

    @property
    def rmse(self) -> float:
        return math.sqrt(self.sum_sq / self.n_px) if self.n_px else math.nan

    @property
    def mae(self) -> float:
        return self.sum_abs / self.n_px if self.n_px else math.nan

    @property
    def bias(self) -> float:
        return self.sum / self.n_px if self.n_px else math.nan

    def __add__(self, other: ErrorStats) -> ErrorStats:
        maxima = [m for m in (self.max_abs, other.max_abs) if not math.isnan(m)]
        return ErrorStats(
            n_px=self.n_px + other.n_px,
            n_unfilled=self.n_unfilled + other.n_unfilled,
            sum_sq=self.sum_sq + other.sum_sq,
            sum_abs=self.sum_abs + other.sum_abs,
            sum=self.sum + other.sum,
            max_abs=max(maxima) if maxima else math.nan,
        )

    def as_dict(self) -> dict[str, Any]:
        return {
            "rmse": _finite(self.rmse),
            "mae": _finite(self.mae),
            "max_abs": _finite(self.max_abs),
            "bias": _finite(self.bias),
            "n_px": self.n_px,
            "n_unfilled": self.n_unfilled,
        }


def fill_errors(filled: np.ndarray, reference: np.ndarray, cut: np.ndarray) -> ErrorStats:
    """Score a filled raster on the removed pixels.

    Parameters
    ----------
    filled, reference : ndarray of shape (M, N)
        The filled raster and the reference (NaN = no data), on the same pixels.
    cut : ndarray of bool, shape (M, N)
        The removed pixels (True).

    Returns
    -------
    ErrorStats
        Over the removed pixels measured in the reference: the filled ones are
        scored, the others counted as ``n_unfilled``.

    Examples
    --------
    >>> import numpy as np
    >>> ref = np.arange(9, dtype=float).reshape(3, 3)
    >>> cut = np.zeros((3, 3), bool); cut[1, 1] = cut[1, 2] = True
    >>> filled = ref.copy(); filled[1, 1] += 0.5; filled[1, 2] = np.nan
    >>> s = fill_errors(filled, ref, cut)
    >>> (s.n_px, s.n_unfilled, s.rmse, s.bias)
    (1, 1, 0.5, 0.5)
    """
    if filled.shape != reference.shape or cut.shape != reference.shape:
        raise ValueError(f"shapes differ: filled {filled.shape}, reference {reference.shape}, cut {cut.shape}")
    truth = reference[cut].astype(np.float64)
    values = filled[cut].astype(np.float64)
    known = np.isfinite(truth)
    scored = known & np.isfinite(values)
    error = values[scored] - truth[scored]
    return ErrorStats(
        n_px=int(scored.sum()),
        n_unfilled=int((known & ~np.isfinite(values)).sum()),
        sum_sq=float(np.sum(error**2)),
        sum_abs=float(np.sum(np.abs(error))),
        sum=float(np.sum(error)),
        max_abs=float(np.max(np.abs(error))) if error.size else math.nan,
    )


def _finite(value: float) -> float | None:
    """A float for JSON: None instead of NaN or infinity."""
    return round(float(value), 4) if value is not None and math.isfinite(value) else None
