"""COG tiles: full resolution as given, overviews built once in memory (average, or nearest for codes)."""

from __future__ import annotations

import numpy as np
import rasterio
from affine import Affine
from rasterio.crs import CRS

from pipeline.io.raster import read_view, write_cog


def _write(tmp_path, array, **kwargs):
    path = tmp_path / "t.tif"
    write_cog(path, array, transform=Affine(1, 0, 0, 0, -1, 200), crs_wkt=CRS.from_epsg(28992).to_wkt(), **kwargs)
    return path


def test_heights_and_their_averaged_overviews(tmp_path, rng):
    heights = rng.normal(10, 3, (200, 136)).astype(np.float32)
    heights[rng.random(heights.shape) < 0.1] = np.nan
    path = _write(tmp_path, heights)
    with rasterio.open(path) as ds:
        assert ds.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
        assert ds.overviews(1) == [2, 4]
        full = ds.read(1, masked=True)
        assert np.array_equal(full.filled(np.nan), heights, equal_nan=True)
    with rasterio.open(path, overview_level=0) as half:
        assert half.shape == (100, 68)
        coarse = half.read(1, masked=True)
    blocks = heights.reshape(100, 2, 68, 2)
    with np.errstate(invalid="ignore"):
        expected = np.nanmean(blocks, axis=(1, 3))  # nodata left out of the average
    assert np.array_equal(coarse.mask, np.isnan(expected))
    assert np.allclose(coarse.filled(np.nan), expected, atol=1e-5, equal_nan=True)


def test_a_map_larger_than_its_limit_is_read_from_an_overview_level(tmp_path, rng):
    """200 x 136 pixels for at most 150: reduced 2 times (not 1.33), which is the first overview's
    pixels as written, not GDAL's average of the full pixels."""
    heights = rng.normal(10, 3, (200, 136)).astype(np.float32)
    heights[rng.random(heights.shape) < 0.1] = np.nan
    path = _write(tmp_path, heights)
    view, bounds = read_view(path, None, 150)
    with rasterio.open(path, overview_level=0) as half:
        overview = half.read(1, masked=True).filled(np.nan)
    assert view.shape == (100, 68)
    assert np.array_equal(view, overview, equal_nan=True)
    assert bounds == (0.0, 0.0, 136.0, 200.0)
    small, _ = read_view(path, None, 400)  # within the limit: every pixel
    assert np.array_equal(small, heights, equal_nan=True)


def test_codes_keep_codes_in_their_overviews(tmp_path, rng):
    codes = rng.choice(np.array([0, 4, 7, 255], np.uint8), size=(256, 256))
    path = _write(tmp_path, codes, nodata=255, categorical=True)
    for level in (0, 1):
        with rasterio.open(path, overview_level=level) as ds:
            assert set(np.unique(ds.read(1))) <= {0, 4, 7, 255}  # an average of 0 and 4 would make a 2


def test_one_burn_of_summed_bits_gives_each_geometry_s_mask(rng):
    """burn_sum with a bit per geometry: bit k holds exactly geometry_mask of geometry k, however
    the geometries overlap (strips at random headings, a multipolygon, one cut to nothing)."""
    import shapely
    from shapely import affinity

    from pipeline.io.raster import burn_sum, geometry_mask

    transform = Affine(0.5, 0, 100.0, 0, -0.5, 260.0)
    shape = (137, 181)
    geometries = []
    for _ in range(20):
        strip = shapely.box(-200, -rng.uniform(3, 25), 200, rng.uniform(3, 25))
        strip = affinity.rotate(strip, rng.uniform(0, 180), origin=(0, 0))
        geometries.append(affinity.translate(strip, rng.uniform(110, 180), rng.uniform(200, 250)))
    geometries.append(shapely.MultiPolygon([shapely.box(100, 200, 130, 230), shapely.box(130, 200, 150, 215)]))
    geometries.append(shapely.box(0, 0, 1, 1))  # outside the window
    burnt = burn_sum([(g, 1 << k) for k, g in enumerate(geometries)], transform, shape)
    for k, geometry in enumerate(geometries):
        assert np.array_equal((burnt >> k) & 1 == 1, geometry_mask(geometry, transform, shape)), k
    assert burn_sum([], transform, shape).shape == shape


def test_a_mosaic_is_written_in_utf8_whatever_the_locale(tmp_path):
    """A WKT2 holds '°' (pyproj's UTM zones): a process whose locale encodes ASCII only (a batch
    job under LC_ALL=C without Python's UTF-8 mode) wrote no dsm.vrt at all (UnicodeEncodeError)."""
    import os
    import subprocess
    import sys

    vrt = tmp_path / "dsm.vrt"
    script = (
        "import sys, locale\n"
        "from affine import Affine\n"
        "from pyproj import CRS\n"
        "from pipeline.io.raster import write_vrt\n"
        "assert locale.getpreferredencoding(False).lower() not in ('utf-8', 'utf8'), locale.getpreferredencoding(False)\n"
        "write_vrt(sys.argv[1], [], width=4, height=3, transform=Affine(1, 0, 500000, 0, -1, 5000003),"
        " crs_wkt=CRS.from_epsg(32631).to_wkt())\n"
    )
    env = {**os.environ, "LC_ALL": "C", "PYTHONCOERCECLOCALE": "0", "PYTHONUTF8": "0"}
    subprocess.run([sys.executable, "-c", script, str(vrt)], check=True, env=env, timeout=120)
    assert "°" in vrt.read_text(encoding="utf-8")
    with rasterio.open(vrt) as dataset:
        assert dataset.crs.to_epsg() == 32631
