"""Outlines of holes: polygons with exact pixel edges, simplified or straightened.

Polygons are built in *global pixel coordinates* (x = grid column, y = grid row,
pixel (r, c) covering [c, c + 1) x [r, r + 1)): every vertex is an integer there,
so the parts of one hole found in different cells share their edges exactly and
merge without slivers (:func:`merge_outlines`). :func:`to_world` then applies the
grid's affine transform (``Grid.transform``). Holes in holes (islands of data)
are kept as interior rings.

Modes (:func:`hole_outline`):

``"exact"``
    The pixel edges (collinear vertices removed).
``"simplified"``
    Douglas-Peucker with topology preserved, tolerance about one pixel.
``"straight"``
    Dominant directions, after Pohl and Feldmann, "Generating straight outlines of
    2D point sets and holes using dominant directions or orthogonal projections"
    ([STRAIGHT], ``seeds/straight-outlines-of-holes.txt``, section 3.1): for holes
    bordered by man-made structures. The simplified outline plays the part of the
    paper's concave hull; its edges vote, weighted by length, in an angle histogram;
    the peak is the main direction and the second one is perpendicular to it ("90 deg"
    option) or the second peak ("peaks" option); runs of consecutive edges close to
    one direction are replaced by one line through the centre of gravity of their
    vertices, and neighbouring lines meet at their intersection.

Pure functions: arrays and shapely geometries in, shapely geometries out.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import TypeAlias

import numpy as np
import shapely
from affine import Affine
from shapely.geometry import MultiPolygon, Polygon
from shapely.geometry.polygon import orient

__all__ = [
    "hole_outline",
    "label_outlines",
    "label_polygons",
    "mask_outline",
    "merge_outlines",
    "simplify_outline",
    "straight_outline",
    "to_world",
]

Polygonal: TypeAlias = Polygon | MultiPolygon
#: A fitted line: a point on it and its unit direction.
_Line: TypeAlias = tuple[np.ndarray, np.ndarray]


def label_outlines(
    labels: np.ndarray,
    *,
    row_off: int = 0,
    col_off: int = 0,
    connectivity: int = 4,
) -> dict[int, Polygonal]:
    """Exact pixel-edge polygons of every positive label.

    Parameters
    ----------
    labels : ndarray of int, shape (M, N)
        Part labels (e.g. ``CellHoles.labels``); values <= 0 are background.
    row_off, col_off : int
        Global grid row and column of ``labels[0, 0]`` (``cell.window.row_off`` ...).
    connectivity : {4, 8}
        As used to label: 8 joins pixels touching at a corner (the polygon then
        touches itself there and is returned as valid (multi)polygon parts).

    Returns
    -------
    dict of int to Polygon or MultiPolygon
        In global pixel coordinates.
    """
    labels = np.asarray(labels)
    if labels.ndim != 2:
        raise ValueError(f"labels must be a 2-dimensional array, got shape {labels.shape}")
    if connectivity not in (4, 8):
        raise ValueError(f"connectivity must be 4 or 8, got {connectivity!r}")
    mask = labels > 0
    if not mask.any():
        return {}
    # GDAL's polygonize, in memory (no file is opened); imported here so that importing
    # the hole kernels loads no I/O library (tests/test_layering.py)
    from rasterio.features import shapes

    found = list(
        shapes(
            labels.astype(np.int32, copy=False),
            mask=mask,
            connectivity=connectivity,
            transform=Affine.translation(col_off, row_off),
        )
    )
    pieces: dict[int, list[Polygon]] = {}
    for polygon, (_, value) in zip(_polygons([geojson for geojson, _ in found]), found, strict=True):
        pieces.setdefault(int(value), []).append(polygon)
    return {label: _clean(polys) for label, polys in sorted(pieces.items())}


def label_polygons(labels: np.ndarray, transform: Affine, *, connectivity: int = 4) -> dict[int, shapely.Geometry]:
    """Polygons with exact pixel edges of each positive label, in ``transform``'s coordinates.

    Holes in labels are kept as interiors; a label in several pieces is their union.
    Unlike :func:`label_outlines`, the pieces are taken as GDAL's polygonize gives them
    (vertex order kept), in the coordinates of ``transform`` (a raster's affine).
    """
    # GDAL's polygonize in memory, imported here like label_outlines' (no file is opened)
    from rasterio.features import shapes

    pieces: dict[int, list] = {}
    data = np.ascontiguousarray(labels, dtype=np.int32)
    found = list(shapes(data, mask=data > 0, transform=transform, connectivity=connectivity))
    for polygon, (_, value) in zip(_polygons([geometry for geometry, _ in found]), found, strict=True):
        pieces.setdefault(int(value), []).append(polygon)
    return {label: parts[0] if len(parts) == 1 else shapely.union_all(parts) for label, parts in pieces.items()}


def _polygons(geojsons: list[dict]) -> list[Polygon]:
    """GeoJSON polygons of GDAL's polygonize as shapely Polygons: every ring of every polygon made in
    one call, then every polygon in one more.

    ``shapely.geometry.shape`` hands the rings over as lists of tuples, read vertex by vertex
    in Python (two thirds of the vertical holes' outlines); a call per ring and per polygon was
    then most of what remained (9,000 vertical holes: 0.58 s). The same coordinates, in the same order.
    """
    if not geojsons:
        return []
    rings = [ring for geojson in geojsons for ring in geojson["coordinates"]]
    sizes = np.fromiter((len(ring) for ring in rings), np.int64, len(rings))
    coordinates = np.array([point for ring in rings for point in ring], dtype=np.float64)
    made = shapely.linearrings(coordinates, indices=np.repeat(np.arange(len(rings)), sizes))
    per_polygon = np.fromiter((len(geojson["coordinates"]) for geojson in geojsons), np.int64, len(geojsons))
    # each polygon's rings, its shell first: the first ring of an index is the shell, the others its holes
    return list(shapely.polygons(made, indices=np.repeat(np.arange(len(geojsons)), per_polygon)))


def mask_outline(
    mask: np.ndarray,
    *,
    row_off: int = 0,
    col_off: int = 0,
    connectivity: int = 4,
) -> Polygonal:
    """Exact pixel-edge (multi)polygon of the True pixels of ``mask`` (global pixel coordinates)."""
    outlines = label_outlines(
        np.asarray(mask, dtype=bool).astype(np.int32), row_off=row_off, col_off=col_off, connectivity=connectivity
    )
    return outlines.get(1, Polygon())


def merge_outlines(geoms: Iterable[Polygonal]) -> Polygonal:
    """One (multi)polygon from the parts of a hole found in several cells.

    Exact in pixel coordinates: shared cell edges dissolve; collinear vertices are removed.
    """
    geoms = [g for g in geoms if g is not None and not g.is_empty]
    if not geoms:
        return Polygon()
    return _clean([shapely.union_all(geoms)])


def to_world(geom: Polygonal, transform: Affine) -> Polygonal:
    """Apply an affine pixel-to-world transform (e.g. ``Grid.transform``); exteriors counter-clockwise."""
    a, b, c, d, e, f = transform.a, transform.b, transform.c, transform.d, transform.e, transform.f
    moved = shapely.affinity.affine_transform(geom, [a, b, d, e, c, f])
    return _orient(moved)


def simplify_outline(geom: Polygonal, *, tolerance: float = 1.0) -> Polygonal:
    """Douglas-Peucker simplification preserving topology (tolerance in the geometry's units)."""
    if geom.is_empty:
        return geom
    out = geom.simplify(tolerance, preserve_topology=True)
    return _clean([out]) if not out.is_valid else _orient(out)


def straight_outline(
    geom: Polygonal,
    *,
    pixel_size: float = 1.0,
    tolerance: float | None = None,
    bin_deg: float = 5.0,
    option: str = "90",
    max_deviation_deg: float = 25.0,
    min_peak_separation_deg: float = 30.0,
    max_area_change: float = 0.3,
) -> Polygonal:
    """Straight outline from dominant directions ([STRAIGHT] section 3.1).

    Parameters
    ----------
    geom : Polygon or MultiPolygon
        An exact or simplified outline.
    pixel_size : float
        Size of a pixel in the geometry's units (1 in pixel coordinates, the
        resolution in world coordinates).
    tolerance : float, optional
        Douglas-Peucker tolerance of the first simplification (the paper's
        concave hull), in the geometry's units; default ``1.5 * pixel_size``: a
        staircase of pixel edges along a slanted wall strays up to about 1.4
        pixels from its chord.
    bin_deg : float
        Width of the angle histogram's bins.
    option : {"90", "peaks"}
        Second direction perpendicular to the first, or the histogram's second peak.
    max_deviation_deg : float
        Edges further than this from both directions are kept as they are.
    min_peak_separation_deg : float
        "peaks": the second peak must be at least this far from the first.
    max_area_change : float
        If straightening changes a polygon's area by more than this fraction (or
        makes it invalid), its simplified outline is returned instead.

    Returns
    -------
    Polygon or MultiPolygon
    """
    if option not in ("90", "peaks"):
        raise ValueError(f"option must be '90' or 'peaks', got {option!r}")
    if geom.is_empty:
        return geom
    if tolerance is None:
        tolerance = 1.5 * pixel_size
    simplified = simplify_outline(geom, tolerance=tolerance)
    polys = list(simplified.geoms) if isinstance(simplified, MultiPolygon) else [simplified]
    rings = [np.asarray(r.coords)[:-1] for p in polys for r in (p.exterior, *p.interiors)]
    directions = _dominant_directions(rings, bin_deg, option, min_peak_separation_deg)
    if directions is None:
        return simplified
    out = []
    for poly in polys:
        shift = 5.0 * tolerance + pixel_size
        shell = _straighten_ring(np.asarray(poly.exterior.coords)[:-1], directions, max_deviation_deg, shift)
        holes = [
            _straighten_ring(np.asarray(r.coords)[:-1], directions, max_deviation_deg, shift) for r in poly.interiors
        ]
        candidate = Polygon(shell, [h for h in holes if len(h) >= 3]) if len(shell) >= 3 else Polygon()
        if not candidate.is_valid:
            candidate = _clean([shapely.make_valid(candidate)])
        if candidate.is_empty or abs(candidate.area - poly.area) > max_area_change * poly.area:
            candidate = poly
        out.append(candidate)
    return _clean(out)


def hole_outline(
    geom: Polygonal,
    *,
    mode: str = "exact",
    transform: Affine | None = None,
    tolerance_px: float | None = None,
    **straight_options,
) -> Polygonal:
    """A hole's outline in one of the modes, in world coordinates.

    Parameters
    ----------
    geom : Polygon or MultiPolygon
        Exact outline in global pixel coordinates (:func:`label_outlines`,
        :func:`merge_outlines`).
    mode : {"exact", "simplified", "straight"}
    transform : Affine, optional
        Pixel-to-world transform (``Grid.transform``); None keeps pixel coordinates.
    tolerance_px : float, optional
        Simplification tolerance in pixels; default 1 ("simplified"), 1.5 ("straight").
    **straight_options
        Passed to :func:`straight_outline`.

    Returns
    -------
    Polygon or MultiPolygon
    """
    if mode == "exact":
        out = _clean([geom])
    elif mode == "simplified":
        out = simplify_outline(geom, tolerance=1.0 if tolerance_px is None else tolerance_px)
    elif mode == "straight":
        out = straight_outline(geom, tolerance=1.5 if tolerance_px is None else tolerance_px, **straight_options)
    else:
        raise ValueError(f"mode must be 'exact', 'simplified' or 'straight', got {mode!r}")
    return out if transform is None else to_world(out, transform)


# --------------------------------------------------------------------------------------
# internals
# --------------------------------------------------------------------------------------


def _clean(geoms: list) -> Polygonal:
    """Valid, oriented (multi)polygon without collinear vertices, from polygonal pieces."""
    polys: list[Polygon] = []
    for g in geoms:
        if g is None or g.is_empty:
            continue
        if not g.is_valid:
            g = shapely.make_valid(g)
        for part in getattr(g, "geoms", [g]):
            if isinstance(part, Polygon) and not part.is_empty and part.area > 0:
                polys.append(part)
            elif isinstance(part, (MultiPolygon, shapely.GeometryCollection)):
                polys.extend(p for p in part.geoms if isinstance(p, Polygon) and p.area > 0)
    if not polys:
        return Polygon()
    merged = polys[0] if len(polys) == 1 else shapely.union_all(polys)
    merged = merged.simplify(0)  # drops collinear vertices only
    return _orient(merged)


def _orient(geom: Polygonal) -> Polygonal:
    if isinstance(geom, Polygon):
        return orient(geom, 1.0)
    if isinstance(geom, MultiPolygon):
        return MultiPolygon([orient(p, 1.0) for p in geom.geoms])
    return geom


def _axial_diff(a: np.ndarray, b: float) -> np.ndarray:
    """Smallest difference between undirected angles (radians, modulo pi)."""
    d = np.mod(a - b, np.pi)
    return np.minimum(d, np.pi - d)


def _dominant_directions(rings, bin_deg, option, min_sep_deg) -> tuple[float, float] | None:
    """The two dominant edge directions (radians in [0, pi)) of a length-weighted histogram."""
    angles, lengths = [], []
    for ring in rings:
        if len(ring) < 3:
            continue
        e = np.roll(ring, -1, axis=0) - ring
        angles.append(np.mod(np.arctan2(e[:, 1], e[:, 0]), np.pi))
        lengths.append(np.hypot(e[:, 0], e[:, 1]))
    if not angles:
        return None
    ang, length = np.concatenate(angles), np.concatenate(lengths)
    if length.sum() <= 0:
        return None
    width = math.radians(bin_deg)
    n_bins = max(int(round(math.pi / width)), 1)
    bins = np.minimum((ang / (math.pi / n_bins)).astype(int), n_bins - 1)
    hist = np.bincount(bins, length, minlength=n_bins)

    def refine(bin_index: int) -> float:
        centre = (bin_index + 0.5) * math.pi / n_bins
        near = _axial_diff(ang, centre) <= math.pi / n_bins
        doubled = np.sum(length[near] * np.exp(2j * ang[near]))  # axial mean
        return float(np.mod(np.angle(doubled) / 2, np.pi))

    beta = refine(int(np.argmax(hist)))
    if option == "90":
        gamma = float(np.mod(beta + math.pi / 2, math.pi))
    else:
        centres = (np.arange(n_bins) + 0.5) * math.pi / n_bins
        far = _axial_diff(centres, beta) >= math.radians(min_sep_deg)
        if not far.any() or hist[far].max() <= 0:
            gamma = float(np.mod(beta + math.pi / 2, math.pi))
        else:
            gamma = refine(int(np.flatnonzero(far)[np.argmax(hist[far])]))
    return beta, gamma


def _straighten_ring(
    ring: np.ndarray, directions: tuple[float, float], max_dev_deg: float, max_shift: float
) -> np.ndarray:
    """Replace runs of edges along a dominant direction by one line each ([STRAIGHT] 3.1)."""
    n = len(ring)
    if n < 3:
        return ring
    e = np.roll(ring, -1, axis=0) - ring
    ang = np.mod(np.arctan2(e[:, 1], e[:, 0]), np.pi)
    dev = np.stack([_axial_diff(ang, d) for d in directions])
    label = np.where(dev.min(axis=0) <= math.radians(max_dev_deg), dev.argmin(axis=0), -1)
    change = np.flatnonzero(label != np.roll(label, 1))
    if len(change) == 0:
        return ring  # a single direction all round cannot be a closed polygon: leave it
    start = int(change[0])  # begin at a run boundary so that no run wraps around
    ring = np.roll(ring, -start, axis=0)
    label = np.roll(label, -start)
    # runs: maximal stretches of one dominant label; edges far from both are runs of one
    runs: list[tuple[int, int, int]] = []  # (label, first edge, last edge)
    i = 0
    while i < n:
        j = i
        if label[i] >= 0:
            while j + 1 < n and label[j + 1] == label[i]:
                j += 1
        runs.append((int(label[i]), i, j))
        i = j + 1
    lines: list[_Line | None] = []
    for lab, i, j in runs:
        if lab < 0:
            lines.append(None)
            continue
        verts = ring[[(k % n) for k in range(i, j + 2)]]
        d = np.array([math.cos(directions[lab]), math.sin(directions[lab])])
        lines.append((verts.mean(axis=0), d))
    corners: list[np.ndarray] = []
    for k in range(len(runs)):
        a, b = lines[k - 1], lines[k]  # the runs before and after vertex at the start of run k
        v = ring[runs[k][1]]
        if a is not None and b is not None:
            p = _intersect(a, b)
            if p is None or np.hypot(*(p - v)) > max_shift:  # nearly parallel: step between them
                corners.extend([_project(v, a), _project(v, b)])
            else:
                corners.append(p)
        elif a is not None:
            corners.append(_project(v, a))
        elif b is not None:
            corners.append(_project(v, b))
        else:
            corners.append(v)
    out = np.asarray(corners)
    keep = np.ones(len(out), bool)
    keep[1:] = np.hypot(*(out[1:] - out[:-1]).T) > 1e-9
    return out[keep]


def _project(v: np.ndarray, line: _Line) -> np.ndarray:
    p, d = line
    return p + d * float((v - p) @ d)


def _intersect(a: _Line, b: _Line) -> np.ndarray | None:
    (p, d), (q, f) = a, b
    det = d[0] * (-f[1]) - d[1] * (-f[0])
    if abs(det) < math.sin(math.radians(20)):
        return None  # nearly parallel
    t = ((q - p)[0] * (-f[1]) - (q - p)[1] * (-f[0])) / det
    return p + t * d
