"""Tests of pipeline.io.vector's layer writing in parts, and of the wall layers written a few cells at a time."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pyogrio
import pytest
import shapely

from pipeline import outputs
from pipeline.holes.walls import Wall
from pipeline.io.vector import read_layer, write_layer, write_layer_in_parts
from pipeline.stages.find_walls import WallResult

CRS = "EPSG:2154"


def _features(n: int, seed: int) -> tuple[list[dict], list[shapely.Geometry]]:
    rng = np.random.default_rng(seed)
    records = [{"name": f"f{i}", "value": float(rng.normal()), "count": int(rng.integers(0, 9))} for i in range(n)]
    boxes = [shapely.box(x, y, x + 1 + i % 3, y + 2) for i, (x, y) in enumerate(rng.uniform(0, 100, (n, 2)))]
    return records, boxes


def _same_layers(a, b, layer: str) -> None:
    one, two = read_layer(a, layer), read_layer(b, layer)
    assert list(one.columns) == list(two.columns)
    assert one.drop(columns="geometry").equals(two.drop(columns="geometry"))
    assert one.geometry.geom_equals_exact(two.geometry, tolerance=0).all()
    assert pyogrio.read_info(a, layer=layer)["geometry_type"] == pyogrio.read_info(b, layer=layer)["geometry_type"]


@pytest.mark.parametrize("sizes", [(5,), (2, 3), (0, 4, 0, 1), (1, 1, 1, 1, 1)])
def test_a_layer_written_in_parts_is_the_layer_written_at_once(tmp_path, sizes):
    records, geometries = _features(sum(sizes), seed=len(sizes))
    write_layer(tmp_path / "once.gpkg", "things", records, geometries, crs_wkt=CRS, geometry_type="MultiPolygon")
    bounds = np.cumsum((0, *sizes))
    parts = [(records[a:b], geometries[a:b]) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    write_layer_in_parts(tmp_path / "parts.gpkg", "things", parts, crs_wkt=CRS, geometry_type="MultiPolygon")
    _same_layers(tmp_path / "once.gpkg", tmp_path / "parts.gpkg", "things")
    assert len(read_layer(tmp_path / "parts.gpkg", "things")) == sum(sizes)


def test_parts_without_records_give_the_empty_typed_layer(tmp_path):
    fields = {"name": "object", "value": "float64"}
    write_layer_in_parts(tmp_path / "a.gpkg", "empty", [([], []), ([], [])], crs_wkt=CRS, fields=fields,
                         geometry_type="Polygon")  # fmt: skip
    info = pyogrio.read_info(tmp_path / "a.gpkg", layer="empty")
    assert info["features"] == 0 and list(info["fields"]) == ["name", "value"] and info["geometry_type"] == "Polygon"


def _wall(x: float) -> Wall:
    return Wall(x, 0.0, x + 3.0, 4.0, 1.0, 7.5, 0.1, 0.4, 30, 8, (0.0, 0.0, 3.0, 4.0), (0.8, -0.6), 1.5)


def _cells(n_cells: int) -> list[WallResult]:
    rng = np.random.default_rng(4)
    cells = []
    for c in range(n_cells):
        k = int(rng.integers(0, 5))
        holes = [
            {"pixels": i + 1, "max_height_range": 2.5 * i, "missing_voxels": i, "top": 10.0 + i,
             "wkb": shapely.to_wkb(shapely.box(c * 10 + i, 0, c * 10 + i + 1, 1))}
            for i in range(k)
        ]  # fmt: skip
        cells.append(WallResult(f"{c}_0", holes, [_wall(c * 10.0 + j) for j in range(int(rng.integers(0, 4)))], 7))
    return cells


def test_wall_layers_written_a_few_cells_at_a_time_are_the_same(tmp_path, monkeypatch):
    """The vertical holes and walls of many cells, in parts of 3 features, give the layers of one part."""
    plan = SimpleNamespace(grid=SimpleNamespace(crs_wkt=CRS), pixel_area_m2=0.25,
                           survey=SimpleNamespace(horizontal_unit_m=1.0))  # fmt: skip
    cells = _cells(12)
    counts_once = outputs.write_wall_layers(tmp_path / "once.gpkg", plan, cells)
    monkeypatch.setattr(outputs, "WALL_LAYER_PART", 3)
    assert len(list(outputs._cell_groups(cells, "vertical_holes"))) > 3
    counts_parts = outputs.write_wall_layers(tmp_path / "parts.gpkg", plan, cells)
    assert counts_parts == counts_once
    assert counts_once["vertical_hole_groups"] == sum(len(c.vertical_holes) for c in cells) > 0
    assert counts_once["walls"] == sum(len(c.walls) for c in cells) > 0
    for layer in ("vertical_holes", "walls"):
        _same_layers(tmp_path / "once.gpkg", tmp_path / "parts.gpkg", layer)
