"""Why each hole is there: occlusion, water, missed coverage or unknown (docs/holes.md)."""

from __future__ import annotations

import numpy as np

from .stats import HoleStats, _hist_quantiles, ring_metrics, shape_metrics

__all__ = ["CAUSE_DTYPE", "CAUSES", "classify_causes"]

#: Causes :func:`classify_causes` can return.
CAUSES: tuple[str, ...] = ("occlusion", "water", "missed_coverage", "unknown")

CAUSE_DTYPE = np.dtype([("cause", "U16"), ("rule", "U16")])


def classify_causes(
    stats: HoleStats,
    *,
    pixel_size: float,
    jump_threshold: float,
    occlusion_min_jump_fraction: float = 0.5,
    shadow_min_high_fraction: float = 0.15,
    shadow_min_residual_ratio: float = 0.35,
    max_terrain_slope: float = 1.0,
    max_shadow_ratio: float = 0.8,
    water_min_mask_fraction: float = 0.5,
    water_min_point_fraction: float = 0.1,
    water_flat_tolerance: float = 0.5,
    water_min_flat_fraction: float = 0.7,
    water_min_low_fraction: float = 0.5,
    strip_min_elongation: float = 4.0,
    strip_min_fill: float = 0.7,
    strip_min_length_px: float = 20.0,
    strip_min_line_share: float = 0.2,
    strip_two_line_share: float = 0.8,
    strip_min_elongation_with_lines: float = 2.0,
    low_quantile: float = 0.05,
    high_quantile: float = 0.95,
) -> np.ndarray:
    """Why each hole is there: occlusion, water, missed coverage or unknown.

    The first rule that holds wins (heights in z units; the reasoning is in
    ``docs/holes.md``). From the ring-height histogram: low level = the
    ``low_quantile`` of ring heights; step = the larger of
    (``high_quantile`` - ``low_quantile``) and the mean span ``zmax - zmin`` of
    the ring's jump pixels (a wall seen from above). From the ring's co-moments
    (:func:`ring_metrics`): the slope of the plane through the ring and the
    scatter about it.

    1. ``water`` / ``water_mask``: at least ``water_min_mask_fraction`` of the
       hole lies inside the given water mask.
    2. ``water`` / ``water_points``: at least ``water_min_point_fraction`` of the
       ring (or of the hole) holds water-class points.
    3. ``occlusion`` ([UAS] 3.2), if the step exceeds ``jump_threshold`` and the
       hole is thin enough to lie in its shadow
       (``thickness_px * pixel_size <= max_shadow_ratio * step``), and either
       ``jumps``: at least ``occlusion_min_jump_fraction`` of the ring pixels
       are height jumps; or ``shadow``: a taller neighbour stands on one side, i.e.
       at least ``shadow_min_high_fraction`` of the ring is more than
       ``jump_threshold`` above the low level, and that is no terrain slope
       (the ring's plane is steeper than ``max_terrain_slope``, or the ring
       scatters about it by at least ``shadow_min_residual_ratio *
       jump_threshold``).
    4. ``missed_coverage`` / ``strip``: a long straight strip
       (``elongation >= strip_min_elongation``, ``fill >= strip_min_fill``,
       ``length_px >= strip_min_length_px``); where flight-line ids were given,
       its ring must also come from two or more flight lines each holding at
       least ``strip_min_line_share`` of it, and the two most common lines must
       hold at least ``strip_two_line_share`` of it (a gap *between two* lines; a
       river crossing the lines is rimmed by all of them). That evidence lowers
       the elongation needed to ``strip_min_elongation_with_lines``: a gap left by
       one missed line is about a swath wide, so a short survey gives a squat strip.
    5. ``water`` / ``flat_low_rim``: at least ``water_min_flat_fraction`` of the
       ring lies within ``water_flat_tolerance`` above the low level, at least
       ``water_min_low_fraction`` of it is at the local minimum (``ring_low_px``).
    6. ``unknown`` / ``none`` (``no_ring`` when no measured pixel borders the hole).

    Parameters
    ----------
    stats : HoleStats
        Per-hole (merged) statistics; per-part statistics work too.
    pixel_size : float
        Pixel side, in z units.
    jump_threshold : float
        As used for detection (z units).

    Returns
    -------
    ndarray of CAUSE_DTYPE
        ``cause`` (one of ``CAUSES``) and ``rule`` (the rule that decided).
    """
    k = len(stats)
    out = np.zeros(k, CAUSE_DTYPE)
    if k == 0:
        return out
    shape = shape_metrics(stats)
    ring_fit = ring_metrics(stats)
    ring = stats["ring_px"].astype(np.float64)
    has_ring = ring > 0
    ring1 = np.maximum(ring, 1.0)
    area1 = np.maximum(stats["area_px"].astype(np.float64), 1.0)
    jump_frac = stats["ring_jump_px"] / ring1
    low_frac = stats["ring_low_px"] / ring1
    q_lo, q_hi = _hist_quantiles(stats, (low_quantile, high_quantile))
    hist = stats.height_hist
    centres = (hist["bin"] + 0.5) * stats.height_bin
    hrow = hist["row"]
    hcount = hist["count"].astype(np.float64)
    high = np.where(centres > q_lo[hrow] + jump_threshold, hcount, 0.0)
    flat = np.where(centres <= q_lo[hrow] + water_flat_tolerance, hcount, 0.0)
    high_frac = np.bincount(hrow, high, minlength=k) / ring1
    flat_frac = np.bincount(hrow, flat, minlength=k) / ring1
    mean_jump_span = stats["ring_jump_span_sum"] / np.maximum(stats["ring_jump_px"], 1)
    step = np.fmax(np.nan_to_num(q_hi - q_lo, nan=0.0), mean_jump_span)

    water_mask = stats["water_mask_px"] / area1 >= water_min_mask_fraction
    water_points = (has_ring & (stats["ring_water_px"] / ring1 >= water_min_point_fraction)) | (
        stats["hole_water_px"] / area1 >= water_min_point_fraction
    )
    shadow_like = (
        has_ring & (step > jump_threshold) & (shape["thickness_px"] * pixel_size <= max_shadow_ratio * step)
    )
    not_terrain = (np.nan_to_num(ring_fit["plane_slope"]) / pixel_size > max_terrain_slope) | (
        np.nan_to_num(ring_fit["plane_residual_std"]) >= shadow_min_residual_ratio * jump_threshold
    )
    occluded_jumps = shadow_like & (jump_frac >= occlusion_min_jump_fraction)
    occluded_shadow = shadow_like & (high_frac >= shadow_min_high_fraction) & not_terrain
    strip_shape = (shape["fill"] >= strip_min_fill) & (shape["length_px"] >= strip_min_length_px)
    strip = strip_shape & (shape["elongation"] >= strip_min_elongation)
    if len(stats.line_hist):
        lrow = stats.line_hist["row"]
        share = stats.line_hist["count"] / ring1[lrow]
        n_lines = np.bincount(lrow, share >= strip_min_line_share, minlength=k)
        has_lines = np.bincount(lrow, minlength=k) > 0
        # share of the ring held by each row's two most common lines
        order = np.lexsort((-share, lrow))
        ranked_rows = lrow[order]
        starts = np.r_[True, ranked_rows[1:] != ranked_rows[:-1]]
        position = np.arange(len(order))
        rank = position - np.maximum.accumulate(np.where(starts, position, 0))
        top_two = np.bincount(ranked_rows[rank < 2], share[order][rank < 2], minlength=k)
        between_two_lines = (n_lines >= 2) & (top_two >= strip_two_line_share)
        strip_with_lines = strip_shape & between_two_lines & (shape["elongation"] >= strip_min_elongation_with_lines)
        strip = np.where(has_lines, strip_with_lines, strip)
    flat_low = has_ring & (flat_frac >= water_min_flat_fraction) & (low_frac >= water_min_low_fraction)
    conditions = [water_mask, water_points, occluded_jumps, occluded_shadow, strip, flat_low]
    out["cause"] = np.select(conditions, ["water", "water", "occlusion", "occlusion", "missed_coverage", "water"],
                             default="unknown")
    out["rule"] = np.select(conditions, ["water_mask", "water_points", "jumps", "shadow", "strip", "flat_low_rim"],
                            default="none")
    out["rule"][~has_ring & (out["cause"] == "unknown")] = "no_ring"
    return out
