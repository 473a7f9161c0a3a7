"""Coverage gaps: where no flight line's swath reaches, from the lines' pixel moments (pure).

A flight line covers a straight band on the ground. The pixels whose highest
return came from one line (``point_source_id``, kept per pixel by stage 1) form
that band, minus what higher-numbered lines overlap: still a band, whose centre,
direction, length and width follow from the pixels' first and second moments (a
uniform rectangle of side ``L`` has variance ``L**2 / 12`` along it). The moments
are sums over cells (:mod:`pipeline.holes.flight_lines`), so the bands, and the
gaps between them, are the same for any cell size.

A *coverage gap* is the space between two adjacent, parallel bands that no band
covers: a missed line or a swath gap. Hole detection labels the hole pixels
inside a gap apart from the others (``CellEvidence.coverage`` of ``detect_cell_holes``),
so a river crossing a missed strip becomes two holes, each with its own cause.
See ``docs/holes.md``, "Coverage gaps".
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import numpy as np

from ..grid import PixelWindow, meeting, window_boxes, window_union_mask

__all__ = [
    "IN_GAP",
    "IN_MISSING_TILE",
    "IN_SWATH",
    "OUTSIDE_TILE_EXTENTS",
    "UNKNOWN",
    "Band",
    "CoverageGaps",
    "coverage_gaps",
    "extent_strips",
    "keep_void_gaps",
    "line_bands",
]

#: Coverage classes of a pixel (:meth:`CoverageGaps.classes`, ``CellEvidence.coverage``).
#: ``IN_MISSING_TILE``: in the square of a missing tile of the tile grid (:mod:`pipeline.survey.tile_grid`),
#: a coverage gap of its own kind.
#: ``OUTSIDE_TILE_EXTENTS``: in the square of a delivered tile but outside every tile's declared
#: extent (the tile's data stops short of its square): evidence of missed coverage only, it does
#: not make a pixel part of the survey area.
UNKNOWN, IN_SWATH, IN_GAP, IN_MISSING_TILE, OUTSIDE_TILE_EXTENTS = 0, 1, 2, 3, 4

#: Lines whose directions differ by more than this are not neighbours of one gap.
MAX_PARALLEL_DEG = 5.0
#: Elongation (length / width) a line's band needs to have a direction at all.
MIN_BAND_ELONGATION = 1.4
#: A band is a rectangle when its pixel count is this share of length x width (holes in it lower it).
BAND_FILL_RANGE = (0.8, 1.1)
#: A gap is kept only where at least this share of its pixels is empty ... A missed line leaves
#: its strip empty end to end, between swath edges that were measured; a lake or a canal on
#: the seam of two lines takes pixels from both bands, narrows them, and opens a sliver of
#: "gap" that is partly measured ground, or that the void spills over. Measured on the
#: synthetic cause scenes: missed strips 98.7-100 % empty with flanks 0.7-7.8 % empty; slivers
#: on lakes and canals 16-83 % empty, or with a flank 36-51 % empty.
GAP_MIN_VOID_SHARE = 0.9
#: ... and at most this share of each flank (``GAP_FLANK_PX`` beyond each edge, inside the bands).
GAP_MAX_FLANK_VOID_SHARE = 0.25
#: Width in pixels of the flanks checked beside a gap (the margin of :meth:`CoverageGaps.classes`).
GAP_FLANK_PX = 3.0


@dataclass(frozen=True)
class Band:
    """The band one flight line covers, in global pixel coordinates (row, column indices).

    ``direction`` is the unit vector (d_row, d_col) along track; ``centre`` the
    band's centroid; ``half_length`` and ``half_width`` its half sides in pixels.
    """

    line: int
    centre: tuple[float, float]
    direction: tuple[float, float]
    half_length: float
    half_width: float


@dataclass(frozen=True)
class CoverageGaps:
    """Strips between adjacent parallel bands that no band covers.

    Each gap is a rectangle in its own frame: along-track unit vector ``direction``,
    across-track coordinate in ``(across_lo, across_hi)``, along-track in
    ``(along_lo, along_hi)`` (pixels, measured from the origin of the grid).
    """

    gaps: tuple[tuple[tuple[float, float], float, float, float, float], ...]
    bands: tuple[Band, ...]
    missing_tiles: tuple[PixelWindow, ...] = ()  # squares of missing tiles, in grid pixels
    tile_extents: tuple[PixelWindow, ...] = ()  # the tiles' header extents, in grid pixels
    #: where a tile's extent stops short of its square: (strip, flank inside the extent), see :func:`extent_strips`
    extent_strips: tuple[tuple[PixelWindow, PixelWindow], ...] = ()

    def __bool__(self) -> bool:
        return bool(self.gaps or self.bands or self.missing_tiles or self.extent_strips)

    def classes(self, window: PixelWindow, *, margin_px: float = 3.0) -> np.ndarray:
        """Per pixel of ``window``: ``IN_GAP``, ``IN_SWATH`` or ``UNKNOWN`` (int8).

        A gap is grown by ``margin_px`` across and along track, a band shrunk by as
        much: the margin absorbs the jitter of swath edges, so that a missed strip is
        not cut into a core and slivers along its edges. A gap wins over a band, a
        missing tile (``IN_MISSING_TILE``, exact pixels) over both; a pixel in a
        delivered tile's square but outside every tile's extent is
        ``OUTSIDE_TILE_EXTENTS`` (in one of the ``extent_strips``) unless it is in a gap or a
        missing tile.
        """
        rows = np.arange(window.row_off, window.row_end, dtype=np.float64)[:, None]
        cols = np.arange(window.col_off, window.col_end, dtype=np.float64)[None, :]
        out = np.full(window.shape, UNKNOWN, np.int8)
        for band in self.bands:
            (dr, dc), (cr, cc) = band.direction, band.centre
            along = np.abs((rows - cr) * dr + (cols - cc) * dc)
            across = np.abs((cols - cc) * dr - (rows - cr) * dc)
            out[(along < band.half_length - margin_px) & (across < band.half_width - margin_px)] = IN_SWATH
        for gap in self.gaps:
            out[_in_gap(gap, rows, cols, margin_px)] = IN_GAP
        for square in self.missing_tiles:
            overlap = square.intersection(window)
            if not overlap.is_empty:
                out[overlap.slices_within(window)] = IN_MISSING_TILE
        if self.extent_strips:
            strips = [self.extent_strips[i][0] for i in meeting(self._strip_boxes[0::2], window)]
            extents = [self.tile_extents[i] for i in meeting(self._extent_boxes, window)]
            uncovered = window_union_mask(window, strips) & ~window_union_mask(window, extents)
            out[uncovered & (out < IN_GAP)] = OUTSIDE_TILE_EXTENTS
        return out

    def checked_near(self, window: PixelWindow) -> bool:
        """Whether a gap (with its flanks) or an extent strip may reach into ``window`` (bounding boxes)."""
        corners_r = np.array([window.row_off, window.row_off, window.row_end, window.row_end], np.float64)
        corners_c = np.array([window.col_off, window.col_end, window.col_off, window.col_end], np.float64)
        for (dr, dc), lo, hi, a_lo, a_hi in self.gaps:  # the window's extent in the gap's frame
            along = corners_r * dr + corners_c * dc
            across = corners_c * dr - corners_r * dc
            if (
                along.max() >= a_lo
                and along.min() <= a_hi
                and across.max() >= lo - GAP_FLANK_PX
                and across.min() <= hi + GAP_FLANK_PX
            ):
                return True
        return len(meeting(self._strip_boxes, window)) > 0

    def near(self, window: PixelWindow) -> tuple[CoverageGaps, np.ndarray]:
        """What a task over ``window`` needs of the survey's gaps, and the indices of its extent strips.

        Every gap and band (a few per flight line), and the missing tiles, tile extents and
        extent strips (strip or flank) that meet ``window``: :meth:`classes` and
        :meth:`void_counts` over ``window``, or any window inside it, are those of the whole
        survey's gaps (the strips' rows of :meth:`void_counts` in the order of the indices
        returned). A task carries this slice, not the survey's: the tiles' extents and strips
        grow with the survey, and every cell's task carried them all (quadratic in the tiles:
        1,536 tasks of 1,536 tiles held about 1 GB of pickled tasks on the client).
        """
        strips = np.unique(meeting(self._strip_boxes, window) // 2)
        extents = meeting(self._extent_boxes, window)
        missing = tuple(square for square in self.missing_tiles if not square.intersection(window).is_empty)
        sliced = CoverageGaps(
            self.gaps,
            self.bands,
            missing_tiles=missing,
            tile_extents=tuple(self.tile_extents[i] for i in extents),
            extent_strips=tuple(self.extent_strips[i] for i in strips),
        )
        return sliced, strips

    @functools.cached_property
    def _extent_boxes(self) -> np.ndarray:
        """The tiles' extents as :func:`~pipeline.grid.window_boxes`: :meth:`classes` reads those meeting its window."""
        return window_boxes(self.tile_extents)

    @functools.cached_property
    def _strip_boxes(self) -> np.ndarray:
        """``(row_off, col_off, row_end, col_end)`` of every extent strip and its flank (rows 2k, 2k + 1).

        Built once: :meth:`checked_near` runs for every cell, and a loop over the strips per
        cell was 1.6 M window intersections (6.4 s on the client) for 1,536 tiles.
        """
        return window_boxes([region for pair in self.extent_strips for region in pair])

    def void_counts(self, window: PixelWindow, empty: np.ndarray) -> np.ndarray:
        """Per gap and per extent strip, for it and its flanks: the pixels of ``window`` and the empty ones.

        int64, shape (gaps + strips, 3, 2): region (gap or strip, low flank, high flank) x
        (pixels, empty); a strip has one flank, inside its tile's extent (the third region
        is empty). Sums over windows that tile the grid are the survey's (:func:`keep_void_gaps`).
        """
        rows = np.arange(window.row_off, window.row_end, dtype=np.float64)[:, None]
        cols = np.arange(window.col_off, window.col_end, dtype=np.float64)[None, :]
        counts = np.zeros((len(self.gaps) + len(self.extent_strips), 3, 2), np.int64)
        for i, (direction, lo, hi, a_lo, a_hi) in enumerate(self.gaps):
            regions = ((lo, hi), (lo - GAP_FLANK_PX, lo), (hi, hi + GAP_FLANK_PX))
            for j, (r_lo, r_hi) in enumerate(regions):
                inside = _in_gap((direction, r_lo, r_hi, a_lo, a_hi), rows, cols, 0.0)
                counts[i, j] = np.count_nonzero(inside), np.count_nonzero(inside & empty)
        for i, pair in enumerate(self.extent_strips, start=len(self.gaps)):
            for j, region in enumerate(pair):
                overlap = region.intersection(window)
                if not overlap.is_empty:
                    part = empty[overlap.slices_within(window)]
                    counts[i, j] = part.size, np.count_nonzero(part)
        return counts


def _in_gap(
    gap: tuple[tuple[float, float], float, float, float, float], rows: np.ndarray, cols: np.ndarray, margin_px: float
) -> np.ndarray:
    """Which pixels (row and column index arrays, broadcast) lie in a gap grown by ``margin_px``."""
    (dr, dc), lo, hi, a_lo, a_hi = gap
    along = rows * dr + cols * dc
    across = cols * dr - rows * dc
    return (
        (across > lo - margin_px) & (across < hi + margin_px) & (along > a_lo - margin_px) & (along < a_hi + margin_px)
    )


def keep_void_gaps(gaps: CoverageGaps, counts: np.ndarray) -> CoverageGaps:
    """The gaps and extent strips that are empty beside measured flanks (:meth:`CoverageGaps.void_counts`, summed).

    At least ``GAP_MIN_VOID_SHARE`` of a gap's (a strip's) pixels are empty and at most
    ``GAP_MAX_FLANK_VOID_SHARE`` of each flank's. A tile's data stopping short of its
    square along a river or a lake shore leaves the water in the strip and on the flank.
    """
    pixels, empty = counts[..., 0].astype(np.float64), counts[..., 1].astype(np.float64)
    share = np.divide(empty, pixels, out=np.zeros_like(empty), where=pixels > 0)
    flanks_measured = (share[:, 1] <= GAP_MAX_FLANK_VOID_SHARE) & (share[:, 2] <= GAP_MAX_FLANK_VOID_SHARE)
    keep = (pixels[:, 0] > 0) & (share[:, 0] >= GAP_MIN_VOID_SHARE) & flanks_measured
    n = len(gaps.gaps)
    return dataclasses.replace(
        gaps,
        gaps=tuple(g for g, k in zip(gaps.gaps, keep[:n]) if k),
        extent_strips=tuple(s for s, k in zip(gaps.extent_strips, keep[n:]) if k),
    )


def extent_strips(
    squares: tuple[PixelWindow, ...], extents: tuple[PixelWindow, ...], flank_px: int = round(GAP_FLANK_PX)
) -> tuple[tuple[PixelWindow, PixelWindow], ...]:
    """Where each tile's extent stops short of its square: (strip, flank) per side.

    ``squares[i]`` is the square of the tile whose header extent is ``extents[i]``. A side
    strip spans the extent along that side, from the extent's edge to the square's; its
    flank is the ``flank_px`` just inside the extent there. Strips that other tiles'
    extents cover whole are left out.
    """
    out = []
    for sq, ex in zip(squares, extents):
        if ex.is_empty:
            continue
        sides = (
            (
                PixelWindow(sq.row_off, ex.col_off, ex.row_off - sq.row_off, ex.width),
                PixelWindow(ex.row_off, ex.col_off, flank_px, ex.width),
            ),
            (
                PixelWindow(ex.row_end, ex.col_off, sq.row_end - ex.row_end, ex.width),
                PixelWindow(ex.row_end - flank_px, ex.col_off, flank_px, ex.width),
            ),
            (
                PixelWindow(ex.row_off, sq.col_off, ex.height, ex.col_off - sq.col_off),
                PixelWindow(ex.row_off, ex.col_off, ex.height, flank_px),
            ),
            (
                PixelWindow(ex.row_off, ex.col_end, ex.height, sq.col_end - ex.col_end),
                PixelWindow(ex.row_off, ex.col_end - flank_px, ex.height, flank_px),
            ),
        )
        out += [(strip, flank.intersection(ex)) for strip, flank in sides if not strip.is_empty]
    # a strip another tile's extent covers whole is no place where data stops short
    boxes = window_boxes(extents)
    return tuple(
        (strip, flank)
        for strip, flank in out
        if not window_union_mask(strip, [extents[i] for i in meeting(boxes, strip)]).all()
    )


def line_bands(moments: np.ndarray) -> list[Band]:
    """The band of every line whose pixels form an elongated rectangle (``LINE_MOMENT_DTYPE`` rows)."""
    bands = []
    for m in moments:
        n = float(m["n"])
        if n < 100:
            continue
        mr, mc = m["r"] / n, m["c"] / n
        var_r = m["rr"] / n - mr * mr + 1.0 / 12.0
        var_c = m["cc"] / n - mc * mc + 1.0 / 12.0
        cov = m["rc"] / n - mr * mc
        values, vectors = np.linalg.eigh(np.array([[var_r, cov], [cov, var_c]]))
        if values[0] <= 0:
            continue
        half_width, half_length = math.sqrt(3.0 * values[0]), math.sqrt(3.0 * values[1])
        fill = n / (4.0 * half_width * half_length)
        if half_length < MIN_BAND_ELONGATION * half_width or not BAND_FILL_RANGE[0] <= fill <= BAND_FILL_RANGE[1]:
            continue
        dr, dc = vectors[:, 1]
        if dr < 0 or (dr == 0 and dc < 0):  # one orientation per axis
            dr, dc = -dr, -dc
        bands.append(Band(int(m["line"]), (float(mr), float(mc)), (float(dr), float(dc)), half_length, half_width))
    return bands


def coverage_gaps(moments: np.ndarray, *, min_width_px: float = 2.0) -> CoverageGaps:
    """The gaps between adjacent parallel flight-line bands (``LINE_MOMENT_DTYPE`` rows, merged).

    Bands are sorted across track in their common direction; two consecutive bands
    that are parallel (within ``MAX_PARALLEL_DEG``) and more than ``min_width_px``
    apart leave a gap, over the along-track stretch both cover. Edges are rounded
    to 1/1024 px, so that sums in another order cannot move a pixel across one.
    """
    bands = line_bands(moments)
    gaps: list[tuple[tuple[float, float], float, float, float, float]] = []
    for a in bands:
        (dr, dc), (ar, ac) = a.direction, a.centre
        across_a = ac * dr - ar * dc
        # the nearest parallel band on the positive side of a, across track
        best: tuple[float, Band] | None = None
        for b in bands:
            if b is a or abs(dr * b.direction[0] + dc * b.direction[1]) < math.cos(math.radians(MAX_PARALLEL_DEG)):
                continue
            offset = (b.centre[1] * dr - b.centre[0] * dc) - across_a
            if offset > 0 and (best is None or offset < best[0]):
                best = (offset, b)
        if best is None:
            continue
        offset, b = best
        lo, hi = across_a + a.half_width, across_a + offset - b.half_width
        if hi - lo < min_width_px:
            continue
        along_a = ar * dr + ac * dc
        along_b = b.centre[0] * dr + b.centre[1] * dc
        a_lo = max(along_a - a.half_length, along_b - b.half_length)
        a_hi = min(along_a + a.half_length, along_b + b.half_length)
        if a_hi - a_lo < min_width_px:
            continue
        lo, hi, a_lo, a_hi = (round(v * 1024.0) / 1024.0 for v in (lo, hi, a_lo, a_hi))
        gaps.append(((dr, dc), lo, hi, a_lo, a_hi))
    return CoverageGaps(tuple(gaps), tuple(bands))
