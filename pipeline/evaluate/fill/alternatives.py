"""The usual alternatives the fills are compared with (:data:`ALTERNATIVES`).

GDAL fillnodata, nearest neighbour, a linear TIN (scipy), startinpy's natural-neighbour and Laplace
interpolation, and GRASS ``r.fillnulls``: each takes the unfilled raster and the hole
labels and returns a filled raster. GRASS runs in a temporary folder through rasterio
files; the others work on arrays.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import scipy.ndimage as ndi

from ...errors import HolefillError


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


def fill_nearest(heights: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Each hole pixel takes the height of the nearest measured pixel (``distance_transform_edt`` indices)."""
    known = np.isfinite(heights)
    if not known.any():
        return np.full(heights.shape, np.nan)
    rows, cols = ndi.distance_transform_edt(~known, return_distances=False, return_indices=True)
    return np.where(labels > 0, heights[rows, cols], np.nan)


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


#: The first GRASS release whose start-up script knows ``--tmp-project`` (before: ``--tmp-location``).
GRASS_TMP_PROJECT_SINCE = (8, 4)


def parse_grass_version(text: str) -> tuple[int, int]:
    """``(major, minor)`` from ``grass --version`` output (``GRASS GIS 8.2.1``)."""
    found = re.search(r"GRASS(?: GIS)?\s+(\d+)\.(\d+)", text)
    if found is None:
        raise AlternativeUnavailable(f"GRASS version not understood: {text.strip()[:80]!r}")
    return int(found.group(1)), int(found.group(2))


def grass_tmp_option(version: tuple[int, int]) -> str:
    """The start-up option that runs a command in a temporary XY project of this GRASS version."""
    return "--tmp-project" if version >= GRASS_TMP_PROJECT_SINCE else "--tmp-location"


def _grass_version(grass: str) -> tuple[int, int]:
    try:
        done = subprocess.run([grass, "--version"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError) as e:
        raise AlternativeUnavailable(f"GRASS GIS does not start ({e})") from None
    return parse_grass_version(done.stdout + done.stderr)


def fill_grass(heights: np.ndarray, labels: np.ndarray, *, timeout_s: float = 600.0) -> np.ndarray:
    """GRASS GIS ``r.fillnulls method=bicubic`` in a temporary XY project.

    Needs the ``grass`` start-up script on PATH; raises :class:`AlternativeUnavailable`
    otherwise or when GRASS fails.
    """
    grass = shutil.which("grass")
    if grass is None:
        raise AlternativeUnavailable("GRASS GIS is not installed ('grass' is not on PATH)")
    tmp_option = grass_tmp_option(_grass_version(grass))  # GRASS < 8.4 (Debian 12's 8.2) knows only --tmp-location
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
                [grass, tmp_option, "XY", "--exec", "bash", "-c", script],
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
    "nearest_alt": fill_nearest,
    "tin_linear": fill_tin_linear,
    "nni": fill_nni,
    "laplace": fill_laplace,
    "grass_fillnulls": fill_grass,
}
