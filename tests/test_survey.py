"""Scanning inputs: formats, CRS handling and every kind of bad input."""

from __future__ import annotations

import struct

import laspy
import numpy as np
import pytest
from pyproj import CRS

from pipeline.errors import CRSError, InputDataError
from pipeline.io import las
from pipeline.io.las import decode_only, header_bounds, iter_point_chunks, read_header
from pipeline.survey.scan import find_inputs, scan_survey

from .lasfiles import random_points, write_points


@pytest.fixture
def points(rng):
    return random_points(rng, 3000)


@pytest.mark.parametrize("version", ["1.2", "1.4"])
@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_headers_of_las_and_laz_12_and_14(tmp_path, points, version, suffix):
    path = write_points(tmp_path / f"t{suffix}", *points, version=version)
    header = read_header(path)
    assert header.format == ("LAZ" if suffix == ".laz" else "LAS")
    assert header.version == version
    assert header.point_format == (6 if version == "1.4" else 1)
    assert header.point_count == len(points[0])
    assert CRS.from_wkt(header.crs_wkt).to_epsg() == 2154
    assert decode_only(path, 1000) == len(points[0])
    assert header_bounds(path) == header.bounds  # the bytes alone, for the flight plan's ground points


def test_inputs_from_files_folders_and_globs(tmp_path, points):
    (tmp_path / "a").mkdir()
    for name in ("a/one.laz", "a/two.las", "three.laz"):
        write_points(tmp_path / name, *points)
    (tmp_path / "a" / "notes.txt").write_text("not a point cloud")
    assert len(find_inputs([str(tmp_path / "a")])) == 2
    assert len(find_inputs([str(tmp_path / "*.laz")])) == 1
    assert len(find_inputs([str(tmp_path / "**" / "*.la[sz]")])) == 3
    # the same file named twice is read once
    assert len(find_inputs([str(tmp_path / "three.laz"), str(tmp_path / "three.laz")])) == 1


def test_missing_crs_needs_crs_option(tmp_path, points):
    path = write_points(tmp_path / "nocrs.laz", *points, crs=None)
    with pytest.raises(CRSError, match=r"nocrs\.laz: it has no CRS.*--crs"):
        scan_survey([str(path)])
    survey = scan_survey([str(path)], crs="EPSG:28992")
    assert survey.crs.to_epsg() == 28992 and not survey.reproject


def test_mixed_crs_needs_target_crs(tmp_path, points):
    x, y, z = points
    a = write_points(tmp_path / "a.laz", x, y, z, crs="EPSG:2154")
    # the same place in UTM 31N
    b = write_points(tmp_path / "b.laz", x - 300_000, y + 5_000_000, z, crs="EPSG:32631")
    with pytest.raises(CRSError, match=r"b\.laz: CRS 'WGS 84 / UTM zone 31N' differs.*--target-crs"):
        scan_survey([str(a), str(b)])
    survey = scan_survey([str(a), str(b)], target_crs="EPSG:2154")
    assert survey.reproject
    assert survey.tiles[0].bounds == read_header(a).bounds
    assert survey.tiles[1].bounds != read_header(b).bounds


def test_geographic_crs_is_refused(tmp_path, points):
    path = write_points(tmp_path / "geo.laz", *points, crs="EPSG:2154")
    with pytest.raises(CRSError, match="not projected"):
        scan_survey([str(path)], target_crs="EPSG:4326")


def test_feet_survey_reports_its_units(tmp_path, points):
    path = write_points(tmp_path / "ft.laz", *points, crs="EPSG:6880")
    survey = scan_survey([str(path)])
    assert survey.horizontal_unit_m == pytest.approx(0.3048006096)


# -- bad input -----------------------------------------------------------------------------


def test_not_a_las_file(tmp_path):
    path = tmp_path / "fake.laz"
    path.write_bytes(b"PK\x03\x04 this is a zip file")
    with pytest.raises(InputDataError, match=r"fake\.laz: not a LAS/LAZ file"):
        scan_survey([str(path)])
    with pytest.raises(InputDataError, match=r"fake\.laz: not a LAS/LAZ file"):
        header_bounds(path)


def test_truncated_laz_fails_on_decoding(tmp_path, rng):
    path = write_points(tmp_path / "cut.laz", *random_points(rng, 50_000))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    read_header(path)  # the header alone is intact
    with pytest.raises(InputDataError, match=r"cut\.laz: point data cannot be decoded.*truncated"):
        decode_only(path, 10_000)


def test_decoding_on_every_core_gives_the_same_points_and_the_same_errors(tmp_path, rng):
    """``parallel`` (the flight planner's ground) decodes the LAZ chunks on lazrs's threads: same points, same checks."""
    x, y, z = random_points(rng, 180_000)  # four LAZ chunks of 50,000 points
    classes = rng.choice(np.array([1, 2, 6, 9], np.uint8), len(x))
    path = write_points(tmp_path / "t.laz", x, y, z, classification=classes, withheld=rng.random(len(x)) < 0.01)

    def decoded(parallel):
        chunks = list(iter_point_chunks(path, 70_000, parallel=parallel))
        return [np.concatenate([getattr(c, f) for c in chunks]) for f in ("X", "Y", "Z", "classification", "withheld")]

    assert las._laz_backend(parallel=True) is laspy.LazBackend.LazrsParallel
    serial, parallel = decoded(False), decoded(True)
    assert len(serial[0]) == len(x)
    for a, b in zip(serial, parallel, strict=True):
        np.testing.assert_array_equal(a, b)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputDataError, match=r"t\.laz: point data cannot be decoded.*truncated"):
        decoded(True)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_header_point_count_that_lies(tmp_path, points, suffix):
    path = write_points(tmp_path / f"lie{suffix}", *points, version="1.2")
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, 107, len(points[0]) + 100)  # legacy point count
    path.write_bytes(bytes(data))
    with pytest.raises(
        InputDataError, match=rf"lie\{suffix}: .*header point count is|lie\{suffix}: point data cannot be decoded"
    ):
        read_header(path)
        decode_only(path, 1000)


def test_zero_point_tile(tmp_path):
    path = write_points(tmp_path / "empty.laz", np.zeros(0), np.zeros(0), np.zeros(0))
    with pytest.raises(InputDataError, match=r"empty\.laz: tile has zero points"):
        scan_survey([str(path)])


def test_empty_and_unmatched_inputs(tmp_path):
    with pytest.raises(InputDataError, match="no input files"):
        find_inputs([])
    with pytest.raises(InputDataError, match="pattern matches no file"):
        find_inputs([str(tmp_path / "*.laz")])
    with pytest.raises(InputDataError, match="folder holds no .las or .laz"):
        find_inputs([str(tmp_path)])
    with pytest.raises(InputDataError, match="no such file"):
        find_inputs([str(tmp_path / "missing.laz")])


def test_skip_policy_lists_bad_tiles(tmp_path, points):
    good = write_points(tmp_path / "good.laz", *points)
    bad = tmp_path / "bad.laz"
    bad.write_text("garbage")
    survey = scan_survey([str(good), str(bad)], on_error="skip")
    assert [t.name for t in survey.tiles] == ["good.laz"]
    assert survey.skipped[0]["path"].endswith("bad.laz") and "not a LAS" in survey.skipped[0]["reason"]
