"""Runs on the real airborne surveys of ../shared/data (skipped when the folder is absent)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio

from pipeline.config import load_config
from pipeline.errors import CRSError
from pipeline.io.vector import list_layers, read_layer
from pipeline.run import run_survey
from pipeline.survey.scan import scan_survey

pytestmark = [pytest.mark.realdata, pytest.mark.slow]


def run(shared, names, out, client, *overrides, **kwargs):
    config = load_config(overrides=list(overrides))
    return run_survey([str(shared / n) for n in names], out, config, client=client, **kwargs)


def check_cog(path, epsg=None):
    with rasterio.open(path) as ds:
        assert ds.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
        assert ds.overviews(1) or ds.shape == (1, 1)  # a single pixel has no overview
        assert ds.crs is not None
        if epsg:
            assert ds.crs.to_epsg() == epsg


def test_adjacent_ign_tiles_match_the_ign_reference_dsm(shared_data, tmp_path, dask_client):
    names = sorted(p.name for p in shared_data.glob("ign_tile_*.laz"))
    out = tmp_path / "ign"
    summary = run(
        shared_data, names, out, dask_client, "grid.resolution_m=0.5", "grid.cell_size_m=50", "grid.align=center"
    )
    assert summary.tiles == 6 and summary.points_read == 405_937
    for tif in (out / "dsm").glob("*.tif"):
        check_cog(tif, 2154)
    assert {"tiles", "cells"} <= set(list_layers(out / "holes.gpkg"))
    assert len(read_layer(out / "holes.gpkg", "tiles")) == 6
    reference_path = shared_data / "reference" / "ign_ldm__DSM__test_data_77055_627760_LA93_IGN69_50CM.tif"
    with rasterio.open(reference_path) as ref, rasterio.open(out / "dsm.vrt") as ours:
        reference = ref.read(1, masked=True)
        # IGN puts pixel centres on the lattice, and so does grid.align = "center": pixel for pixel
        window = ours.window(*ref.bounds)
        assert (window.col_off, window.row_off) == (round(window.col_off), round(window.row_off))
        assert (window.width, window.height) == (100, 100)
        mine = ours.read(1, window=window, masked=True)
    both = ~reference.mask & ~mine.mask
    assert both.sum() > 0.95 * reference.size
    assert np.median(np.abs(mine.data[both] - reference.data[both])) < 0.3


def test_tiles_with_seams_and_a_feet_survey(shared_data, tmp_path, dask_client):
    out = tmp_path / "bcts"
    names = [f"lasr_bcts_{i}.laz" for i in range(1, 5)]
    summary = run(shared_data, names, out, dask_client, "grid.cell_size_m=100")
    assert summary.points_read == 531_662 + 823_945 + 887_254 + 591_489
    with rasterio.open(out / "dsm.vrt") as ds:
        dsm = ds.read(1, masked=True)
        assert ds.crs.to_epsg() == 3005
    # no seam: the rows either side of each tile boundary are as full as the rest
    filled_rows = (~dsm.mask).mean(axis=1)
    assert np.percentile(filled_rows[5:-5], 1) > 0.8
    # autzen is in international feet with an ESRI WKT: 1 m pixels are 3.28 ft
    out = tmp_path / "autzen"
    run(shared_data, ["autzen_trim.laz"], out, dask_client, "grid.resolution_m=2")
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["grid"]["resolution"] == pytest.approx(2 / 0.3048)
    check_cog(next((out / "dsm").glob("*.tif")))


def test_crs_overrides_on_real_files(shared_data, tmp_path, dask_client):
    with pytest.raises(CRSError, match="ahn3_delft_1.laz"):
        scan_survey([str(shared_data / "ahn3_delft_1.laz")])
    run(shared_data, ["ahn3_delft_1.laz"], tmp_path / "ahn", dask_client, 'survey.crs="EPSG:28992"')
    check_cog(next((tmp_path / "ahn" / "dsm").glob("*.tif")), 28992)
    with pytest.raises(CRSError, match="pdal_warsaw_small.las: its CRS record cannot be parsed"):
        scan_survey([str(shared_data / "pdal_warsaw_small.las")])
    run(
        shared_data,
        ["pdal_warsaw_small.las"],
        tmp_path / "warsaw",
        dask_client,
        'survey.crs="EPSG:2180"',
        "grid.cell_size_m=50",
    )
    with pytest.raises(CRSError, match="differs"):
        scan_survey([str(shared_data / n) for n in ("ign_tile_77050_627755.laz", "lidr_megaplot.laz")])


def test_reprojection_while_streaming(shared_data, tmp_path, dask_client):
    out = tmp_path / "utm"
    summary = run(shared_data, ["lasr_bcts_1.laz"], out, dask_client, 'survey.target_crs="EPSG:26909"')
    assert summary.points_used == summary.points_read
    with rasterio.open(out / "dsm.vrt") as ds:
        assert ds.crs.to_epsg() == 26909
        dsm = ds.read(1, masked=True)
    assert (~dsm.mask).sum() > 30_000  # bcts_1 covers about 45,000 m2


def test_dtm_keeps_only_ground(shared_data, tmp_path, dask_client):
    out = tmp_path / "dtm"
    summary = run(shared_data, ["ign_bat.laz"], out, dask_client, "filter.keep_classes=[2]", "grid.cell_size_m=50")
    assert summary.points_used == 33_888  # class 2 count in PROVENANCE.md


@pytest.mark.parametrize(
    "name, crs",
    [
        ("ahn3_delft_1.laz", "EPSG:28992"),
        ("lidr_topography.laz", None),
        ("ign_corse_water.laz", None),
        ("ign_bridge_0299_6802.laz", None),  # river_rim: the ring plane's slopes along and across the hole
    ],
)
def test_real_holes_and_causes_do_not_depend_on_cell_size(shared_data, tmp_path, dask_client, name, crs):
    """The same holes (area, place) with the same causes, with cells of 50 m, 250 m and 1000 m."""
    found = {}
    for cell_m in (50, 250, 1000):
        overrides = [f"grid.cell_size_m={cell_m}"] + ([f"survey.crs={crs}"] if crs else [])
        out = tmp_path / f"out{cell_m}"
        run(shared_data, [name], out, dask_client, *overrides)
        holes = read_layer(out / "holes.gpkg", "holes")
        found[cell_m] = sorted(
            (round(area, 2), cause, round(g.centroid.x, 1), round(g.centroid.y, 1))
            for area, cause, g in zip(holes["area_m2"], holes["cause"], holes.geometry)
        )
    assert found[50], name
    assert found[50] == found[250] == found[1000]


def test_decimated_river_reach_is_water_by_its_sloped_rim(shared_data, tmp_path, dask_client):
    """IGN's decimated Brittany tile: no water class, no flight lines; the open reach's rim is a gentle plane."""
    out = tmp_path / "bridge"
    run(shared_data, ["ign_bridge_0299_6802.laz"], out, dask_client)
    holes = read_layer(out / "holes.gpkg", "holes")
    water = holes[holes["cause"] == "water"]
    assert list(water["cause_rule"]) == ["river_rim"]
    reach = water.geometry.iloc[0]
    assert 299_700 < reach.centroid.x < 299_800 and 6_801_720 < reach.centroid.y < 6_801_780
    # the reaches under trees: seen by the lines (no_return) or not judged (unknown), no evidence of water
    assert set(holes["cause"]) <= {"water", "no_return", "unknown"}
