"""The fill benchmark: cut artificial holes into real surveys, fill them, score the fills.

For each survey (and each surface model, DSM or DTM) the benchmark

1. runs the pipeline on the full survey without filling: the *reference* raster;
2. places seeded artificial holes (discs, rotated rectangles, irregular blobs,
   2 m to 50 m across) where the reference is measured over the hole and a margin
   around it, apart from each other (:func:`place_holes`);
3. writes a copy of each input file without the points that fall in those pixels
   (:func:`cut_points`): the removed pixels are exactly the hole pixels;
4. runs the pipeline on the cut copy once per fill method (``--set``-style
   overrides of ``[fill]``) and scores each filled raster on the removed pixels
   against the reference (:func:`fill_errors`);
5. fills the same holes of the cut survey's unfilled raster with the usual
   alternatives (:data:`ALTERNATIVES`: GDAL fillnodata, a linear TIN, startinpy's
   natural-neighbour and Laplace interpolation, GRASS ``r.fillnulls``) and scores
   them the same way.

The array functions (:func:`hole_shape`, :func:`place_holes`, :func:`fill_errors`,
the alternatives) take and return arrays; :func:`evaluate_fill` is the tool that
reads and writes files and runs the pipeline. Rows and columns are pixels, x/y are
world coordinates; heights are in the survey's z unit.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import subprocess
import tempfile
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import scipy.ndimage as ndi

from .config import Config
from .errors import ConfigError, HolefillError, InputDataError

logger = logging.getLogger(__name__)

#: Pipeline runs on the cut survey: name -> ``[fill]`` overrides. ``default`` is the
#: default configuration (``auto``, filled by cause); the others change one thing.
PIPELINE_RUNS: dict[str, dict[str, Any]] = {
    "default": {},
    "auto-nocause": {"by_cause": False},
    "tin": {"method": "tin"},
    "mls": {"method": "mls"},
    "idw": {"method": "idw"},
    "nearest": {"method": "nearest"},
    # the interpolators alone, every hole filled as ground would be (no flat water, no lower side)
    "mls-nocause": {"method": "mls", "by_cause": False},
    "idw-nocause": {"method": "idw", "by_cause": False},
}

#: Surface models: name -> ``[filter]`` overrides.
MODELS: dict[str, dict[str, Any]] = {"dsm": {}, "dtm": {"keep_classes": [2]}}

#: Hole shapes placed by :func:`place_holes`.
SHAPES = ("disc", "rectangle", "blob")

#: Pixel sizes (m) tried for a survey, finest first (see :func:`choose_resolution`).
RESOLUTIONS_M = (1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0)


# -- metrics ---------------------------------------------------------------------------------


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


# -- artificial holes ------------------------------------------------------------------------


def hole_shape(kind: str, size_px: float, rng: np.random.Generator) -> np.ndarray:
    """A hole of one shape as a boolean mask, ``size_px`` pixels across at most.

    Parameters
    ----------
    kind : {"disc", "rectangle", "blob"}
        A disc of diameter ``size_px``; a rectangle ``size_px`` long and 0.25 to 1
        times as wide, rotated at random; a star-shaped blob whose radius varies
        between about 0.35 and 0.5 ``size_px`` with the angle.
    size_px : float
        Largest extent in pixels (at least 1).
    rng : numpy.random.Generator
        Draws the sub-pixel position, orientation and outline.

    Returns
    -------
    ndarray of bool
        The largest 4-connected component of the shape on the pixel lattice (at
        least one pixel), trimmed to its bounding box.
    """
    if kind not in SHAPES:
        raise ValueError(f"unknown hole shape {kind!r}; choose one of {list(SHAPES)}")
    size = max(float(size_px), 1.0)
    side = math.ceil(size) + 2
    centre = side / 2 + rng.uniform(-0.5, 0.5, 2)
    rows, cols = np.mgrid[0:side, 0:side] + 0.5
    dy, dx = rows - centre[0], cols - centre[1]
    if kind == "disc":
        mask = dx**2 + dy**2 <= (size / 2) ** 2
    elif kind == "rectangle":
        angle = rng.uniform(0, math.pi)
        width = size * rng.uniform(0.25, 1.0)
        u = dx * math.cos(angle) + dy * math.sin(angle)
        v = -dx * math.sin(angle) + dy * math.cos(angle)
        # the longer side is size (the diagonal may be longer: both stay within the box)
        mask = (np.abs(u) <= size / 2) & (np.abs(v) <= width / 2)
    else:
        k = np.arange(2, 6)
        amplitude = rng.uniform(0.0, 0.3, len(k)) / np.sqrt(k)
        phase = rng.uniform(0, 2 * math.pi, len(k))
        theta = np.arctan2(dy, dx)
        outline = 1 + np.sum(amplitude[:, None, None] * np.cos(k[:, None, None] * theta + phase[:, None, None]), axis=0)
        top = 1 + amplitude.sum()
        radius = (size / 2) * np.maximum(outline, 0.7) / top
        mask = np.hypot(dx, dy) <= radius
    labels, n = ndi.label(mask)
    if n == 0:
        mask = np.zeros((1, 1), bool)
        mask[0, 0] = True
        return mask
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    mask = labels == int(sizes.argmax())
    box = ndi.find_objects(mask.astype(np.int8))[0]
    return mask[box]


@dataclass(frozen=True)
class CutHole:
    """One artificial hole (pixel units of the survey grid)."""

    hole_id: int
    shape: str
    size_m: float  # requested largest extent
    n_px: int
    row: int  # bounding box
    col: int
    height: int
    width: int
    relief: float  # max - min of the reference over the hole (z units): buildings, trees
    max_distance_px: float  # farthest hole pixel from the nearest pixel outside the hole

    def as_dict(self, pixel_size_m: float) -> dict[str, Any]:
        return {
            "hole_id": self.hole_id,
            "shape": self.shape,
            "size_m": round(self.size_m, 2),
            "n_px": self.n_px,
            "area_m2": round(self.n_px * pixel_size_m**2, 2),
            "bbox_rc": [self.row, self.col, self.height, self.width],
            "relief": _finite(self.relief),
            "max_distance_m": round(self.max_distance_px * pixel_size_m, 2),
        }


def place_holes(
    reference: np.ndarray,
    *,
    n_holes: int,
    rng: np.random.Generator,
    pixel_size_m: float,
    min_size_m: float = 2.0,
    max_size_m: float = 50.0,
    margin_px: int = 4,
    edge_px: int = 0,
    tries_per_hole: int = 40,
) -> tuple[np.ndarray, list[CutHole]]:
    """Place seeded artificial holes where the reference is measured.

    Each hole has a shape drawn from :data:`SHAPES` and a largest extent drawn
    log-uniformly between ``min_size_m`` (at least one pixel) and ``max_size_m``.
    It is kept only where every pixel within ``margin_px`` of it is measured in
    the reference and belongs to no other hole's margin; a size that fits nowhere
    is drawn again, up to ``tries_per_hole * n_holes`` draws in all, so small or
    patchy surveys get fewer (and smaller) holes than asked.

    Parameters
    ----------
    reference : ndarray of shape (M, N)
        The raster of the full survey (NaN = no data).
    n_holes : int
        Holes wanted.
    rng : numpy.random.Generator
    pixel_size_m : float
        Pixel size in metres (hole sizes are in metres).
    margin_px : int
        Measured pixels kept around each hole (and between holes).
    edge_px : int
        Pixels kept clear of the raster's edge: the pipeline takes the data's
        border blocks (``holes.footprint_block_m``) as outside the survey where
        they are empty, so a hole there would be partly exterior, not filled.

    Returns
    -------
    labels : ndarray of int32, shape (M, N)
        Hole id (1..) on each removed pixel, 0 elsewhere.
    holes : list of CutHole
    """
    if reference.ndim != 2:
        raise ValueError(f"the reference must be a 2-dimensional array, got shape {reference.shape}")
    labels = np.zeros(reference.shape, np.int32)
    free = np.isfinite(reference)
    if edge_px > 0:
        free[:edge_px] = free[-edge_px:] = False
        free[:, :edge_px] = free[:, -edge_px:] = False
    holes: list[CutHole] = []
    if n_holes <= 0 or not free.any():
        return labels, holes
    distance = ndi.distance_transform_edt(np.pad(free, 1))[1:-1, 1:-1]
    low, high = math.log(max(min_size_m, pixel_size_m)), math.log(max(max_size_m, min_size_m, pixel_size_m))
    for _ in range(tries_per_hole * n_holes):
        if len(holes) == n_holes:
            break
        size_m = math.exp(rng.uniform(low, high))
        kind = SHAPES[int(rng.integers(len(SHAPES)))]
        mask = hole_shape(kind, size_m / pixel_size_m, rng)
        h, w = mask.shape
        # a quick necessary condition on the centre (a disc needs room for its radius), then the exact test
        need = margin_px + (min(h, w) / 2 - 1 if kind == "disc" else 0)
        candidates = np.flatnonzero(distance.ravel() > need)
        if not len(candidates):
            continue
        centre = int(candidates[rng.integers(len(candidates))])
        r0 = centre // reference.shape[1] - h // 2
        c0 = centre % reference.shape[1] - w // 2
        if r0 < 0 or c0 < 0 or r0 + h > reference.shape[0] or c0 + w > reference.shape[1]:
            continue
        if not np.all(distance[r0 : r0 + h, c0 : c0 + w][mask] > margin_px):
            continue
        hole_id = len(holes) + 1
        labels[r0 : r0 + h, c0 : c0 + w][mask] = hole_id
        heights = reference[r0 : r0 + h, c0 : c0 + w][mask]
        inside = ndi.distance_transform_edt(np.pad(mask, 1))[1:-1, 1:-1]
        holes.append(
            CutHole(
                hole_id=hole_id,
                shape=kind,
                size_m=size_m,
                n_px=int(mask.sum()),
                row=r0,
                col=c0,
                height=h,
                width=w,
                relief=float(heights.max() - heights.min()),
                max_distance_px=float(inside.max()),
            )
        )
        # the hole and its margin are no place for another hole
        near = ndi.distance_transform_edt(~np.pad(mask, margin_px)) <= margin_px
        rows = slice(r0 - margin_px, r0 + h + margin_px)
        cols = slice(c0 - margin_px, c0 + w + margin_px)
        keep_r = slice(max(0, -rows.start), near.shape[0] - max(0, rows.stop - reference.shape[0]))
        keep_c = slice(max(0, -cols.start), near.shape[1] - max(0, cols.stop - reference.shape[1]))
        free[max(0, rows.start) : rows.stop, max(0, cols.start) : cols.stop] &= ~near[keep_r, keep_c]
        distance = ndi.distance_transform_edt(np.pad(free, 1))[1:-1, 1:-1]
    return labels, holes


def choose_resolution(points: int, area_m2: float, *, min_points_per_px: float = 2.0) -> float:
    """The finest pixel (m) of :data:`RESOLUTIONS_M` that holds ``min_points_per_px`` points on average.

    A survey with at least one point per m2 keeps 1 m pixels.
    """
    density = points / area_m2 if area_m2 > 0 else 0.0
    if density >= 1.0:
        return RESOLUTIONS_M[0]
    for resolution in RESOLUTIONS_M:
        if density * resolution**2 >= min_points_per_px:
            return resolution
    return RESOLUTIONS_M[-1]


# -- alternatives -----------------------------------------------------------------------------


class AlternativeUnavailable(HolefillError):
    """An alternative cannot run here (its package or program is missing)."""


def _hole_windows(labels: np.ndarray) -> list[tuple[int, tuple[slice, slice], tuple[slice, slice]]]:
    """Per hole: its id, its bounding box, and the box grown by its own extent (its support)."""
    windows = []
    for index, box in enumerate(ndi.find_objects(labels)):
        if box is None:
            continue
        rows, cols = box
        grow = max(rows.stop - rows.start, cols.stop - cols.start) + 2
        window = (
            slice(max(0, rows.start - grow), min(labels.shape[0], rows.stop + grow)),
            slice(max(0, cols.start - grow), min(labels.shape[1], cols.stop + grow)),
        )
        windows.append((index + 1, (rows, cols), window))
    return windows


def _scattered(
    heights: np.ndarray, labels: np.ndarray, interpolate: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
) -> np.ndarray:
    """Fill each hole from the measured pixel centres around it with a scattered-data interpolator."""
    out = np.full(heights.shape, np.nan)
    for hole_id, _, window in _hole_windows(labels):
        sub = heights[window]
        known = np.isfinite(sub)
        target = labels[window] == hole_id
        if known.sum() < 3:
            continue
        points = np.column_stack(np.nonzero(known)).astype(np.float64)[:, ::-1] + 0.5  # (col, row) centres
        queries = np.column_stack(np.nonzero(target)).astype(np.float64)[:, ::-1] + 0.5
        values = interpolate(points, sub[known].astype(np.float64), queries)
        out[window][target] = values
    return out


def fill_gdal(heights: np.ndarray, labels: np.ndarray, *, max_search_px: float = 100.0) -> np.ndarray:
    """GDAL's fillnodata (``rasterio.fill.fillnodata``) over the whole raster, no smoothing.

    Parameters
    ----------
    heights : ndarray of shape (M, N)
        The unfilled raster (NaN = no data).
    labels : ndarray of int, shape (M, N)
        The holes to score (> 0); every empty pixel within reach is filled.
    max_search_px : float
        Search distance in pixels (at least the deepest hole pixel's distance to data).
    """
    from rasterio.fill import fillnodata

    known = np.isfinite(heights)
    if not known.any():
        return np.full(heights.shape, np.nan)
    depth = ndi.distance_transform_edt(labels > 0).max() if (labels > 0).any() else 0.0
    image = np.where(known, heights, 0).astype(np.float32)
    filled = fillnodata(image, mask=known.astype(np.uint8), max_search_distance=max(max_search_px, depth + 2))
    filled = filled.astype(np.float64)
    # fillnodata leaves a pixel it cannot reach as it was (0 here)
    reached = ndi.distance_transform_edt(~known) <= max(max_search_px, depth + 2)
    return np.where(known | reached, filled, np.nan)


def fill_tin_linear(heights: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Linear interpolation on the Delaunay triangulation of the measured pixel centres (scipy)."""
    from scipy.interpolate import LinearNDInterpolator

    def interpolate(points: np.ndarray, z: np.ndarray, queries: np.ndarray) -> np.ndarray:
        return LinearNDInterpolator(points, z)(queries)

    return _scattered(heights, labels, interpolate)


def _startinpy(method: str) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    try:
        import startinpy
    except ImportError:
        raise AlternativeUnavailable("startinpy is not installed (pip install 'holefill[eval]')") from None

    def interpolate(points: np.ndarray, z: np.ndarray, queries: np.ndarray) -> np.ndarray:
        dt = startinpy.DT()
        dt.insert(np.column_stack([points, z]))
        return np.asarray(dt.interpolate({"method": method}, queries), np.float64)

    def fill(heights: np.ndarray, labels: np.ndarray) -> np.ndarray:
        return _scattered(heights, labels, interpolate)

    return fill


def fill_nni(heights: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Natural-neighbour (Sibson) interpolation of the measured pixel centres (startinpy)."""
    return _startinpy("NNI")(heights, labels)


def fill_laplace(heights: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Laplace (non-Sibsonian natural-neighbour) interpolation of the measured pixel centres (startinpy)."""
    return _startinpy("Laplace")(heights, labels)


def fill_grass(heights: np.ndarray, labels: np.ndarray, *, timeout_s: float = 600.0) -> np.ndarray:
    """GRASS GIS ``r.fillnulls method=bicubic`` in a temporary XY project.

    Needs the ``grass`` start-up script on PATH; raises :class:`AlternativeUnavailable`
    otherwise or when GRASS fails.
    """
    grass = shutil.which("grass")
    if grass is None:
        raise AlternativeUnavailable("GRASS GIS is not installed ('grass' is not on PATH)")
    import rasterio
    from affine import Affine

    known = np.isfinite(heights)
    rows = np.flatnonzero((labels > 0).any(axis=1))
    cols = np.flatnonzero((labels > 0).any(axis=0))
    if not len(rows):
        return np.full(heights.shape, np.nan)
    pad = max(len(rows), len(cols)) + 8  # bicubic splines need support around the holes, not the whole survey
    r0, r1 = max(0, rows[0] - pad), min(heights.shape[0], rows[-1] + 1 + pad)
    c0, c1 = max(0, cols[0] - pad), min(heights.shape[1], cols[-1] + 1 + pad)
    sub = np.where(known, heights, -9999.0)[r0:r1, c0:c1].astype(np.float32)
    with tempfile.TemporaryDirectory(prefix="holefill-grass-") as tmp:
        source, result = Path(tmp) / "in.tif", Path(tmp) / "out.tif"
        profile = dict(driver="GTiff", width=sub.shape[1], height=sub.shape[0], count=1, dtype="float32")
        with rasterio.open(source, "w", nodata=-9999.0, transform=Affine(1, 0, c0, 0, -1, -r0), **profile) as dst:
            dst.write(sub, 1)
        script = (
            f"r.in.gdal -o input={source} output=dsm --quiet && g.region raster=dsm && "
            f"r.fillnulls input=dsm output=filled method=bicubic --quiet && "
            f"r.out.gdal input=filled output={result} format=GTiff type=Float64 --quiet"
        )
        try:
            subprocess.run(
                [grass, "--tmp-project", "XY", "--exec", "bash", "-c", script],
                check=True,
                capture_output=True,
                text=True,
                timeout=timeout_s,
            )
            with rasterio.open(result) as src:
                filled = src.read(1, masked=True).astype(np.float64).filled(np.nan)
        except (OSError, subprocess.SubprocessError) as e:
            detail = getattr(e, "stderr", "") or str(e)
            raise AlternativeUnavailable(f"GRASS r.fillnulls failed: {detail.strip()[-300:]}") from None
    out = np.full(heights.shape, np.nan)
    out[r0:r1, c0:c1] = filled
    return out


#: Alternatives scored on the same holes: name -> fill(heights, labels) -> heights.
ALTERNATIVES: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "gdal_fillnodata": fill_gdal,
    "tin_linear": fill_tin_linear,
    "nni": fill_nni,
    "laplace": fill_laplace,
    "grass_fillnulls": fill_grass,
}


# -- cutting the survey -------------------------------------------------------------------------


def pixel_indices(x: np.ndarray, y: np.ndarray, transform: Any) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of points on a north-up raster on the pipeline's absolute lattice.

    The pipeline puts a point in column ``floor(x / res)`` and row
    ``floor(y / res)`` of the global lattice (``pipeline.grid``); a raster's
    transform says where its first pixel is on that lattice.
    """
    resolution = transform.a
    col0 = round(transform.c / resolution)
    row_top = round(transform.f / resolution) - 1
    cols = np.floor(x / resolution).astype(np.int64) - col0
    rows = row_top - np.floor(y / resolution).astype(np.int64)
    return rows, cols


def cut_points(source: str | os.PathLike, target: str | os.PathLike, labels: np.ndarray, transform: Any) -> int:
    """Copy a LAS/LAZ file without the points in the labelled pixels; returns how many were removed."""
    import laspy

    try:
        las = laspy.read(source)
    except Exception as e:  # laspy raises several unrelated types
        raise InputDataError(source, f"cannot be read for cutting: {e}") from None
    rows, cols = pixel_indices(np.asarray(las.x), np.asarray(las.y), transform)
    inside = (rows >= 0) & (rows < labels.shape[0]) & (cols >= 0) & (cols < labels.shape[1])
    remove = np.zeros(len(rows), bool)
    remove[inside] = labels[rows[inside], cols[inside]] > 0
    las.points = las.points[~remove]
    Path(target).parent.mkdir(parents=True, exist_ok=True)
    las.write(str(target), do_compress=Path(target).suffix.lower() == ".laz")
    return int(remove.sum())


def align(array: np.ndarray, transform: Any, to_transform: Any, to_shape: tuple[int, int]) -> np.ndarray:
    """A raster on the same lattice put onto another window of it (NaN where it has no pixel)."""
    resolution = to_transform.a
    dr = round((transform.f - to_transform.f) / resolution)  # rows of `array` above the target's first row
    dc = round((transform.c - to_transform.c) / resolution)
    out = np.full(to_shape, np.nan, np.float64)
    r0, c0 = max(0, dr), max(0, -dc)  # first source row / column inside the target
    tr, tc = max(0, -dr), max(0, dc)  # where it lands
    h = min(array.shape[0] - r0, to_shape[0] - tr)
    w = min(array.shape[1] - c0, to_shape[1] - tc)
    if h > 0 and w > 0:
        out[tr : tr + h, tc : tc + w] = array[r0 : r0 + h, c0 : c0 + w]
    return out


# -- the tool -----------------------------------------------------------------------------------


@dataclass
class MethodResult:
    """One method on one survey: errors, or why it did not run."""

    errors: ErrorStats | None = None
    skipped: str = ""
    seconds: float = math.nan
    stage_seconds: dict[str, float] = field(default_factory=dict)
    per_hole_rmse: dict[int, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = self.errors.as_dict() if self.errors else {}
        if self.skipped:
            out["skipped"] = self.skipped
        out["seconds"] = _finite(self.seconds)
        if self.stage_seconds:
            out["stage_seconds"] = {k: _finite(v) for k, v in self.stage_seconds.items()}
        return out


@dataclass
class SurveyResult:
    """One survey, one surface model."""

    survey: str
    model: str
    inputs: list[str]
    resolution_m: float = math.nan
    z_unit_m: float = 1.0  # metres per z unit: errors are in z units (feet on a survey in feet)
    skipped: str = ""
    holes: list[CutHole] = field(default_factory=list)
    points_removed: int = 0
    cut_check: dict[str, int] = field(default_factory=dict)
    common_px: int = 0  # removed pixels every method filled: the pixels scored
    methods: dict[str, MethodResult] = field(default_factory=dict)
    alternatives: dict[str, MethodResult] = field(default_factory=dict)

    @property
    def cut_px(self) -> int:
        return sum(h.n_px for h in self.holes)

    def best_alternative(self) -> tuple[str, float] | None:
        scored = [
            (name, r.errors.rmse)
            for name, r in self.alternatives.items()
            if r.errors and r.errors.n_px and not r.skipped
        ]
        return min(scored, key=lambda item: item[1]) if scored else None

    def rmse(self, name: str) -> float:
        result = self.methods.get(name) or self.alternatives.get(name)
        return result.errors.rmse if result and result.errors else math.nan

    def as_dict(self) -> dict[str, Any]:
        best = self.best_alternative()
        per_hole = []
        for hole in self.holes:
            record = hole.as_dict(self.resolution_m)
            record["rmse"] = {
                name: _finite(r.per_hole_rmse.get(hole.hole_id, math.nan))
                for name, r in {**self.methods, **self.alternatives}.items()
                if r.errors
            }
            per_hole.append(record)
        return {
            "survey": self.survey,
            "model": self.model,
            "inputs": self.inputs,
            "resolution_m": _finite(self.resolution_m),
            "z_unit_m": self.z_unit_m,
            "skipped": self.skipped or None,
            "n_holes": len(self.holes),
            "cut_px": self.cut_px,
            "scored_px": self.common_px,
            "points_removed": self.points_removed,
            "cut_check": self.cut_check,
            "methods": {k: v.as_dict() for k, v in self.methods.items()},
            "alternatives": {k: v.as_dict() for k, v in self.alternatives.items()},
            "best_alternative": best[0] if best else None,
            "default_vs_best_alternative": _finite(self.rmse("default") / best[1]) if best and best[1] else None,
            "mls_vs_idw": _finite(self.rmse("mls") / self.rmse("idw")) if self.rmse("idw") else None,
            "mls_vs_idw_nocause": _finite(self.rmse("mls-nocause") / self.rmse("idw-nocause"))
            if self.rmse("idw-nocause")
            else None,
            "holes": per_hole,
        }


@dataclass
class FillBenchmark:
    """Every survey and model of one benchmark, with the settings it ran with."""

    settings: dict[str, Any]
    surveys: list[SurveyResult] = field(default_factory=list)
    seconds: float = math.nan

    def as_dict(self) -> dict[str, Any]:
        return {
            "settings": self.settings,
            "seconds": _finite(self.seconds),
            "summary": summarize(self),
            "surveys": [s.as_dict() for s in self.surveys],
        }


def summarize(benchmark: FillBenchmark) -> dict[str, Any]:
    """Pooled errors per model and method, the targets, and the default run's stage times."""
    out: dict[str, Any] = {}
    for model in dict.fromkeys(s.model for s in benchmark.surveys):
        done = [s for s in benchmark.surveys if s.model == model and not s.skipped]
        pooled: dict[str, ErrorStats] = {}
        for survey in done:
            for name, result in {**survey.methods, **survey.alternatives}.items():
                if result.errors:
                    pooled[name] = pooled.get(name, ErrorStats()) + result.errors
        ratios = {s.survey: s.rmse("default") / best[1] for s in done if (best := s.best_alternative()) and best[1] > 0}
        mls_idw = {s.survey: s.rmse("mls") / s.rmse("idw") for s in done if s.rmse("idw") > 0}
        mls_idw_nocause = {
            s.survey: s.rmse("mls-nocause") / s.rmse("idw-nocause") for s in done if s.rmse("idw-nocause") > 0
        }
        rasterize = sum(
            s.methods["default"].stage_seconds.get("rasterize", 0.0) for s in done if "default" in s.methods
        )
        fill = sum(s.methods["default"].stage_seconds.get("fill", 0.0) for s in done if "default" in s.methods)
        out[model] = {
            "surveys": len(done),
            "skipped_surveys": {s.survey: s.skipped for s in benchmark.surveys if s.model == model and s.skipped},
            "holes": sum(len(s.holes) for s in done),
            "cut_px": sum(s.cut_px for s in done),
            "pooled": {name: stats.as_dict() for name, stats in pooled.items()},
            "target_default_vs_best_alternative": {
                "limit": 0.85,
                "met": sum(r <= 0.85 for r in ratios.values() if math.isfinite(r)),
                "of": sum(math.isfinite(r) for r in ratios.values()),
                "ratios": {k: _finite(v) for k, v in ratios.items()},
            },
            "target_mls_vs_idw": {
                "limit": 0.5,
                "met": sum(r <= 0.5 for r in mls_idw.values() if math.isfinite(r)),
                "of": sum(math.isfinite(r) for r in mls_idw.values()),
                "ratios": {k: _finite(v) for k, v in mls_idw.items()},
            },
            "target_mls_vs_idw_nocause": {
                "limit": 0.5,
                "met": sum(r <= 0.5 for r in mls_idw_nocause.values() if math.isfinite(r)),
                "of": sum(math.isfinite(r) for r in mls_idw_nocause.values()),
                "ratios": {k: _finite(v) for k, v in mls_idw_nocause.items()},
            },
            "default_run_seconds": {
                "rasterize": _finite(rasterize),
                "fill": _finite(fill),
                "fill_over_rasterize": _finite(fill / rasterize) if rasterize else None,
            },
        }
    return out


def evaluate_fill(
    surveys: list[list[str]],
    out_dir: str | os.PathLike,
    config: Config,
    *,
    names: list[str] | None = None,
    n_holes: int = 20,
    seed: int = 0,
    models: tuple[str, ...] = ("dsm",),
    methods: tuple[str, ...] = tuple(PIPELINE_RUNS),
    alternatives: tuple[str, ...] = tuple(ALTERNATIVES),
    resolution_m: float | None = None,
    crs: dict[str, str] | None = None,
    margin_px: int = 4,
    min_size_m: float = 2.0,
    max_size_m: float = 50.0,
    client: Any = None,
    scheduler: str | None = None,
    on_survey: Callable[[SurveyResult], None] | None = None,
) -> FillBenchmark:
    """Run the fill benchmark on surveys and write ``fill_eval.json`` into ``out_dir``.

    Parameters
    ----------
    surveys : list of list of str
        Each survey's inputs (files, folders or globs, as for ``holefill run``).
    out_dir : path-like
        Where the cut copies, the runs and ``fill_eval.json`` go; inputs are never modified.
    config : Config
        The base configuration; the benchmark overrides ``grid.resolution_m`` (when
        ``resolution_m`` is given or a survey is sparse), ``filter.keep_classes`` (DTM),
        ``fill.*`` per method, ``output.keep_unfilled`` and ``flightplan.enabled`` (off).
    names : list of str, optional
        A name per survey (default: the file or folder name).
    n_holes, seed : int
        Holes per survey and model, and the seed they are drawn from (with the
        survey's name and the model, so a survey gets the same holes in any company).
    models : tuple of {"dsm", "dtm"}
    methods : tuple of str
        Keys of :data:`PIPELINE_RUNS`; ``default`` is always run (first).
    alternatives : tuple of str
        Keys of :data:`ALTERNATIVES`.
    resolution_m : float, optional
        Pixel size for every survey; default: :func:`choose_resolution` per survey.
    crs : dict, optional
        ``survey.crs`` per survey name (``"*"``: every survey) for files without one.
    client, scheduler
        A Dask client, or a scheduler address; default: one local cluster for all runs.
    on_survey : callable, optional
        Called with each :class:`SurveyResult` when it is done (progress).
    """
    from .run import _dask_client

    unknown = [m for m in methods if m not in PIPELINE_RUNS] + [a for a in alternatives if a not in ALTERNATIVES]
    unknown += [m for m in models if m not in MODELS]
    if unknown:
        raise ConfigError(
            f"unknown benchmark method or model {unknown}; methods: {list(PIPELINE_RUNS)}, "
            f"alternatives: {list(ALTERNATIVES)}, models: {list(MODELS)}"
        )
    if config.survey.target_crs:
        raise ConfigError("the fill benchmark cuts points in their own CRS: survey.target_crs must be empty")
    methods = ("default", *(m for m in methods if m != "default"))
    names = names or [survey_name(inputs) for inputs in surveys]
    if len(set(names)) != len(names):
        raise ConfigError(f"survey names must be unique, got {names}")
    crs = crs or {}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    benchmark = FillBenchmark(
        settings={
            "n_holes": n_holes,
            "seed": seed,
            "models": list(models),
            "methods": list(methods),
            "alternatives": list(alternatives),
            "resolution_m": resolution_m,
            "margin_px": margin_px,
            "size_range_m": [min_size_m, max_size_m],
            "grass": shutil.which("grass") or None,
        }
    )
    base = config.replace("flightplan", source="fill benchmark", enabled=False)
    with _dask_client(client, scheduler, base) as dask_client:
        for model_index, model in enumerate(models):
            for name, inputs in zip(names, surveys):
                survey_config = base
                survey_crs = crs.get(name) or crs.get("*")
                if survey_crs:
                    survey_config = survey_config.replace("survey", source="--crs", crs=survey_crs)
                if MODELS[model]:
                    survey_config = survey_config.replace("filter", source=f"model {model}", **MODELS[model])
                rng = np.random.default_rng([seed, zlib.crc32(name.encode()), model_index])
                result = _evaluate_survey(
                    name,
                    inputs,
                    out / model / name,
                    survey_config,
                    model=model,
                    rng=rng,
                    n_holes=n_holes,
                    methods=methods,
                    alternatives=alternatives,
                    resolution_m=resolution_m,
                    margin_px=margin_px,
                    size_range_m=(min_size_m, max_size_m),
                    client=dask_client,
                )
                benchmark.surveys.append(result)
                benchmark.seconds = time.perf_counter() - started
                write_json(
                    out / "fill_eval.json", benchmark.as_dict()
                )  # so far: a long benchmark can be read while it runs
                if on_survey is not None:
                    on_survey(result)
    benchmark.seconds = time.perf_counter() - started
    write_json(out / "fill_eval.json", benchmark.as_dict())
    return benchmark


def survey_name(inputs: list[str]) -> str:
    """A survey's name: its file or folder name (the first one's, + the number of others)."""
    first = Path(inputs[0].rstrip("/"))
    return first.name if len(inputs) == 1 else f"{first.stem}+{len(inputs) - 1}"


def _evaluate_survey(
    name: str,
    inputs: list[str],
    folder: Path,
    config: Config,
    *,
    model: str,
    rng: np.random.Generator,
    n_holes: int,
    methods: tuple[str, ...],
    alternatives: tuple[str, ...],
    resolution_m: float | None,
    margin_px: int,
    size_range_m: tuple[float, float],
    client: Any,
) -> SurveyResult:
    from .io.raster import read_raster
    from .run import run_survey
    from .survey import scan_survey

    result = SurveyResult(survey=name, model=model, inputs=list(inputs))
    try:
        survey = scan_survey(inputs, crs=config.survey.crs, on_error=config.survey.on_error)
    except HolefillError as e:
        result.skipped = f"cannot be read: {e}"
        return result
    result.z_unit_m = survey.vertical_unit_m
    if resolution_m is None:
        area = sum((t.bounds[2] - t.bounds[0]) * (t.bounds[3] - t.bounds[1]) for t in survey.tiles)
        area_m2 = area * survey.horizontal_unit_m**2
        resolution_m = choose_resolution(sum(t.header.point_count for t in survey.tiles), area_m2)
    result.resolution_m = resolution_m
    if resolution_m != config.grid.resolution_m:  # the cell stays about as large, on the new lattice
        cell_px = max(16, round(config.grid.cell_size_m / resolution_m))
        config = config.replace(
            "grid", source="fill benchmark", resolution_m=resolution_m, cell_size_m=cell_px * resolution_m
        )
    reference_config = config.replace("holes", source="fill benchmark", enabled=False)
    try:
        run_survey(inputs, folder / "reference", reference_config, client=client)
    except HolefillError as e:
        result.skipped = f"reference run failed: {e}"
        return result
    if not (folder / "reference" / "dsm.vrt").exists():
        result.skipped = "the reference run wrote no raster (no point of the kept classes)"
        return result
    reference, transform, crs_wkt = read_raster(folder / "reference" / "dsm.vrt")
    labels, holes = place_holes(
        reference,
        n_holes=n_holes,
        rng=rng,
        pixel_size_m=resolution_m,
        min_size_m=size_range_m[0],
        max_size_m=size_range_m[1],
        margin_px=margin_px,
        edge_px=math.ceil(2 * config.holes.footprint_block_m / resolution_m),
    )
    result.holes = holes
    if not holes:
        result.skipped = "no place is measured over a 2 m hole and its margin"
        return result
    _write_cut_holes(folder / "cut_holes.gpkg", labels, transform, crs_wkt, holes, resolution_m)
    cut_inputs = []
    for tile in survey.tiles:
        target = folder / "cut" / f"{tile.index:04d}_{tile.name}"
        result.points_removed += cut_points(tile.path, target, labels, transform)
        cut_inputs.append(str(target))
    cut = labels > 0
    deepest_m = max(h.max_distance_px for h in holes) * resolution_m
    fill_limits = {
        "max_distance_m": max(config.fill.max_distance_m, deepest_m + 2 * resolution_m),
        "max_area_m2": max(config.fill.max_area_m2, (max(h.n_px for h in holes) + 1) * resolution_m**2),
    }
    unfilled = None
    fills: dict[str, np.ndarray] = {}
    for method in methods:
        run_config = config.replace("fill", source=f"method {method}", **{**fill_limits, **PIPELINE_RUNS[method]})
        if method == "default":
            run_config = run_config.replace("output", source="fill benchmark", keep_unfilled=True)
        t0 = time.perf_counter()
        try:
            summary = run_survey(cut_inputs, folder / "runs" / method, run_config, client=client)
        except HolefillError as e:
            result.methods[method] = MethodResult(skipped=f"run failed: {e}")
            continue
        result.methods[method] = MethodResult(seconds=time.perf_counter() - t0, stage_seconds=summary.stage_seconds)
        filled, filled_transform, _ = read_raster(folder / "runs" / method / "dsm.vrt")
        fills[method] = align(filled, filled_transform, transform, reference.shape)
        if method == "default":
            raw, raw_transform, _ = read_raster(folder / "runs" / method / "dsm_unfilled.vrt")
            unfilled = align(raw, raw_transform, transform, reference.shape)
            result.cut_check = {
                "cut_px_with_data": int(np.isfinite(unfilled[cut]).sum()),
                "other_px_changed": int(
                    (~cut & (np.isfinite(reference) != np.isfinite(unfilled))).sum()
                    + (~cut & np.isfinite(reference) & np.isfinite(unfilled) & (reference != unfilled)).sum()
                ),
            }
            if any(result.cut_check.values()):
                logger.warning("%s (%s): the cut run differs from the reference: %s", name, model, result.cut_check)
    if unfilled is not None:
        for alternative in alternatives:
            t0 = time.perf_counter()
            try:
                filled = ALTERNATIVES[alternative](unfilled, labels)
            except AlternativeUnavailable as e:
                result.alternatives[alternative] = MethodResult(skipped=str(e))
                continue
            result.alternatives[alternative] = MethodResult(seconds=time.perf_counter() - t0)
            fills[alternative] = np.where(cut, filled, np.nan)
    # every method is scored on the same pixels: those every method filled; what one left empty is counted apart
    common = cut & np.isfinite(reference)
    for filled in fills.values():
        common &= np.isfinite(filled)
    result.common_px = int(common.sum())
    for name_, filled in fills.items():
        record = result.methods.get(name_) or result.alternatives[name_]
        _score(record, filled, reference, labels, common)
    return result


def _score(record: MethodResult, filled: np.ndarray, reference: np.ndarray, labels: np.ndarray, common: np.ndarray):
    """Errors of one method on the common pixels; its own empty removed pixels counted apart."""
    record.errors = fill_errors(filled, reference, common)
    record.errors.n_unfilled = int((labels > 0)[np.isfinite(reference) & ~np.isfinite(filled)].sum())
    for hole_id, box, _ in _hole_windows(labels):
        record.per_hole_rmse[hole_id] = fill_errors(
            filled[box], reference[box], common[box] & (labels[box] == hole_id)
        ).rmse


def _write_cut_holes(
    path: Path, labels: np.ndarray, transform: Any, crs_wkt: str, holes: list[CutHole], pixel_size_m: float
) -> None:
    from .io.raster import label_polygons
    from .io.vector import write_layer

    polygons = label_polygons(labels, transform)
    path.unlink(missing_ok=True)
    records = []
    for hole in holes:
        record = hole.as_dict(pixel_size_m)
        record["bbox_rc"] = ",".join(map(str, record["bbox_rc"]))
        records.append(record)
    write_layer(
        path,
        "cut_holes",
        records,
        [polygons[h.hole_id] for h in holes],
        crs_wkt=crs_wkt,
        geometry_type="MultiPolygon",
    )


# -- reporting ----------------------------------------------------------------------------------


def write_json(path: str | os.PathLike, data: dict[str, Any]) -> Path:
    """Write a report as strict JSON (no NaN: missing values are null)."""
    import json

    path = Path(path)
    path.write_text(json.dumps(_no_nan(data), indent=1, allow_nan=False) + "\n")
    return path


def _no_nan(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _no_nan(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_no_nan(v) for v in value]
    if isinstance(value, np.generic):
        return _no_nan(value.item())
    return value


def format_table(benchmark: FillBenchmark) -> str:
    """A plain-text table: one row per survey, model and method (pipeline runs, then alternatives)."""
    lines = [
        f"{'model':5} {'survey':34} {'px':>4} {'holes':>5} {'method':16} {'RMSE':>8} {'MAE':>8} "
        f"{'max':>8} {'bias':>8} {'n px':>7} {'unfilled':>8}"
    ]

    def number(value: float) -> str:
        return f"{value:8.3f}" if math.isfinite(value) else f"{'-':>8}"

    for survey in benchmark.surveys:
        head = f"{survey.model:5} {survey.survey[:34]:34} {_fmt_res(survey.resolution_m):>4} {len(survey.holes):5d}"
        if survey.skipped:
            lines.append(f"{head} skipped: {survey.skipped}")
            continue
        for name, result in {**survey.methods, **survey.alternatives}.items():
            if result.skipped or result.errors is None:
                lines.append(f"{head} {name:16} skipped: {result.skipped}")
                continue
            e = result.errors
            lines.append(
                f"{head} {name:16} {number(e.rmse)} {number(e.mae)} {number(e.max_abs)} {number(e.bias)} "
                f"{e.n_px:7d} {e.n_unfilled:8d}"
            )
    summary = summarize(benchmark)
    for model, s in summary.items():
        lines.append("")
        lines.append(f"{model}: {s['surveys']} surveys, {s['holes']} holes, {s['cut_px']} px (pooled over surveys)")
        for name, stats in s["pooled"].items():
            lines.append(
                f"  {name:16} RMSE {stats['rmse']}  MAE {stats['mae']}  max {stats['max_abs']}  "
                f"bias {stats['bias']}  n {stats['n_px']}  unfilled {stats['n_unfilled']}"
            )
        t = s["target_default_vs_best_alternative"]
        lines.append(f"  default RMSE <= 0.85 x best alternative's: {t['met']} of {t['of']} surveys")
        t = s["target_mls_vs_idw"]
        lines.append(f"  MLS RMSE <= 0.5 x IDW's: {t['met']} of {t['of']} surveys")
        t = s["target_mls_vs_idw_nocause"]
        lines.append(f"  the same, both by_cause = false: {t['met']} of {t['of']} surveys")
        d = s["default_run_seconds"]
        lines.append(
            f"  default run: rasterize {d['rasterize']} s, fill {d['fill']} s (ratio {d['fill_over_rasterize']})"
        )
    return "\n".join(lines)


def _fmt_res(resolution: float) -> str:
    return f"{resolution:g}" if math.isfinite(resolution) else "-"
