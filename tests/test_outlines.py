"""Tests of pipeline.holes.outlines: exact, merged, world, simplified and straight outlines."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
from rasterio.features import rasterize
from shapely import affinity
from shapely.geometry import MultiPolygon, Polygon

from pipeline import holes as H
from pipeline.grid import Grid
from pipeline.holes import outlines as O


def corner_angles(poly: Polygon) -> np.ndarray:
    """Interior turning angles (degrees, 0..180) at every vertex of the exterior."""
    xy = np.asarray(poly.exterior.coords)[:-1]
    a = np.roll(xy, 1, axis=0) - xy
    b = np.roll(xy, -1, axis=0) - xy
    cos = (a * b).sum(1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


def iou(a, b) -> float:
    return a.intersection(b).area / a.union(b).area


def test_exact_outline_follows_pixel_edges_and_keeps_islands():
    mask = np.zeros((30, 40), bool)
    mask[5:20, 8:30] = True
    mask[10:14, 15:20] = False  # an island of data inside the hole
    poly = O.mask_outline(mask, row_off=100, col_off=200)
    assert poly.is_valid and isinstance(poly, Polygon)
    assert poly.area == mask.sum()
    assert len(poly.interiors) == 1 and Polygon(poly.interiors[0]).area == 20
    assert poly.bounds == (208.0, 105.0, 230.0, 120.0)
    coords = np.asarray(poly.exterior.coords)
    assert np.array_equal(coords, np.round(coords)) and len(coords) == 5  # collinear vertices dropped


def test_label_outlines_one_polygon_per_label():
    labels = np.zeros((10, 10), np.int32)
    labels[1:3, 1:3] = 1
    labels[5:9, 5:7] = 2
    labels[0, 9] = -1  # settled small void: background
    out = O.label_outlines(labels)
    assert sorted(out) == [1, 2] and out[1].area == 4 and out[2].area == 8


def test_eight_connected_parts_touching_at_a_corner_are_valid():
    labels = np.zeros((6, 6), np.int32)
    labels[1:3, 1:3] = 1
    labels[3:5, 3:5] = 1
    out = O.label_outlines(labels, connectivity=8)
    assert out[1].is_valid and out[1].area == 8


def test_parts_from_cells_merge_into_the_whole_hole():
    n = 100
    r, c = np.mgrid[:n, :n]
    count = np.ones((n, n), np.uint32)
    blob = ((r - 50) / 30.0) ** 2 + ((c - 45) / 38.0) ** 2 < 1
    count[blob] = 0
    count[45:55, 40:50] = 1  # island
    grid = Grid(resolution=0.5, col_min=1000, row_top=3999, width=n, height=n, cell_px=32, halo_px=8, crs_wkt="")
    z = np.zeros((n, n), np.float32)
    parts = []
    for cell in grid.cells():
        sl = cell.halo_window.slices_within(grid.window)
        res = H.detect_cell_holes(
            count[sl], z[sl], z[sl], cell=cell, grid_window=grid.window, params=H.DetectParams(2.0)
        )
        outlines = O.label_outlines(res.labels, row_off=cell.window.row_off, col_off=cell.window.col_off)
        parts.extend(outlines.values())
    assert len(parts) > 4
    merged = O.merge_outlines(parts)
    whole = O.mask_outline(count == 0)
    assert isinstance(merged, Polygon) and merged.is_valid
    assert merged.symmetric_difference(whole).area == 0
    assert len(merged.interiors) == 1
    assert len(merged.exterior.coords) == len(whole.exterior.coords)  # no leftover cell-edge vertices
    world = O.to_world(merged, grid.transform)
    x0, y0, x1, y1 = world.bounds
    cols, rows = np.nonzero((count == 0).T)
    assert x0 == pytest.approx(grid.x_left + cols.min() * 0.5)
    assert y1 == pytest.approx(grid.y_top - rows.min() * 0.5)
    assert world.area == pytest.approx((count == 0).sum() * 0.25)
    assert world.exterior.is_ccw


def test_simplified_outline_is_valid_and_close():
    rect = affinity.rotate(Polygon([(20, 30), (80, 30), (80, 60), (20, 60)]), 30, origin="centroid")
    courtyard = affinity.rotate(Polygon([(40, 40), (60, 40), (60, 50), (40, 50)]), 30, origin=rect.centroid)
    mask = rasterize([rect.difference(courtyard)], out_shape=(100, 100)).astype(bool)
    exact = O.mask_outline(mask)
    simple = O.hole_outline(exact, mode="simplified")
    assert simple.is_valid and len(simple.interiors) == 1
    assert len(simple.exterior.coords) < len(exact.exterior.coords) / 3
    assert simple.area == pytest.approx(exact.area, rel=0.03)


def test_straight_outline_of_a_rotated_building_hole():
    rect = affinity.rotate(Polygon([(20, 30), (80, 30), (80, 60), (20, 60)]), 30, origin="centroid")
    courtyard = affinity.rotate(Polygon([(40, 38), (62, 38), (62, 52), (40, 52)]), 30, origin=rect.centroid)
    truth = rect.difference(courtyard)
    mask = rasterize([truth], out_shape=(100, 100)).astype(bool)
    straight = O.hole_outline(O.mask_outline(mask), mode="straight")
    assert isinstance(straight, Polygon) and straight.is_valid
    assert len(straight.exterior.coords) - 1 == 4 and len(straight.interiors) == 1
    assert np.allclose(corner_angles(straight), 90, atol=1.0)
    assert iou(straight, truth) > 0.95
    # the edges run along the building's directions (30 and 120 degrees)
    xy = np.asarray(straight.exterior.coords)
    e = np.diff(xy, axis=0)
    angles = np.mod(np.degrees(np.arctan2(e[:, 1], e[:, 0])), 90)
    assert np.allclose(angles, 30, atol=1.5)


def test_straight_outline_of_an_l_shape_is_exact():
    mask = np.zeros((60, 60), bool)
    mask[10:40, 10:20] = True
    mask[30:40, 10:45] = True
    straight = O.straight_outline(O.mask_outline(mask))
    assert len(straight.exterior.coords) - 1 == 6 and straight.area == mask.sum()


def test_straight_outline_peaks_option_keeps_oblique_angles():
    para = Polygon([(10, 10), (70, 10), (90, 10 + 20 * math.sqrt(3)), (30, 10 + 20 * math.sqrt(3))])  # 60 degrees
    mask = rasterize([para], out_shape=(60, 100)).astype(bool)
    exact = O.mask_outline(mask)
    peaks = O.straight_outline(exact, option="peaks")
    assert len(peaks.exterior.coords) - 1 == 4
    assert np.allclose(sorted(corner_angles(peaks)), [60, 60, 120, 120], atol=2.0)
    assert iou(peaks, para) > 0.95


def test_multipolygon_and_world_transform():
    mask = np.zeros((20, 20), bool)
    mask[1:4, 1:4] = True
    mask[10:15, 10:18] = True
    geom = O.mask_outline(mask)
    assert isinstance(geom, MultiPolygon) and len(geom.geoms) == 2
    grid = Grid(resolution=2.0, col_min=50, row_top=99, width=20, height=20, cell_px=16, halo_px=2, crs_wkt="")
    world = O.hole_outline(geom, mode="exact", transform=grid.transform)
    assert world.area == pytest.approx(mask.sum() * 4.0)
    assert shapely.is_valid(world)
    with pytest.raises(ValueError, match="mode"):
        O.hole_outline(geom, mode="wobbly")


def test_straight_outline_in_world_units():
    mask = np.zeros((60, 60), bool)
    mask[10:40, 10:20] = True
    mask[30:40, 10:45] = True
    grid = Grid(resolution=0.5, col_min=2000, row_top=5999, width=60, height=60, cell_px=32, halo_px=2, crs_wkt="")
    world = O.to_world(O.mask_outline(mask), grid.transform)
    straight = O.straight_outline(world, pixel_size=0.5)
    assert len(straight.exterior.coords) - 1 == 6 and straight.area == pytest.approx(world.area)


def test_label_polygons_keep_islands_of_every_size_as_gdal_gives_them():
    """Rings of unequal lengths (islands of 1, 4 and 15 pixels in one label, one of them an L) come through as
    GDAL's polygonize gives them, the same as shapely.geometry.shape builds them."""
    from affine import Affine
    from rasterio.features import shapes

    labels = np.zeros((20, 30), np.int32)
    labels[1:19, 1:29] = 3
    labels[3, 3] = 0
    labels[6:8, 6:8] = 0
    labels[10:13, 12:16] = 0
    labels[10, 16:19] = 0  # an L: a ring of 7 vertices beside squares of 5
    labels[15:17, 20:22] = 5  # another label inside
    transform = Affine(0.5, 0, 100.0, 0, -0.5, 200.0)
    got = O.label_polygons(labels, transform)
    expected = {
        int(value): shapely.geometry.shape(geometry)
        for geometry, value in shapes(labels, mask=labels > 0, transform=transform, connectivity=4)
    }
    assert sorted(got) == [3, 5]
    assert len(got[3].interiors) == 4
    for label, polygon in expected.items():
        assert shapely.to_wkb(got[label]) == shapely.to_wkb(polygon)


def test_polygonized_pieces_become_the_polygons_their_rings_make_one_by_one(rng):
    """The batched rings and polygons (label_outlines, label_polygons) are those a ring at a time
    made: the same coordinates in the same order, holes included (8-connected blobs with gaps)."""
    import scipy.ndimage as ndi
    from affine import Affine
    from rasterio.features import shapes

    from pipeline.holes.outlines import _polygons

    def one_by_one(geojson):
        rings = [shapely.linearrings(np.asarray(ring, dtype=np.float64)) for ring in geojson["coordinates"]]
        return shapely.polygons(rings[0], holes=rings[1:] or None)

    blobs = ndi.binary_opening(rng.random((90, 70)) < 0.55) ^ (rng.random((90, 70)) < 0.05)
    labels, _ = ndi.label(blobs, structure=np.ones((3, 3)))
    found = list(
        shapes(labels.astype(np.int32), mask=labels > 0, transform=Affine(0.5, 0, 10, 0, -0.5, 100), connectivity=8)
    )
    made = _polygons([geojson for geojson, _ in found])
    assert len(made) == len(found) > 100
    assert any(len(geojson["coordinates"]) > 1 for geojson, _ in found)  # some with holes
    for (geojson, _), polygon in zip(found, made, strict=True):
        assert shapely.to_wkb(polygon) == shapely.to_wkb(one_by_one(geojson))
    assert _polygons([]) == []
