"""Tile-grid inference (pipeline.survey.tile_grid) on small synthetic layouts and on the real tiles' headers."""

from __future__ import annotations

import pytest
import shapely

from pipeline.config import load_config
from pipeline.errors import InputDataError
from pipeline.plan import plan_survey
from pipeline.survey.scan import scan_survey
from pipeline.survey.tile_grid import grid_survey_area, infer_tile_grid


def grid_bounds(size, cols, rows, *, x0=700_000.0, y0=6_600_000.0, short=0.0, skip=()):
    """Bounds of a cols x rows block of square tiles, each stopping ``short`` before its max edges."""
    return [
        (x0 + i * size, y0 + j * size, x0 + (i + 1) * size - short, y0 + (j + 1) * size - short)
        for j in range(rows)
        for i in range(cols)
        if (i, j) not in skip
    ]


def test_a_block_of_tiles_is_a_grid_of_their_size():
    found = infer_tile_grid(grid_bounds(50.0, 3, 2, short=0.01), tolerance=0.1)
    assert found.grid is not None, found.reason
    assert (found.grid.size_x, found.grid.size_y) == (50.0, 50.0)
    assert found.grid.squares[0] == (14000, 132000) and len(set(found.grid.squares)) == 6
    assert found.grid.square_bounds(found.grid.squares[0]) == (700_000.0, 6_600_000.0, 700_050.0, 6_600_050.0)


def test_rectangular_tiles_and_a_tile_whose_data_stops_short():
    bounds = [(x, y, x + 500.0, y + 250.0) for x in (300_000.0, 300_500.0) for y in (5_000_000.0, 5_000_250.0)]
    bounds[0] = (300_000.0, 5_000_000.0, 300_441.7, 5_000_250.0)  # the data ends 58 m before the edge
    grid = infer_tile_grid(bounds, tolerance=0.5).grid
    assert grid is not None and (grid.size_x, grid.size_y) == (500.0, 250.0)


@pytest.mark.parametrize(
    "bounds, words",
    [
        ([(931118.57, 6449651.34, 931175.8, 6449693.76)], "one tile"),  # ign_bat.laz: a single crop
        ([(100.3, 200.7, 163.1, 251.2), (163.1, 200.7, 230.4, 251.2)], "do not lie on the edges"),
        (
            [(0.0, 0.0, 75.0, 50.0), (75.0, 0.0, 150.0, 50.0)],
            "distinct squares",
        ),  # 75 m tiles: 150 m squares would hold both
        ([(0.0, 0.0, 50.0, 50.0), (20.0, 0.0, 70.0, 50.0)], "distinct squares"),  # overlapping flight strips
    ],
)
def test_no_grid_without_strong_evidence(bounds, words):
    found = infer_tile_grid(bounds, tolerance=0.1)
    assert found.grid is None and words in found.reason, found.reason


def test_a_corridor_takes_the_other_axis_size():
    # lasr_bcts-like: tiles cut every 300 m along the corridor, the data never reaching their sides
    bounds = [
        (885022.37, 629157.18, 885210.15, 629399.99),
        (885024.09, 629400.0, 885217.09, 629699.99),
        (885026.3, 629700.0, 885223.96, 629999.99),
        (885028.41, 630000.0, 885228.88, 630219.48),
    ]
    grid = infer_tile_grid(bounds, tolerance=0.5).grid
    assert grid is not None and (grid.size_x, grid.size_y) == (300.0, 300.0)
    assert grid.squares == ((2950, 2097), (2950, 2098), (2950, 2099), (2950, 2100))


def test_names_confirm_the_grid_and_place_a_skipped_tile():
    names = [f"LHD_FXX_{x:04d}_{y:04d}_PTS_C_LAMB93_IGN69.laz" for y in (6802, 6803) for x in (299, 300)]
    bounds = [(x * 1000.0, (y - 1) * 1000.0, x * 1000.0 + 999.99, y * 1000.0 - 0.01) for y in (6802, 6803) for x in (299, 300)]  # fmt: skip
    grid = infer_tile_grid(bounds, names, tolerance=0.1).grid
    assert grid is not None and grid.naming == (1000, "upper-left") and "names" in grid.evidence
    assert grid.square_of_name("LHD_FXX_0301_6803_PTS_C_LAMB93_IGN69.laz") == (301, 6802)
    assert grid.square_of_name("bcts_1.laz") is None
    # names that do not fit every tile confirm nothing
    assert infer_tile_grid(bounds, ["a_0299_6802.laz"] * 4, tolerance=0.1).grid.naming is None


def test_a_missing_tile_enclosed_by_the_grid_is_inside_and_the_outer_edge_is_not():
    bounds = grid_bounds(100.0, 3, 3, skip={(1, 1), (2, 2)})
    grid = infer_tile_grid(bounds, tolerance=0.1).grid
    area = grid_survey_area(grid)
    assert area.missing == ((7001, 66001),)  # the middle; the missing corner is outside
    assert area.area.area == pytest.approx(8 * 100.0 * 100.0)
    assert not area.area.contains(shapely.Point(700_250.0, 6_600_250.0))


def test_a_skipped_tile_is_not_a_missing_tile():
    names = [f"t_{700_000 + 100 * i}_{6_600_000 + 100 * j}.laz" for j in range(3) for i in range(3) if (i, j) != (1, 1)]
    grid = infer_tile_grid(grid_bounds(100.0, 3, 3, skip={(1, 1)}), names, tolerance=0.1).grid
    assert grid.naming == (1, "lower-left")
    placed = grid_survey_area(grid, skipped_names=["t_700100_6600100.laz"])
    assert placed.missing == () and placed.skipped == ((7001, 66001),)
    assert placed.area.area == pytest.approx(8 * 100.0 * 100.0)  # the skipped square is exterior
    unplaced = grid_survey_area(grid, skipped_names=["corrupt.laz"])
    assert unplaced.missing == () and "cannot be placed" in unplaced.note


# -- real tiles (headers only) ----------------------------------------------------------------


@pytest.mark.parametrize(
    "pattern, size, first_square, naming",
    [
        ("ign_tile_770*_6277*.laz", 50.0, (770500.0, 6277500.0), (10, "upper-left")),
        ("lasr_bcts_*.laz", 300.0, (885000.0, 629100.0), None),
        ("ign_bridge_*.laz", 1000.0, (299000.0, 6801000.0), (1000, "upper-left")),
    ],
)
def test_real_tiles_lie_on_their_grid(shared_data, pattern, size, first_square, naming):
    survey = scan_survey([str(shared_data / pattern)])
    plan = plan_survey(survey, load_config())
    grid = plan.tile_grid
    assert grid is not None and (grid.size_x, grid.size_y) == (size, size)
    assert grid.naming == naming
    assert min(grid.square_bounds(s)[:2] for s in grid.squares) == first_square
    squares = shapely.union_all([shapely.box(*grid.square_bounds(s)) for s in grid.squares])
    assert plan.survey_area.equals(squares) and plan.area.missing_tiles == ()
    # the lattice covers the tiles' data, not the squares' empty margins beyond it (exterior anyway)
    data = shapely.union_all([shapely.box(*t.bounds) for t in survey.tiles])
    assert shapely.box(*plan.grid.bounds).contains(data)
    assert data.envelope.buffer(2 * plan.grid.resolution, join_style="mitre").contains(shapely.box(*plan.grid.bounds))


def test_single_crops_are_no_grid_and_keep_the_tile_extents(shared_data):
    survey = scan_survey([str(shared_data / "ign_bat.laz")])
    plan = plan_survey(survey, load_config())
    assert plan.tile_grid is None and plan.survey_area.equals(shapely.box(*survey.tiles[0].bounds))
    with pytest.raises(InputDataError, match='survey.area = "tiles" but the tiles lie on no grid: one tile'):
        plan_survey(survey, load_config(overrides=["survey.area=tiles"]))
    two = scan_survey([str(shared_data / "ign_bat.laz"), str(shared_data / "ign_pont_bridge.laz")])
    assert plan_survey(two, load_config()).tile_grid is None


def test_footprint_mode_and_an_aoi_infer_no_grid(shared_data, tmp_path):
    from pipeline.io.vector import write_layer

    survey = scan_survey([str(shared_data / "ign_tile_770*_6277*.laz")])
    assert plan_survey(survey, load_config(overrides=["survey.area=footprint"])).tile_grid is None
    aoi = write_layer(
        tmp_path / "aoi.gpkg",
        "aoi",
        [{"id": 1}],
        [shapely.box(770510, 6277510, 770640, 6277590)],
        crs_wkt=survey.crs_wkt,
    )
    plan = plan_survey(survey, load_config(), aoi=aoi)
    assert plan.tile_grid is None and plan.aoi_given and plan.area.source == "--aoi polygon"
