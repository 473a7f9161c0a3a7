"""The direction of each flight line, from the pixels it covers (pure, mergeable).

A flight line's strip on the ground is long along track and as wide as the swath,
so the principal axis of the pixels whose highest return came from that line
(``point_source_id``, kept per pixel by stage 1) is its direction. Each cell sums
the pixel moments of every line in its core; sums merge across cells exactly, so
the direction does not depend on the cell size. A missed strip between two lines
is re-flown parallel to them, as the survey itself was flown.
"""

from __future__ import annotations

import math

import numpy as np

#: Per cell and flight line: pixel count and the first and second moments of global (row, col).
LINE_MOMENT_DTYPE = np.dtype(
    [("line", np.int64), ("n", np.float64), ("r", np.float64), ("c", np.float64),
     ("rr", np.float64), ("cc", np.float64), ("rc", np.float64)]
)  # fmt: skip


def line_moments(line_ids: np.ndarray, *, row_off: int, col_off: int) -> np.ndarray:
    """Moments of the pixels of every flight line in a raster (``line_ids``: -1 where none).

    Rows and columns are global grid indices (the raster's first pixel is
    ``(row_off, col_off)``), so moments of different cells add up.
    """
    rows, cols = np.nonzero(line_ids >= 0)
    if len(rows) == 0:
        return np.empty(0, LINE_MOMENT_DTYPE)
    lines = line_ids[rows, cols].astype(np.int64)
    r = rows.astype(np.float64) + row_off
    c = cols.astype(np.float64) + col_off
    unique, index = _small_ids(lines)
    out = np.zeros(len(unique), LINE_MOMENT_DTYPE)
    out["line"] = unique
    for name, values in (("n", np.ones_like(r)), ("r", r), ("c", c), ("rr", r * r), ("cc", c * c), ("rc", r * c)):
        out[name] = np.bincount(index, weights=values, minlength=len(unique))
    return out


def _small_ids(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(ids, return_inverse=True)`` of non-negative ids: counted, not sorted, where they are
    small (point source ids are 16-bit: a cell's 62,500 pixels in 0.5 ms, not 3 ms)."""
    if len(ids) == 0 or int(ids.max()) >= 1 << 20:
        return np.unique(ids, return_inverse=True)
    unique = np.flatnonzero(np.bincount(ids))
    position = np.zeros(int(unique[-1]) + 1, np.int64)
    position[unique] = np.arange(len(unique))
    return unique, position[ids]


def merge_line_moments(parts: list[np.ndarray]) -> np.ndarray:
    """Sum the moments of the same lines over many cells."""
    joined = np.concatenate(parts) if parts else np.empty(0, LINE_MOMENT_DTYPE)
    if len(joined) == 0:
        return joined
    unique, index = np.unique(joined["line"], return_inverse=True)
    out = np.zeros(len(unique), LINE_MOMENT_DTYPE)
    out["line"] = unique
    for name in ("n", "r", "c", "rr", "cc", "rc"):
        out[name] = np.bincount(index, weights=joined[name], minlength=len(unique))
    return out


def line_azimuths(moments: np.ndarray, *, min_elongation: float = 1.4) -> dict[int, float]:
    """Azimuth (degrees clockwise from grid north, 0-180) of every line whose strip is elongated.

    ``min_elongation`` is the ratio of the standard deviations along and across the
    principal axis: a uniform strip as long as it is wide has 1, a 300 m stretch of a
    200 m swath 1.5, a kilometre of it 5. Below it (a line clipped to a corner, a few
    stray returns) a line has no reliable direction, and the re-flight falls back to
    the hole's own long side.
    """
    out = {}
    for m in moments:
        n = m["n"]
        if n < 10:
            continue
        mr, mc = m["r"] / n, m["c"] / n
        var_r, var_c = m["rr"] / n - mr * mr, m["cc"] / n - mc * mc
        cov = m["rc"] / n - mr * mc
        values, vectors = np.linalg.eigh(np.array([[var_c, cov], [cov, var_r]]))
        if values[0] <= 0 or values[1] < min_elongation**2 * values[0]:
            continue
        d_col, d_row = vectors[:, 1]
        out[int(m["line"])] = math.degrees(math.atan2(d_col, -d_row)) % 180.0  # east, north (rows grow south)
    return out


def axial_mean(azimuths: list[float], weights: list[float]) -> float:
    """Weighted mean of directions modulo 180 degrees (NaN when none)."""
    if not azimuths:
        return math.nan
    angle = np.radians(2.0 * np.asarray(azimuths))
    w = np.asarray(weights, dtype=np.float64)
    s, c = float((w * np.sin(angle)).sum()), float((w * np.cos(angle)).sum())
    if math.hypot(s, c) < 1e-9 * w.sum():
        return math.nan
    return math.degrees(math.atan2(s, c)) / 2.0 % 180.0


def strip_azimuths(line_hist: np.ndarray, is_strip: np.ndarray, directions: dict[int, float]) -> np.ndarray:
    """Per hole, the mean direction of the flight lines on its rim (missed strips only; else NaN).

    A missed strip lies between flight lines flown in one direction; its re-flight is
    laid parallel to them. Lines weigh by the rim pixels they hold.
    """
    out = np.full(len(is_strip), np.nan)
    rows = line_hist["row"]
    for hole in np.flatnonzero(is_strip):
        entries = line_hist[rows == hole]
        known = [(directions[int(e["line"])], float(e["count"])) for e in entries if int(e["line"]) in directions]
        if known:
            out[hole] = axial_mean([a for a, _ in known], [w for _, w in known])
    return out
