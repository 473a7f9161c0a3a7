"""Artificial holes: their shapes, where they go (:func:`place_holes`) and the survey's pixel size.

Pure array functions: a seeded :class:`numpy.random.Generator` draws every choice.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.ndimage as ndi

from .metrics import _finite

#: Hole shapes placed by :func:`place_holes`.
SHAPES = ("disc", "rectangle", "blob")

#: Pixel sizes (m) tried for a survey, finest first (see :func:`choose_resolution`).
RESOLUTIONS_M = (1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0)


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
    distance = _distance_to_unfree(free)
    low, high = math.log(max(min_size_m, pixel_size_m)), math.log(max(max_size_m, min_size_m, pixel_size_m))
    for _ in range(tries_per_hole * n_holes):
        if len(holes) == n_holes:
            break
        size_m = math.exp(rng.uniform(low, high))
        kind = SHAPES[int(rng.integers(len(SHAPES)))]
        mask = hole_shape(kind, size_m / pixel_size_m, rng)
        corner = _find_place(mask, kind, distance, margin_px, rng)
        if corner is None:
            continue
        r0, c0 = corner
        hole = _cut_hole(len(holes) + 1, kind, size_m, mask, r0, c0, reference)
        labels[r0 : r0 + hole.height, c0 : c0 + hole.width][mask] = hole.hole_id
        holes.append(hole)
        _reserve(free, mask, r0, c0, margin_px)  # the hole and its margin are no place for another hole
        distance = _distance_to_unfree(free)
    return labels, holes


def _distance_to_unfree(free: np.ndarray) -> np.ndarray:
    """Per pixel, the distance (px) to the nearest pixel that is not free (the raster's outside included)."""
    return ndi.distance_transform_edt(np.pad(free, 1))[1:-1, 1:-1]


def _find_place(
    mask: np.ndarray, kind: str, distance: np.ndarray, margin_px: int, rng: np.random.Generator
) -> tuple[int, int] | None:
    """A random top-left corner where ``mask`` and its margin lie on free pixels, or None (one draw)."""
    h, w = mask.shape
    # a quick necessary condition on the centre (a disc needs room for its radius), then the exact test
    need = margin_px + (min(h, w) / 2 - 1 if kind == "disc" else 0)
    candidates = np.flatnonzero(distance.ravel() > need)
    if not len(candidates):
        return None
    centre = int(candidates[rng.integers(len(candidates))])
    r0 = centre // distance.shape[1] - h // 2
    c0 = centre % distance.shape[1] - w // 2
    if r0 < 0 or c0 < 0 or r0 + h > distance.shape[0] or c0 + w > distance.shape[1]:
        return None
    if not np.all(distance[r0 : r0 + h, c0 : c0 + w][mask] > margin_px):
        return None
    return r0, c0


def _cut_hole(
    hole_id: int, kind: str, size_m: float, mask: np.ndarray, r0: int, c0: int, reference: np.ndarray
) -> CutHole:
    """The record of a hole placed with its top-left corner at ``(r0, c0)``."""
    h, w = mask.shape
    heights = reference[r0 : r0 + h, c0 : c0 + w][mask]
    inside = ndi.distance_transform_edt(np.pad(mask, 1))[1:-1, 1:-1]
    return CutHole(
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


def _reserve(free: np.ndarray, mask: np.ndarray, r0: int, c0: int, margin_px: int) -> None:
    """Mark a hole placed at ``(r0, c0)`` and its margin as no longer free (in place)."""
    h, w = mask.shape
    near = ndi.distance_transform_edt(~np.pad(mask, margin_px)) <= margin_px
    rows = slice(r0 - margin_px, r0 + h + margin_px)
    cols = slice(c0 - margin_px, c0 + w + margin_px)
    keep_r = slice(max(0, -rows.start), near.shape[0] - max(0, rows.stop - free.shape[0]))
    keep_c = slice(max(0, -cols.start), near.shape[1] - max(0, cols.stop - free.shape[1]))
    free[max(0, rows.start) : rows.stop, max(0, cols.start) : cols.stop] &= ~near[keep_r, keep_c]


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
