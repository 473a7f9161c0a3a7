"""Why each hole is there: occlusion, water, missed coverage or unknown (docs/holes.md, "Causes").

:func:`classify_causes` is a function of the merged per-hole statistics and a
:class:`CauseRules` holding every threshold. The rules are data: the thresholds
are the ``[causes]`` configuration keys (plus the pixel size and the height-jump
threshold), put into survey units once by :func:`pipeline.parameters.cause_rules`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ._kernels import _BIG
from .stats import HoleStats, _hist_quantiles, ring_metrics, shape_metrics

__all__ = ["CAUSE_DTYPE", "CAUSES", "RULES", "CauseRules", "classify_causes", "strip_joins"]

#: Causes :func:`classify_causes` can return.
CAUSES: tuple[str, ...] = ("occlusion", "water", "missed_coverage", "no_return", "covered", "unknown")

#: The rules in the order they are tried (the first that holds wins): (rule, cause).
#: A hole no rule claims is ``unknown`` / ``none`` (``no_ring`` without any measured neighbour).
RULES: tuple[tuple[str, str], ...] = (
    ("water_mask", "water"),
    ("covered", "covered"),
    ("water_ring", "water"),
    ("missing_tile", "missed_coverage"),
    ("coverage_gap", "missed_coverage"),
    ("water_points", "water"),
    ("line_of_sight", "occlusion"),
    ("water_edge", "water"),
    ("jumps", "occlusion"),
    ("shadow", "occlusion"),
    ("strip", "missed_coverage"),
    ("level_rim", "water"),
    ("flat_low_rim", "water"),
    ("river_rim", "water"),
    ("seen", "no_return"),
)
#: The rules that judge a hole from its rim alone, where the sensor's lines of sight are not known.
RIM_ONLY_RULES = ("jumps", "shadow", "strip", "flat_low_rim")
#: The water rules that read the rim's heights alone (no water returns): off on heights above the ground.
RIM_WATER_RULES = ("level_rim", "river_rim", "flat_low_rim")

#: A hole whose ring holds water-class returns on at least this share of its pixels is water before
#: any coverage gap or missing tile: it is enclosed by measured water more than by anything else, and
#: water is level, so the pulses that returned from the water beyond it reached its height there (a
#: delivery leaves out the tiles from which nothing came back: the middle of a lake wider than a tile). Where a swath's
#: modelled edge runs through a lake (heights assumed, sides cut by a small extract's edge), the
#: returns around the void say more than the model (``ign_crop2_water``: a 36 m2 void at a 50 m
#: extract's edge, class 9 all round, the ring within 0.17 m of the water's level, was a coverage gap).
WATER_RING_SHARE = 0.5

CAUSE_DTYPE = np.dtype([("cause", "U16"), ("rule", "U16")])


@dataclass(frozen=True)
class CauseRules:
    """Every threshold of :func:`classify_causes`, in survey units.

    Build it with :func:`pipeline.parameters.cause_rules` (a run) or
    :func:`pipeline.parameters.default_cause_rules` (the ``[causes]`` defaults, for
    kernels used on their own). Heights are in z units, lengths in pixels, shares
    are fractions; ``configs/default.toml`` documents each key and
    ``pipeline.parameters.CONFIG_KEYS`` names the key behind each field.

    Attributes
    ----------
    pixel_size : float
        Pixel side in z units (``grid.resolution_m`` in the survey's units).
    jump_threshold : float
        Height-jump threshold in z units, as used for detection (``holes.jump_threshold_m``).
    water_min_mask_fraction, water_min_point_fraction
        ``water_mask`` / ``water_points`` rules.
    covered_min_fraction
        ``covered`` rule.
    gap_min_fraction
        ``coverage_gap`` and ``missing_tile`` rules.
    occlusion_min_jump_fraction
        ``jumps`` rule.
    occlusion_min_blocked_fraction
        ``line_of_sight`` rule.
    shadow_min_high_fraction, shadow_min_residual_ratio, max_terrain_slope
        ``shadow`` rule.
    max_shadow_ratio
        Both occlusion rules: ``thickness_px * pixel_size <= max_shadow_ratio * step``.
    strip_min_fill, strip_min_length_px, strip_min_elongation, strip_min_elongation_with_lines,
    strip_min_line_share, strip_two_line_share
        ``strip`` rule.
    water_flat_tolerance, water_min_flat_fraction, water_min_low_fraction
        ``flat_low_rim`` rule (``water_flat_tolerance`` in z units).
    water_max_below_fraction
        ``level_rim`` rule (with ``water_flat_tolerance`` and ``water_min_flat_fraction``).
    water_max_slope, river_min_elongation
        ``river_rim`` rule (with ``water_flat_tolerance``); ``water_max_slope`` is rise over run.
    water_min_rim_area_m2, pixel_area_m2
        The rim-only water rules (``level_rim``, ``river_rim``, ``flat_low_rim``) need a hole of at
        least this area: a small void with a flat rim is as often a dropout on dark or
        wet ground as water.
    low_quantile, high_quantile
        Quantiles of the ring heights taken as its low and high level.
    """

    pixel_size: float
    jump_threshold: float
    water_min_mask_fraction: float
    covered_min_fraction: float
    gap_min_fraction: float
    water_min_point_fraction: float
    occlusion_min_jump_fraction: float
    occlusion_min_blocked_fraction: float
    shadow_min_high_fraction: float
    shadow_min_residual_ratio: float
    max_terrain_slope: float
    max_shadow_ratio: float
    strip_min_fill: float
    strip_min_length_px: float
    strip_min_elongation: float
    strip_min_elongation_with_lines: float
    strip_min_line_share: float
    strip_two_line_share: float
    water_flat_tolerance: float
    water_min_flat_fraction: float
    water_min_low_fraction: float
    water_max_below_fraction: float
    water_max_slope: float
    river_min_elongation: float
    water_min_rim_area_m2: float
    low_quantile: float
    high_quantile: float
    pixel_area_m2: float = 1.0


def classify_causes(
    stats: HoleStats,
    rules: CauseRules,
    *,
    bands_known: bool = False,
    sight_known: bool = False,
    heights_assumed: bool = False,
    above_ground: bool = False,
) -> np.ndarray:
    """Why each hole is there: the first rule of ``RULES`` that holds wins.

    Each rule, its condition and the physical evidence behind it are in ``docs/holes.md``
    ("Causes", and "The sensor's geometry" for ``line_of_sight``, ``water_edge`` and ``seen``).
    From the ring-height histogram: low level = the ``low_quantile`` of ring heights; step =
    the larger of (``high_quantile`` - ``low_quantile``) and the mean span ``zmax - zmin`` of
    the ring's jump pixels (a wall seen from above). From the ring's co-moments
    (:func:`ring_metrics`): the slope of the plane through the ring and the scatter about it.
    A hole no rule claims is ``unknown`` / ``none`` (``no_ring`` without a measured neighbour).

    Parameters
    ----------
    stats : HoleStats
        Per-hole (merged) statistics; per-part statistics work too.
    rules : CauseRules
        The thresholds, in survey units.
    bands_known : bool
        Whether two or more flight lines' bands were found (:func:`pipeline.holes.coverage.line_bands`).
    sight_known : bool
        Whether the flight lines' trajectories account for the survey (``gap_px`` is then "outside
        every swath", ``blocked_px`` and ``seen_px`` are measured): the causes come from the
        sensor's geometry (``line_of_sight``, ``seen``) and the rim-only rules (``RIM_ONLY_RULES``)
        are off; ``river_rim`` and ``level_rim`` then ask for an elongated hole (a river's or a
        canal's course: a level rim alone is no evidence of water).
    heights_assumed : bool
        Whether the sensor's heights are assumed (``nominal``: single returns and no scan angles)
        from a field of view nothing measured (the survey's shadows did not settle it,
        :func:`pipeline.stages.sensor_geometry.fov_from_shadows`): the swaths stand, but the lines of
        sight lean as the assumed field of view makes them, and the rim's occlusion rules (``jumps``,
        ``shadow``) speak too.
    above_ground : bool
        Whether the heights are above the ground (a normalised survey,
        :class:`pipeline.survey.ground_level.GroundLevel`): the ground is z = 0 everywhere, so
        a level, low or planar rim is bare ground, not a water surface, and the rim-only water
        rules (``RIM_WATER_RULES``) are off; water is known from its returns (``water_points``,
        ``water_ring``, ``water_edge``) or a water mask.

    Returns
    -------
    ndarray of CAUSE_DTYPE
        ``cause`` (one of ``CAUSES``) and ``rule`` (the rule that decided).
    """
    out = np.zeros(len(stats), CAUSE_DTYPE)
    if len(stats) == 0:
        return out
    ring = _RingEvidence.of(stats, rules)
    holds = _rule_conditions(stats, ring, rules)
    if bands_known:
        holds["strip"] = np.zeros(len(stats), bool)
    if sight_known:
        for rule in RIM_ONLY_RULES:
            if not (heights_assumed and rule in ("jumps", "shadow")):
                holds[rule] = np.zeros(len(stats), bool)
        elongated = shape_metrics(stats)["elongation"] >= rules.river_min_elongation
        holds["river_rim"] &= elongated
        holds["level_rim"] &= elongated
        # water returns beside a void the lines could not see into are no evidence that it is water:
        # a tree's shadow on a lake's shore has the lake's edge in its ring (water_ring still speaks)
        holds["water_points"] &= ~holds["line_of_sight"]
    else:
        holds["line_of_sight"] = holds["water_edge"] = holds["seen"] = np.zeros(len(stats), bool)
    if above_ground:
        for rule in RIM_WATER_RULES:
            holds[rule] = np.zeros(len(stats), bool)
    conditions = [holds[rule] for rule, _ in RULES]
    out["cause"] = np.select(conditions, [cause for _, cause in RULES], default="unknown")
    out["rule"] = np.select(conditions, [rule for rule, _ in RULES], default="none")
    out["rule"][~ring.has_ring & (out["cause"] == "unknown")] = "no_ring"
    return out


class _RingEvidence(NamedTuple):
    """What the ring of each hole shows, as shares of its pixels."""

    has_ring: np.ndarray
    size: np.ndarray  # ring pixels, at least 1 (a divisor)
    jump_frac: np.ndarray  # height-jump pixels
    low_frac: np.ndarray  # pixels at the local minimum
    high_frac: np.ndarray  # pixels more than jump_threshold above the low level
    flat_frac: np.ndarray  # pixels within water_flat_tolerance above the low level
    level_frac: np.ndarray  # pixels in the most populated height window water_flat_tolerance wide
    below_frac: np.ndarray  # pixels below that window
    step: np.ndarray  # height of the step beside the hole

    @classmethod
    def of(cls, stats: HoleStats, rules: CauseRules) -> _RingEvidence:
        k = len(stats)
        ring = stats["ring_px"].astype(np.float64)
        ring1 = np.maximum(ring, 1.0)
        q_lo, q_hi = _hist_quantiles(stats, (rules.low_quantile, rules.high_quantile))
        hist = stats.height_hist
        centres = (hist["bin"] + 0.5) * stats.height_bin
        hrow = hist["row"]
        hcount = hist["count"].astype(np.float64)
        high = np.where(centres > q_lo[hrow] + rules.jump_threshold, hcount, 0.0)
        flat = np.where(centres <= q_lo[hrow] + rules.water_flat_tolerance, hcount, 0.0)
        mean_jump_span = stats["ring_jump_span_sum"] / np.maximum(stats["ring_jump_px"], 1)
        level, below = _level_window(stats, rules.water_flat_tolerance)
        return cls(
            has_ring=ring > 0,
            size=ring1,
            jump_frac=stats["ring_jump_px"] / ring1,
            low_frac=stats["ring_low_px"] / ring1,
            high_frac=np.bincount(hrow, high, minlength=k) / ring1,
            flat_frac=np.bincount(hrow, flat, minlength=k) / ring1,
            level_frac=level / ring1,
            below_frac=below / ring1,
            step=np.fmax(np.nan_to_num(q_hi - q_lo, nan=0.0), mean_jump_span),
        )


def _rule_conditions(stats: HoleStats, ring: _RingEvidence, rules: CauseRules) -> dict[str, np.ndarray]:
    """Whether each rule of ``RULES`` holds, per hole."""
    shape = shape_metrics(stats)
    ring_fit = ring_metrics(stats)
    area1 = np.maximum(stats["area_px"].astype(np.float64), 1.0)
    shadow_like = (
        ring.has_ring
        & (ring.step > rules.jump_threshold)
        & (shape["thickness_px"] * rules.pixel_size <= rules.max_shadow_ratio * ring.step)
    )
    not_terrain = (np.nan_to_num(ring_fit["plane_slope"]) / rules.pixel_size > rules.max_terrain_slope) | (
        np.nan_to_num(ring_fit["plane_residual_std"]) >= rules.shadow_min_residual_ratio * rules.jump_threshold
    )
    large_enough_for_rim_water = stats["area_px"] * rules.pixel_area_m2 >= rules.water_min_rim_area_m2
    strip_shape = (shape["fill"] >= rules.strip_min_fill) & (shape["length_px"] >= rules.strip_min_length_px)
    in_swath = stats["swath_px"] / area1 >= 0.5  # the lines flew over it: not a gap in coverage
    in_gap = stats["gap_px"] / area1 >= rules.gap_min_fraction  # no line flew over it
    strip = strip_shape & ~in_swath & (shape["elongation"] >= rules.strip_min_elongation)
    if len(stats.line_hist):
        has_lines, between_two_lines = _between_two_lines(stats, ring.size, rules)
        strip_with_lines = (
            strip_shape & ~in_swath & between_two_lines & (shape["elongation"] >= rules.strip_min_elongation_with_lines)
        )
        strip = np.where(has_lines, strip_with_lines, strip)
    swept = np.maximum((stats["blocked_px"] + stats["seen_px"]).astype(np.float64), 1.0)
    return {
        "line_of_sight": (stats["blocked_px"] > 0)
        & (stats["blocked_px"] / swept >= rules.occlusion_min_blocked_fraction),
        "seen": stats["seen_px"] > 0,
        # seen unobstructed, nothing came back, and water was measured at its edge
        "water_edge": (stats["seen_px"] > 0) & (stats["ring_water_px"] > 0),
        "water_mask": stats["water_mask_px"] / area1 >= rules.water_min_mask_fraction,
        # a ground-only model's void under the points it left out: a building, trees
        "covered": stats["covered_px"] / area1 >= rules.covered_min_fraction,
        "missing_tile": stats["missing_tile_px"] / area1 >= rules.gap_min_fraction,
        "coverage_gap": stats["gap_px"] / area1 >= rules.gap_min_fraction,
        "water_ring": ring.has_ring & (stats["ring_water_px"] / ring.size >= WATER_RING_SHARE),
        "water_points": (ring.has_ring & (stats["ring_water_px"] / ring.size >= rules.water_min_point_fraction))
        | (stats["hole_water_px"] / area1 >= rules.water_min_point_fraction),
        "jumps": shadow_like & (ring.jump_frac >= rules.occlusion_min_jump_fraction),
        "shadow": shadow_like & (ring.high_frac >= rules.shadow_min_high_fraction) & not_terrain,
        "strip": strip,
        "level_rim": ring.has_ring
        & large_enough_for_rim_water
        & in_swath
        & (ring.level_frac >= rules.water_min_flat_fraction)
        & (ring.below_frac <= rules.water_max_below_fraction),
        "river_rim": ring.has_ring & large_enough_for_rim_water & ~in_gap & _river_rim(shape, ring_fit, rules),
        "flat_low_rim": ring.has_ring
        & large_enough_for_rim_water
        & (ring.flat_frac >= rules.water_min_flat_fraction)
        & (ring.low_frac >= rules.water_min_low_fraction),
    }


def _river_rim(shape: np.ndarray, ring_fit: np.ndarray, rules: CauseRules) -> np.ndarray:
    """Whether each ring is a water surface's rim that may fall along the hole: a lake or a river reach.

    Heights in z units, slopes in z per pixel (:func:`ring_metrics`); the falls over
    the hole's width and length are compared with ``water_flat_tolerance``.
    """
    tolerance = rules.water_flat_tolerance
    along = np.nan_to_num(ring_fit["along_slope"], nan=np.inf)
    across = np.nan_to_num(ring_fit["cross_slope"], nan=np.inf)
    falls_along = along * shape["length_px"] > tolerance
    return (
        (np.nan_to_num(ring_fit["plane_residual_std"], nan=np.inf) <= tolerance)
        & (across * shape["width_px"] <= tolerance)
        & (along / rules.pixel_size <= rules.water_max_slope)
        & (~falls_along | (shape["elongation"] >= rules.river_min_elongation))
    )


def _between_two_lines(stats: HoleStats, ring_size: np.ndarray, rules: CauseRules) -> tuple[np.ndarray, np.ndarray]:
    """Per hole: whether flight-line ids are known, and whether its ring comes from two lines.

    Two or more lines each hold at least ``strip_min_line_share`` of the ring, and
    the two most common lines hold at least ``strip_two_line_share`` of it.
    """
    k = len(stats)
    lrow = stats.line_hist["row"]
    share = stats.line_hist["count"] / ring_size[lrow]
    n_lines = np.bincount(lrow, share >= rules.strip_min_line_share, minlength=k)
    has_lines = np.bincount(lrow, minlength=k) > 0
    # share of the ring held by each row's two most common lines
    order = np.lexsort((-share, lrow))
    ranked_rows = lrow[order]
    starts = np.r_[True, ranked_rows[1:] != ranked_rows[:-1]]
    position = np.arange(len(order))
    rank = position - np.maximum.accumulate(np.where(starts, position, 0))
    top_two = np.bincount(ranked_rows[rank < 2], share[order][rank < 2], minlength=k)
    return has_lines, (n_lines >= 2) & (top_two >= rules.strip_two_line_share)


def _level_window(stats: HoleStats, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Per row: ring pixels in the most populated height window ``tolerance`` wide, and below it.

    The window spans ``max(1, round(tolerance / height_bin))`` histogram bins; ties go
    to the lowest window. A shore is a contour line: most of the ring in one window.
    """
    k = len(stats)
    hist = stats.height_hist
    level, below = np.zeros(k), np.zeros(k)
    if not len(hist):
        return level, below
    width = max(1, round(tolerance / stats.height_bin))
    rows, bins = hist["row"], hist["bin"]
    counts = hist["count"].astype(np.float64)
    cum = np.concatenate([[0.0], np.cumsum(counts)])
    row_start = np.searchsorted(rows, rows)  # histogram sorted by (row, bin)
    key = rows * _BIG + bins
    end = np.searchsorted(key, rows * _BIG + bins + width)  # first entry past the window
    inside = cum[end] - cum[np.arange(len(hist))]
    under = cum[np.arange(len(hist))] - cum[row_start]
    order = np.lexsort((np.arange(len(hist)), -inside, rows))  # best window first within each row
    first = order[np.r_[True, rows[order][1:] != rows[order][:-1]]]
    level[rows[first]] = inside[first]
    below[rows[first]] = under[first]
    return level, below


#: Kinds of join across a gap's edge (:func:`strip_joins`): a missed strip and the voids of its missed line ...
STRIP_JOIN = 1
#: ... and one water body's voids on both sides (a lake's tiles left out of a delivery, its voids in the others).
WATER_JOIN = 2


def strip_joins(causes: np.ndarray, *, heights_assumed: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Which holes take in the voids touching them across a coverage gap's edge, and which voids join.

    A missed strip (``missed_coverage`` by ``coverage_gap``: outside every flown line's swath)
    takes in the occlusions that open onto it: the shadows cast toward the strip by what
    stands at a flown line's swath edge. The line that was not flown is one whose sensor
    positions should have seen into them (they lie across the strip from the shadows' flown
    line), so they are voids of the missed line too and its re-flight covers them. And where the
    swath's edge runs through a void, the side each pixel lies on depends on the unknown height
    of its first surface: the edge at a roof's or a crown's height and at the ground's lie
    ``(z_top - z_ground) tan(angle)`` apart (3-5 m at a swath edge's 20-27 degrees under 10 m
    trees or houses), so the void split there is slivers whose cause is a toss of a coin. The
    joined void's cause follows the rules on its merged evidence (``coverage_gap`` where at
    least ``gap_min_fraction`` of it lies outside every swath): a wide shadow with a sliver of
    strip stays an occlusion. Water and voids seen unobstructed (``no_return``) stay apart: a
    river crossing a missed strip is two holes; except where the sensor's heights are assumed
    (single returns, no scan angles): a line's modelled edge is then only as good as its
    assumed field of view and the half-width of other lines, and "seen" beside a missed strip
    is the same coin toss (a simulated Delft scan flown with a 54 degree scanner, assumed 40:
    five voids of 4-12 m2 between the data's edge and the modelled one, each seen).

    Water takes in water: a gap-side void that is water (``water_ring``: the middle of a lake
    wider than a tile, whose tiles the delivery left out because nothing came back) and the
    water voids it touches in the delivered tiles are one water body, filled at one level read
    from all of its edge (``bench_water.py --lake-m 300``: the left-out tiles' level was read
    from 11 water-return pixels, 2.4 cm low, the rest of the lake from 431).

    Parameters
    ----------
    causes : ndarray of CAUSE_DTYPE
        :func:`classify_causes` of the holes as linked on each side of the gap's edge.
    heights_assumed : bool
        As for :func:`classify_causes`: voids seen unobstructed join too.

    Returns
    -------
    takes_in, joins : ndarray of int8
        Per hole, the kind of join (``STRIP_JOIN``, ``WATER_JOIN``; 0 none) it takes in and the
        kind it joins (the ``joins`` of :func:`pipeline.holes.link_holes`).
    """
    water = causes["cause"] == "water"
    joins = np.where(causes["cause"] == "occlusion", STRIP_JOIN, 0).astype(np.int8)
    if heights_assumed:
        joins[causes["rule"] == "seen"] = STRIP_JOIN
    joins[water] = WATER_JOIN
    takes_in = np.where(causes["rule"] == "coverage_gap", STRIP_JOIN, 0).astype(np.int8)
    takes_in[water] = WATER_JOIN
    return takes_in, joins
