"""Shores of synthetic water bodies: ground blended down to a bank just above the water (pure)."""

from __future__ import annotations

import numpy as np

from .spec import RIVER_BANK_HEIGHT_M


def blend_to_shore(ground: np.ndarray, distance: np.ndarray, level: np.ndarray, bank_width: float) -> np.ndarray:
    """Ground blended down to ``level + RIVER_BANK_HEIGHT_M`` at a shore ``distance`` metres away.

    A smoothstep over ``bank_width``: the ground is untouched farther out and at the
    bank top on the shore, so the shore is a contour line just above the water.
    """
    t = np.clip(distance / bank_width, 0.0, 1.0)
    smooth = t * t * (3.0 - 2.0 * t)
    bank_top = level + RIVER_BANK_HEIGHT_M
    return bank_top + (ground - bank_top) * smooth
