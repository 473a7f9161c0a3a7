"""report.html: the PNG encoder, the shaded relief, the maps, bounded inputs, a browser screenshot."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import warnings
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from rasterio.io import MemoryFile

from pipeline.io.raster import write_cog, write_vrt
from pipeline.report import (
    MapHole,
    MapRaster,
    ReportInputs,
    encode_png,
    prepare_maps,
    read_report_inputs,
    render_report,
    shaded_relief,
    with_route,
    write_report,
)

CRS_WKT = rasterio.crs.CRS.from_epsg(32631).to_wkt()


def decode_png(data: bytes) -> np.ndarray:
    """(bands, rows, cols) through GDAL's PNG driver: an independent decoder."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with MemoryFile(data) as memory, memory.open() as dataset:
            assert dataset.driver == "PNG"
            return dataset.read()


@pytest.mark.parametrize("channels", [None, 2, 3, 4])
def test_png_round_trips_through_gdal(rng, channels):
    shape = (37, 53) if channels is None else (37, 53, channels)
    pixels = rng.integers(0, 256, size=shape, dtype=np.uint8)
    decoded = decode_png(encode_png(pixels))
    expected = pixels[None] if channels is None else np.moveaxis(pixels, -1, 0)
    np.testing.assert_array_equal(decoded, expected)


def test_png_refuses_what_it_cannot_encode():
    with pytest.raises(ValueError, match="uint8"):
        encode_png(np.zeros((4, 4), np.float32))
    with pytest.raises(ValueError, match="shape"):
        encode_png(np.zeros((4, 4, 5), np.uint8))


def test_shaded_relief_lights_slopes_facing_the_light_and_hides_no_data():
    rows, cols = np.indices((40, 40), dtype=np.float32)
    northwest_facing = (rows + cols).astype(np.float32)  # rises to the south-east
    southeast_facing = -northwest_facing
    hollow = northwest_facing.copy()
    hollow[10:20, 10:20] = np.nan
    bright = shaded_relief(northwest_facing, pixel_size=(1, 1), height_range=(-80, 80))
    dark = shaded_relief(southeast_facing, pixel_size=(1, 1), height_range=(-80, 80))
    # same colour ramp position at the centre; only the light differs
    assert bright[20, 20, :3].astype(int).sum() > dark[20, 20, :3].astype(int).sum()
    image = shaded_relief(hollow, pixel_size=(1, 1))
    assert image.shape == (40, 40, 4) and image.dtype == np.uint8
    assert (image[10:20, 10:20, 3] == 0).all() and (image[:10, :, 3] == 255).all()
    assert shaded_relief(np.full((3, 3), np.nan), pixel_size=(1, 1))[..., 3].max() == 0


def manifest() -> dict:
    return {
        "complete": True,
        "holefill_version": "0.1.0",
        "created": "2026-01-01T00:00:00+0000",
        "host": "test",
        "crs": {"name": "WGS 84 / UTM zone 31N", "wkt": CRS_WKT},
        "grid": {"resolution": 1.0, "resolution_unit_m": 1.0, "width": 200, "height": 100},
        "skipped": [{"path": "bad.laz", "reason": "not a LAS file"}],
        "outputs": {"dsm_vrt": "dsm.vrt"},
        "summary": {
            "tiles": 3,
            "cells": 2,
            "points_read": 1_234_567,
            "points_used": 1_200_000,
            "seconds": 12.5,
            "points_per_second": 98_765,
            "stage_seconds": {"scan": 0.2, "rasterize": 8.0, "holes": 3.0},
            "empty_pixels": 900,
            "resumed_tasks": 0,
        },
        "holes": {
            "listed": 2,
            "area_m2": 900.0,
            "by_cause": {"occlusion": 1, "water": 0, "missed_coverage": 1, "unknown": 0},
            "parts_by_type": {"IIB": 1, "closed": 1},
            "small_voids": 4,
            "small_void_area_m2": 6.0,
            "min_area_m2": 4.0,
            "vertical_hole_groups": 1,
            "walls": 2,
            "height_jump_px": 50,
            "aoi_area_m2": 20_000.0,
            "fill": {
                "holes_by_status": {"filled": 1, "skipped: too large": 1},
                "holes_by_method": {"tin": 1},
                "filled_area_m2": 100.0,
                "skipped_area_m2": 800.0,
            },
        },
        "flightplan": {
            "holes": 2,
            "holes_planned": 1,
            "holes_not_planned": {"1": "cause 'occlusion' is not re-flown"},
            "patterns": 1,
            "lanes": 3,
            "sorties": 1,
            "flown_route_m": 900.0,
            "greedy_route_m": 950.0,
            "sortie_durations_s": [300.0],
            "altitude_reference": "takeoff",
        },
    }


def largest() -> list[dict]:
    common = dict(n_cells=1, max_layer=1, boundary_jump_px=3, boundary_px=40, cause_rule="strip")
    return [
        dict(hole_id=2, area_m2=800.0, cause="missed_coverage", fill_status="skipped: too large", **common),
        dict(hole_id=1, area_m2=100.0, cause="occlusion", fill_status="filled", fill_method="tin", **common),
    ]


def square(x0: float, y0: float, size: float) -> np.ndarray:
    return np.array([[x0, y0], [x0 + size, y0], [x0 + size, y0 + size], [x0, y0 + size], [x0, y0]])


def inputs() -> ReportInputs:
    """A 200 m x 100 m survey: a slope with a filled occlusion and an empty missed strip."""
    rows, cols = np.indices((100, 200))
    dsm = (50 + 0.1 * cols + 3 * np.sin(rows / 7)).astype(np.float32)
    dsm[20:60, 100:120] = np.nan  # the strip, left without data
    filled = np.zeros(dsm.shape, bool)
    filled[70:80, 30:40] = True
    overview = MapRaster(dsm=dsm, bounds=(500_000.0, 5_000_000.0, 500_200.0, 5_000_100.0), filled=filled)
    holes = (
        MapHole(2, "missed_coverage", 800.0, "skipped: too large", cause_rule="strip",
                bounds=(500_100.0, 5_000_040.0, 500_120.0, 5_000_080.0), label_xy=(500_110.0, 5_000_060.0),
                rings=(np.array([[500_100, 5_000_040], [500_120, 5_000_040], [500_120, 5_000_080],
                                 [500_100, 5_000_080], [500_100, 5_000_040]], float),)),
        MapHole(1, "occlusion", 100.0, "filled", "tin", cause_rule="shadow", fill_error_m=0.2,
                bounds=(500_030.0, 5_000_020.0, 500_040.0, 5_000_030.0), label_xy=(500_035.0, 5_000_025.0),
                rings=(square(500_030.0, 5_000_020.0, 10.0),)),
    )  # fmt: skip
    zoom = MapRaster(dsm=dsm[10:70, 80:140], bounds=(500_080.0, 5_000_030.0, 500_140.0, 5_000_090.0))
    route = (np.array([[500_110.0, 4_999_990.0], [500_110.0, 5_000_110.0], [500_130.0, 5_000_110.0]]),)
    return ReportInputs(
        overview=overview,
        holes=holes,
        zooms=((2, zoom),),
        route=route,
        survey_area=(square(500_000.0, 5_000_000.0, 100.0),),
        part_area_by_type={"IIB": 800.0, "closed": 100.0},
    )


def test_report_without_maps_keeps_the_tables():
    page = render_report(manifest(), largest())
    assert "<svg" not in page
    for text in ("By cause", "1,234,567", "bad.laz", "Re-flight plan", "skipped: too large", "Time by stage"):
        assert text in page


def test_report_with_maps_is_one_self_contained_page(tmp_path):
    path = write_report(tmp_path / "report.html", manifest(), largest(), inputs=inputs())
    page = path.read_text(encoding="utf-8")
    assert page.count("<svg class='map'") == 2  # the overview and one zoom
    # nothing fetched: every href/src is a data URI or a fragment, no script
    links = re.findall(r"(?:href|src)='([^']*)'", page)
    assert links and all(link.startswith(("data:image/png;base64,", "url(#", "#")) for link in links)
    assert "<script" not in page and "http://" not in page.replace("http://www.w3.org/2000/svg", "")
    # holes by cause with their areas, their tooltips, the route, the warnings
    assert "hole 2: missed coverage (strip), 800 m², skipped: too large" in page
    assert "re-flight route" in page and "take-off" in page
    assert "4.00%" in page  # missed coverage: 800 of 20,000 m²
    assert "Look at first" in page and "1 input tiles were skipped" in page
    assert "left without data in the DSM" in page
    # the images decode
    for uri in re.findall(r"data:image/png;base64,([A-Za-z0-9+/=]+)", page):
        import base64

        assert decode_png(base64.b64decode(uri)).size > 0


def test_report_grows_the_overview_to_hold_the_route():
    page = render_report(manifest(), largest(), inputs=inputs())
    view_box = re.search(r"viewBox='([-\d. ]+)'", page).group(1)
    x0, y0, w, h = map(float, view_box.split())
    assert y0 < -9 and y0 + h > 109  # the route leaves the 100 px grid by 10 m on both sides


def write_dsm(folder: Path, width: int, height: int, *, resolution: float = 1.0) -> None:
    """A DSM of two COG tiles and their VRT, like a run writes (with overviews)."""
    (folder / "dsm").mkdir(parents=True)
    rows, cols = np.indices((height, width))
    dsm = (100 + 20 * np.sin(cols / 150) * np.cos(rows / 90)).astype(np.float32)
    dsm[height // 3 : height // 2, width // 4 : width // 3] = np.nan
    half = width // 2
    sources = []
    for i, (c0, c1) in enumerate(((0, half), (half, width))):
        transform = Affine(resolution, 0, 500_000 + c0 * resolution, 0, -resolution, 5_000_000)
        tile = folder / "dsm" / f"dsm_{i}.tif"
        write_cog(tile, dsm[:, c0:c1], transform=transform, crs_wkt=CRS_WKT)
        sources.append((tile, 0, c0, height, c1 - c0))
    write_vrt(
        folder / "dsm.vrt",
        sources,
        width=width,
        height=height,
        transform=Affine(resolution, 0, 500_000, 0, -resolution, 5_000_000),
        crs_wkt=CRS_WKT,
    )


def test_report_inputs_are_bounded_whatever_the_survey_size(tmp_path):
    write_dsm(tmp_path, 6000, 2400)
    got = read_report_inputs(tmp_path, max_px=800)
    # 6000 pixels at most 800: reduced 8 times (an overview level's factor, not 7.5)
    assert got is not None and got.overview.dsm.shape == (300, 750)
    assert got.overview.bounds == pytest.approx((500_000.0, 4_997_600.0, 506_000.0, 5_000_000.0))
    assert np.isnan(got.overview.dsm).any() and np.isfinite(got.overview.dsm).mean() > 0.9
    assert got.holes == () and got.route == () and got.zooms == ()
    page = render_report(manifest(), largest(), inputs=got)
    assert len(page) < 1_500_000
    assert read_report_inputs(tmp_path / "nothing-here") is None


def find_browser() -> str | None:
    return next(
        (b for b in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable") if shutil.which(b)),
        None,
    )


def test_report_screenshot_in_a_headless_browser(tmp_path):
    browser = find_browser()
    if browser is None:
        pytest.skip("no headless browser (Debian: apt-get install chromium)")
    path = write_report(tmp_path / "report.html", manifest(), largest(), inputs=inputs())
    shot = tmp_path / "shot.png"
    subprocess.run(
        [browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", f"--screenshot={shot}",
         "--window-size=1200,1600", path.resolve().as_uri()],
        capture_output=True, timeout=120, check=False,
    )  # fmt: skip
    assert shot.exists(), "the browser wrote no screenshot"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(shot) as dataset:
            rgb = dataset.read()[:3].astype(int)
    # the map was drawn: the missed-coverage colour (#d55e00) and the green of the relief are on the page
    colours = rgb.reshape(3, -1).T
    stroke = np.abs(colours - [0xD5, 0x5E, 0x00]).sum(axis=1) < 40
    green = (colours[:, 1] > colours[:, 0] + 30) & (colours[:, 1] > colours[:, 2] + 30)
    assert stroke.sum() > 50 and green.sum() > 5000


@pytest.mark.slow
def test_report_inputs_from_a_real_run(tmp_path, dask_client):
    from pipeline.config import load_config
    from pipeline.run import run_survey
    from pipeline.synth import generate_survey, preset, write_truth

    survey = generate_survey(tmp_path / "tiles", preset("demo", width_m=300.0, height_m=200.0, seed=6))
    truth = write_truth(survey, tmp_path)
    out = tmp_path / "out"
    run_survey([str(tmp_path / "tiles")], out, load_config(), client=dask_client, aoi=truth["survey_area"])
    got = read_report_inputs(out)
    manifest = json.loads((out / "manifest.json").read_text())
    assert got is not None
    assert got.overview.dsm.shape == (manifest["grid"]["height"], manifest["grid"]["width"])
    assert got.overview.filled is not None and got.overview.filled.any()
    assert got.survey_area and got.holes and got.part_area_by_type
    assert sum(h.area_m2 for h in got.holes) == pytest.approx(
        sum(got.part_area_by_type.values()), rel=1e-6
    )  # the parts tile the holes
    assert 0 < len(got.zooms) <= 4
    page = render_report(manifest, manifest["holes"]["largest"], inputs=got)
    assert "<svg class='map'" in page
    # the run drew its maps while it planned the flights and added the route after: the same page
    assert got.route, "the demo's missed strip has a re-flight route"
    prepared = prepare_maps(out)
    assert prepared is not None and prepared.route == ()
    assert render_report(manifest, manifest["holes"]["largest"], inputs=with_route(prepared, out)) == page
    assert (out / "report.html").read_text(encoding="utf-8") == page


@pytest.mark.slow
def test_a_run_without_holes_keeps_its_map(tmp_path, rng, dask_client):
    """An empty holes layer (no hole listed) must not cost the report its map."""
    from pipeline.config import load_config
    from pipeline.run import run_survey

    from .lasfiles import write_points

    n = 40_000
    x, y = rng.uniform(1000, 1060, n).round(2), rng.uniform(2000, 2060, n).round(2)
    path = write_points(tmp_path / "dense.laz", x, y, (50 + rng.uniform(0, 1, n)).round(2))
    out = tmp_path / "out"
    run_survey([str(path)], out, load_config(overrides=["grid.resolution_m=1"]), client=dask_client)
    assert json.loads((out / "manifest.json").read_text())["holes"]["listed"] == 0
    got = read_report_inputs(out)
    assert got is not None and got.holes == ()
    assert "<svg class='map'" in (out / "report.html").read_text()


def test_points_not_used_are_named_first():
    """Points outside their header bounds (a reprojected or PDAL read) are the first thing to look at."""
    record = manifest()
    record["summary"]["points_outside"] = 63_226
    page = render_report(record, largest())
    assert "Look at first" in page and "63,226 points lie outside" in page
    assert "points used" in page


def test_products_and_fill_counts_say_what_the_run_wrote():
    """The Products line lists the files the run wrote (no drone files where none were written); the
    fill table tells the listed holes from every void the stage filled (small ones included)."""
    page = render_report(manifest(), largest(), inputs=inputs())
    products = page.split("<h2>Products</h2>", 1)[1]
    assert "manifest.json" in products and ".plan" not in products and "drone" not in products
    written = manifest()
    written["outputs"] = {
        "files": [
            {"path": p}
            for p in ("dsm/a.tif", "dsm/b.tif", "holes.gpkg", "flightplan.gpkg", "flightplan.plan", "flightplan.kmz")
        ]
    }
    products = render_report(written, largest()).split("<h2>Products</h2>", 1)[1]
    assert "dsm/*.tif, holes.gpkg, flightplan.gpkg, flightplan.plan, flightplan.kmz, manifest.json" in products
    table = page.split("Holes by fill status", 1)[1].split("</table>", 1)[0]
    assert "listed holes" in table and "all voids (small ones included)" in table
    # one listed hole of each status in largest()/inputs(), the stage's own counts beside them
    assert re.search(r"<td>filled</td><td>1</td><td>100</td><td>1</td>", table), table


def test_the_flight_section_gives_clearance_take_off_and_the_ground_seen():
    """A pilot reads the least clearance of each sortie, where the drone takes off and from what height."""
    plan = manifest()
    plan["flightplan"].update(
        sortie_min_clearance_m=[67.8],
        home=[500197.5, 5000183.5],
        home_ground_m=50.63,
        home_height_from="ground points",
        home_warning="",
        hole_visible_share={"3": 0.97, "26": 1.0},
    )
    page = render_report(plan, largest())
    section = page.split("<h2>Re-flight plan</h2>", 1)[1].split("</table>", 1)[0]
    assert "<td>least clearance per sortie (m)</td><td>67.8</td>" in section
    assert "(500,197.5, 5,000,183.5), ground 50.63 (from ground points)" in section
    assert "least 97% (hole 3), median 100%, over 2 planned holes" in section
