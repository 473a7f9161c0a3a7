"""COG tiles: full resolution as given, overviews built once in memory (average, or nearest for codes)."""

from __future__ import annotations

import numpy as np
import rasterio
from affine import Affine
from rasterio.crs import CRS

from pipeline.io.raster import write_cog


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


def test_codes_keep_codes_in_their_overviews(tmp_path, rng):
    codes = rng.choice(np.array([0, 4, 7, 255], np.uint8), size=(256, 256))
    path = _write(tmp_path, codes, nodata=255, categorical=True)
    for level in (0, 1):
        with rasterio.open(path, overview_level=level) as ds:
            assert set(np.unique(ds.read(1))) <= {0, 4, 7, 255}  # an average of 0 and 4 would make a 2
