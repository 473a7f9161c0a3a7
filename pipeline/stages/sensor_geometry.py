"""The survey's sensor geometry on the client: its flight lines and swaths, fitted from stage 1's sums.

:func:`sensor_geometry` fits the lines (:mod:`pipeline.sensor.trajectory`) and their swaths;
where heights are assumed it finds the field of view the shadows agree with
(:func:`fov_from_shadows`). Hole detection (:mod:`.detect_holes`) hands each cell the
lines that reach it.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.ndimage as ndi
import shapely

from ..config import Config
from ..grid import PixelWindow
from ..holes import height_jumps
from ..io.intermediate import load_shared_cell_statistics
from ..io.raster import geometry_mask
from ..plan import SurveyPlan
from ..sensor.sight import (
    TARGET_RADII_M,
    StepPixels,
    pixels_beside_steps,
    shadow_contradictions,
)
from ..sensor.sums import TrajectorySums
from ..sensor.trajectory import FlightLine, fit_flight_lines, swath_polygon
from .bin_tiles import TileResult
from .merge_cells import CellResult

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SensorGeometry:
    """The survey's flight lines (:mod:`pipeline.sensor.trajectory`) and their swaths (world polygons).

    ``complete``: the lines account for the survey's points (their GPS times place them), so a
    pixel outside every swath was swept by none; else the swaths are written but not judged.
    """

    lines: tuple[FlightLine, ...]
    swaths_wkb: tuple[bytes, ...]  # one polygon per line (WKB: kept results hold data only)
    points_in_lines: int
    points_timed: int
    points_used: int
    fov_from_shadows: float | None = None  # the field of view the shadows gave, where heights are assumed

    @property
    def rim_rules(self) -> bool:
        """Whether the rim's occlusion rules speak too: heights assumed from a field of view nothing measured."""
        return self.heights_assumed and self.fov_from_shadows is None

    @property
    def swaths(self) -> tuple[shapely.Geometry, ...]:
        return tuple(shapely.from_wkb(w) for w in self.swaths_wkb)

    @property
    def heights_assumed(self) -> bool:
        """Whether most points lie in lines whose sensor heights are assumed (single returns, no scan angles)."""
        assumed = sum(line.points for line in self.lines if line.method == "nominal")
        return assumed > 0.5 * max(self.points_in_lines, 1)

    @property
    def complete(self) -> bool:
        return (
            bool(self.lines)
            and self.points_in_lines >= LINES_MIN_POINT_SHARE * self.points_timed
            and self.points_timed >= TIMED_MIN_POINT_SHARE * self.points_used
        )


#: The fitted lines must hold this share of the points with a GPS time ...
LINES_MIN_POINT_SHARE = 0.95
#: ... and those this share of the points used (a survey of tiles without GPS time has no lines).
TIMED_MIN_POINT_SHARE = 0.9


def survey_extent(boxes: list[tuple[float, float, float, float]], seam: float) -> shapely.Geometry:
    """Where the survey holds data: the union of the tiles' boxes, with the seams between neighbours closed.

    A header's box ends at its outermost point, so neighbouring tiles leave a gap of up to a
    point spacing between their boxes (0.01 m on a survey cut at whole metres); left open, every
    tile border would be a boundary of the data and cut the swaths crossing it. Gaps narrower
    than ``2 * seam`` (a pixel: it holds several returns, so a gap under it is no edge of the data)
    are closed.
    """
    union = shapely.union_all([shapely.box(*box) for box in boxes])
    closed = union.buffer(seam, join_style="mitre").buffer(-seam, join_style="mitre")
    return _without_holes(closed)


def _without_holes(area: shapely.Geometry) -> shapely.Geometry:
    """``area`` with its interior rings filled: a void the survey's tiles enclose is no edge of the survey.

    A missed flight line's strip between tiles whose data stops at its edges leaves a hole in the
    union of their boxes; taken for the survey's edge, it made the swath sides facing the strip
    cropped, and the neighbouring lines' tracks were placed 1.4 and 2.6 m off (a simulated Delft
    scan with assumed heights).
    """
    polygons = shapely.get_parts(area)
    return shapely.union_all([shapely.Polygon(shapely.get_exterior_ring(p)) for p in polygons if not p.is_empty])


def sensor_geometry(
    tiles: list[TileResult], plan: SurveyPlan, config: Config, *, fov_from_shadows: float | None = None
) -> SensorGeometry:
    """Gather: the flight lines' trajectories and swaths from the sums of every tile.

    ``fov_from_shadows``: the field of view the survey's shadows give (:func:`fov_from_shadows`),
    taken instead of ``sensor.nominal_fov_deg`` where a line's heights are assumed.
    """
    sums = TrajectorySums.merged([t.trajectory for t in tiles])
    fov = config.sensor.nominal_fov_deg if fov_from_shadows is None else fov_from_shadows
    lines = _line_fitter(sums, plan)(fov)
    return SensorGeometry(
        lines=tuple(lines),
        swaths_wkb=tuple(shapely.to_wkb(swath_polygon(line)) for line in lines),
        points_in_lines=sum(line.points for line in lines),
        points_timed=sums.points,
        points_used=sum(t.points_used for t in tiles),
        fov_from_shadows=fov_from_shadows,
    )


def _line_fitter(sums: TrajectorySums, plan: SurveyPlan) -> Callable[[float], list[FlightLine]]:
    """The survey's flight lines fitted from ``sums`` for a given field of view (the extent made once)."""
    grid = plan.grid
    extent = survey_extent([tile.bounds for tile in plan.survey.tiles], grid.resolution)

    def fit(nominal_fov_deg: float) -> list[FlightLine]:
        origin = (grid.x_left, grid.y_top, 0.0)
        return fit_flight_lines(
            sums.lines, sums.bins, sums.values, origin=origin, nominal_fov_deg=nominal_fov_deg, extent=extent
        )

    return fit


#: Fields of view tried for lines whose heights are assumed (degrees): airborne scanners sweep 20-75.
FOV_SEARCH_DEG = tuple(range(20, 77, 4))
#: Squares of this side (metres, on the absolute pixel lattice, whatever the cells) judge a field of view:
FOV_SQUARE_M = 250.0
#: the ones with most voids beside a step among an even sample of this many ...
FOV_SAMPLE_SQUARES = 24
#: ... of which this many are used.
FOV_EVIDENCE_SQUARES = 4
#: Voids and returned ground beside steps a field of view needs before the shadows speak.
FOV_MIN_EVIDENCE_PX = 200


def fov_from_shadows(
    tiles: list[TileResult], merged: list[CellResult], plan: SurveyPlan, config: Config
) -> float | None:
    """The scanner's field of view at which the survey's shadows fit best, where its heights are assumed.

    Single returns without scan angles give no sensor position: each line's height is its
    swath's half-width over the tangent of half an assumed field of view. The shadows beside
    the survey's steps tell that height: a sensor too low casts them over ground that returned
    points, one too high leaves the voids behind the steps in view
    (:func:`pipeline.sensor.sight.shadow_contradictions`). The field of view whose trajectories
    contradict fewest pixels, over the ``FOV_EVIDENCE_SQUARES`` squares with most voids beside a step,
    searched every 4 degrees from 20 to 76 and then to the degree; None where those squares hold
    fewer than ``FOV_MIN_EVIDENCE_PX`` pixels beside a step (flat open ground casts no shadow), or
    where the best lies at either end of the range (no scanner's field of view fits: the tracks
    are off, as in an extract cut from inside the swaths on both sides).
    The squares do not depend on the cells, so neither does the field of view.
    """
    fitted = _line_fitter(TrajectorySums.merged([t.trajectory for t in tiles]), plan)
    grid = plan.grid
    pixel_m = grid.resolution * plan.survey.horizontal_unit_m
    reach_px = max(1, math.ceil(config.sensor.sight_reach_m / pixel_m))
    windows = _step_windows(merged, plan, reach_px, near_px=max(1, math.ceil(TARGET_RADII_M[-1] / pixel_m)))
    if not windows:
        return None

    def contradictions(fov: float) -> tuple[int, int]:
        lines = fitted(fov)
        swaths = [swath_polygon(line) for line in lines]
        contradicting = judged = 0
        for window, zmax, measured, beside in windows:
            transform = grid.window_transform(window)
            masks = np.zeros((len(swaths), *window.shape), bool)
            for k, swath in enumerate(swaths):
                masks[k] = geometry_mask(swath, transform, window.shape)
            blocked, seen, n = shadow_contradictions(
                zmax, measured, beside, masks, [line.sensor for line in lines],
                origin_xy=(transform.c, transform.f), pixel_size=grid.resolution, reach=reach_px * grid.resolution,
                max_scan_angles=[line.max_scan_angle_deg for line in lines],
            )  # fmt: skip
            contradicting, judged = contradicting + blocked + seen, judged + n
        return contradicting, judged

    assumed = config.sensor.nominal_fov_deg
    at_assumed, judged = contradictions(assumed)
    if judged < FOV_MIN_EVIDENCE_PX:
        return None
    scores = {assumed: at_assumed}
    for fov in FOV_SEARCH_DEG:
        if fov not in scores:
            scores[fov] = contradictions(fov)[0]
    coarse = min(FOV_SEARCH_DEG, key=lambda f: (scores[f], abs(f - assumed)))
    if coarse in (FOV_SEARCH_DEG[0], FOV_SEARCH_DEG[-1]):
        # no airborne scanner's field of view fits: the tracks are off, not the heights (an extract
        # inside the swaths, cut on both sides: IGN's 50 m tile 77050_627755 fitted best at 17 degrees)
        logger.info(
            "field of view from the shadows: none between %d and %d degrees fits",
            *FOV_SEARCH_DEG[:: len(FOV_SEARCH_DEG) - 1],
        )
        return None
    for fov in range(coarse - 3, coarse + 4):
        if fov not in scores:
            scores[fov] = contradictions(fov)[0]
    best = min(scores, key=lambda f: (scores[f], abs(f - assumed)))
    logger.info(
        "field of view from the shadows: %d degrees (%d of %d pixels beside steps contradict it; %d at the assumed %g)",
        best, scores[best], judged, at_assumed, assumed,
    )  # fmt: skip
    return float(best)


def _step_windows(
    merged: list[CellResult], plan: SurveyPlan, reach_px: int, *, near_px: int
) -> list[tuple[PixelWindow, np.ndarray, np.ndarray, StepPixels]]:
    """The windows (a square grown by the reach) of the squares with most voids beside a step.

    The squares, ``FOV_SQUARE_M`` on the absolute pixel lattice, do not depend on the cells: an
    even sample of ``FOV_SAMPLE_SQUARES`` of those the grid meets is ranked by its empty pixels
    within ``near_px`` of a height jump, and the best ``FOV_EVIDENCE_SQUARES`` that hold any are read
    whole: ``(window, zmax, measured, beside)``, ``beside`` the square's own pixels beside a step.
    """
    grid, cells, step = plan.grid, plan.cell_by_id(), plan.hole_params.jump_threshold
    neighbours = tuple((cells[r.cell_id].window, r.statistics_path) for r in merged)
    side = max(1, math.ceil(FOV_SQUARE_M / (grid.resolution * plan.survey.horizontal_unit_m)))
    rows = range((grid.row_top - grid.height + 1) // side, grid.row_top // side + 1)  # absolute rows count upwards
    cols = range(grid.col_min // side, (grid.col_min + grid.width - 1) // side + 1)
    squares = [
        PixelWindow(grid.row_top - (r * side + side - 1), c * side - grid.col_min, side, side).intersection(grid.window)
        for r in reversed(rows)
        for c in cols
    ]
    squares = [w for w in squares if not w.is_empty]
    sample = squares[:: max(1, math.ceil(len(squares) / FOV_SAMPLE_SQUARES))]
    structure = np.ones((3, 3), bool)
    ranked = []
    for k, square in enumerate(sample):
        zmax, zmin, measured, _ = read_neighbours(neighbours, square)
        jumps = height_jumps(zmax, zmin, jump_threshold=step)
        near = ndi.binary_dilation(jumps, structure=structure, iterations=near_px) if jumps.any() else jumps
        ranked.append((int((near & ~measured).sum()), k))
    out = []
    for voids, k in sorted(ranked, key=lambda r: (-r[0], r[1]))[:FOV_EVIDENCE_SQUARES]:
        if voids == 0:
            break
        window = sample[k].expand(reach_px).intersection(grid.window)
        zmax, zmin, measured, _ = read_neighbours(neighbours, window)
        core = np.zeros(window.shape, bool)
        core[sample[k].slices_within(window)] = True
        beside = pixels_beside_steps(
            zmax, zmin, measured, step=step, near_px=near_px, pixel_size=grid.resolution, within=core
        )
        out.append((window, zmax, measured, beside))
    return out


def read_neighbours(
    neighbours: tuple[tuple[PixelWindow, str], ...], window: PixelWindow
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Highest and lowest return, whether measured and whether water was, over a window, from the cells it meets."""
    zmax = np.full(window.shape, np.nan)
    zmin = np.full(window.shape, np.nan)
    measured = np.zeros(window.shape, bool)
    water = np.zeros(window.shape, bool)
    for core, path in neighbours:
        overlap = core.intersection(window)
        if overlap.is_empty:
            continue
        stats = load_shared_cell_statistics(path, ("zmax", "zmin", "count", "water")).crop(overlap)
        inside = overlap.slices_within(window)
        zmax[inside], zmin[inside], measured[inside] = stats.zmax, stats.zmin, stats.count > 0
        water[inside] = stats.water > 0
    return zmax, zmin, measured, water
