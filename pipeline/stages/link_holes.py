"""Linking, on the client: the cells' hole parts become the survey's holes, each with a cause.

Parts are linked across cell edges into global holes and layered outer to inner
(:func:`pipeline.holes.link_holes`); every hole gets a cause
(:func:`pipeline.holes.classify_causes`). The result is kept under the work
folder: the fill stage schedules its cells by the layers and fills each hole by
its cause, and a resumed run reads it instead of linking again.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np

from ..config import Config
from ..holes import (
    HoleCatalog,
    classify_causes,
    link_holes,
    mark_sampling_gaps,
    number_listed_first,
    ring_metrics,
    strip_joins,
)
from ..holes.coverage import line_bands
from ..holes.flight_lines import line_azimuths, strip_azimuths
from ..io.intermediate import save_object
from ..parameters import HoleParams, cause_rules
from ..plan import SurveyPlan
from ..survey.footprint_density import sampling_gap_px
from ..survey.ground_level import GroundLevel
from .bin_tiles import BIN_TILES
from .detect_holes import COVERAGE, DETECT_HOLES, DetectResult, finds_holes
from .sensor_geometry import SensorGeometry
from .stage import RunState, Stage


@dataclass(frozen=True)
class HoleSet:
    """The survey's holes: the linked catalog with a cause and rim statistics per hole.

    ``causes`` and ``ring`` rows are aligned with ``catalog.holes``.
    """

    catalog: HoleCatalog
    causes: np.ndarray
    ring: np.ndarray
    azimuth_deg: np.ndarray  # float64: for a missed strip, the direction of the flight lines beside it; else NaN
    sampling_gaps: int = 0  # holes no thicker than HoleParams.sampling_gap_px (not listed, filled as small voids)
    sampling_gap_px: int = 0  # their pixels
    geometry: SensorGeometry | None = None  # the flight lines and swaths (None: the sensor's geometry was off)


def link_cells(
    detected: list[DetectResult],
    plan: SurveyPlan,
    config: Config,
    params: HoleParams,
    line_moments: np.ndarray,
    geometry: SensorGeometry | None = None,
    *,
    above_ground: bool = False,
) -> HoleSet:
    """Gather: link the detected parts of every cell (in plan order) and classify the holes.

    ``line_moments``: the survey's flight-line pixel moments (gathered from stage 2),
    for the direction of the flight lines beside a missed strip where their trajectories
    are not known; ``geometry``: the flight lines' trajectories and swaths, whose lines of
    sight decide the causes where it is complete; ``above_ground``: the heights are above the
    ground (no water from the rim's heights alone, :func:`pipeline.holes.classify_causes`).
    """
    rules = cause_rules(
        config,
        pixel_size_m=plan.grid.resolution * plan.survey.horizontal_unit_m,
        vertical_unit_m=plan.survey.vertical_unit_m,
    )
    sight_known = geometry is not None and geometry.complete
    heights_assumed = sight_known and geometry is not None and geometry.heights_assumed
    classify = partial(
        classify_causes,
        rules=rules,
        bands_known=len(line_bands(line_moments)) >= 2,
        sight_known=sight_known,
        # the rim's occlusion rules speak where nothing measured the assumed heights (the shadows did not)
        heights_assumed=heights_assumed and geometry is not None and geometry.rim_rules,
        above_ground=above_ground,
    )
    catalog = link_holes(
        [d.cell_holes for d in detected],
        min_area_px=params.min_area_px,
        joins=lambda stats: strip_joins(classify(stats), heights_assumed=heights_assumed),
    )
    gap_px = sampling_gap_px(plan.survey, plan.grid, catalog.stats, params.sampling_gap_px)
    catalog, gaps = mark_sampling_gaps(catalog, gap_px)
    causes = classify(catalog.stats)
    if not plan.aoi_given:
        catalog, steps = mark_sampling_gaps(
            catalog, np.where(footprint_steps(catalog, causes, plan.block_px), np.inf, 0)
        )
        gaps |= steps
    catalog, order = number_listed_first(catalog)
    causes, gaps = causes[order], gaps[order]
    if sight_known:
        assert geometry is not None
        # to 0.01 degree: the fit's last digits follow the order the reads summed in (a split COPC file)
        directions = {line.line: round(line.azimuth_deg % 180.0, 2) for line in geometry.lines}
    else:
        directions = line_azimuths(line_moments)
    azimuths = strip_azimuths(catalog.stats.line_hist, causes["cause"] == "missed_coverage", directions)
    return HoleSet(
        catalog=catalog,
        causes=causes,
        ring=ring_metrics(catalog.stats),
        azimuth_deg=azimuths,
        sampling_gaps=int(gaps.sum()),
        sampling_gap_px=int(catalog.holes["area_px"][gaps].sum()),
        geometry=geometry,
    )


def footprint_steps(catalog: HoleCatalog, causes: np.ndarray, block_px: int) -> np.ndarray:
    """The holes outside every swath that are the footprint's block steps, not a missed strip.

    Without a planned area the survey area is the data's footprint, made of blocks of
    ``block_px`` (:mod:`pipeline.survey.footprint`): where the data's edge runs at a slant
    across them, an empty corner of a block it crosses is inside the area and outside every
    swath, though nothing was missed (the survey ends there: ``wires_quebec``, 22 triangles
    of 4-13 m2 every 24 m along its diagonal strips). Such a hole opens onto the area's edge
    and spans less than a block both ways; a missed strip spans the lines' gap across and
    the survey along. They are settled like sampling gaps: not listed, filled.
    """
    stats = catalog.stats
    within_block = (stats["row_max"] - stats["row_min"] < block_px) & (stats["col_max"] - stats["col_min"] < block_px)
    outside_swaths = (causes["cause"] == "missed_coverage") & (causes["rule"] == "coverage_gap")
    return outside_swaths & catalog.holes["touches_aoi_boundary"] & within_block & ~catalog.holes["is_small"]


def keep_hole_set(holes: HoleSet, path: str) -> None:
    """Writer: keep the linked holes for the later stages and for a resumed run."""
    save_object(path, holes)


# -- the stage's record ----------------------------------------------------------------------


def link_detected(state: RunState, results: list[object]) -> HoleSet:
    """Gather, on the client: the detected cells' holes linked and classified, and kept."""
    coverage, plan = state[COVERAGE], state.plan
    detected = list(state[DETECT_HOLES])
    ground = sum((t.ground for t in state[BIN_TILES].tiles), GroundLevel())
    holes = link_cells(
        detected, plan, state.config, plan.hole_params, coverage.line_moments, coverage.geometry,
        above_ground=ground.normalised,
    )  # fmt: skip
    keep_hole_set(holes, str(state.staging.hole_catalog))
    return holes


LINK_HOLES: Stage[object, HoleSet] = Stage(name="link_holes", gather=link_detected, runs=finds_holes, lap="holes")
