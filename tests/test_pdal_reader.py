"""The PDAL reader (optional): same statistics as laspy, the user's stages, the checks at the edge.

Tests that need python-pdal skip cleanly when it does not import; the install hint is
tested only when it does not.
"""

from __future__ import annotations

import json
from pathlib import Path

import laspy
import numpy as np
import pytest
from click.testing import CliRunner

from pipeline.cli import main
from pipeline.config import load_config
from pipeline.errors import ConfigError
from pipeline.io.intermediate import load_tile_shared_keys, load_tile_statistics
from pipeline.io.pdal_reader import PdalRead, iter_pdal_chunks, load_user_pipeline
from pipeline.plan import plan_survey
from pipeline.stages.bin_tiles import rasterize_tile, tile_tasks
from pipeline.staging import Staging
from pipeline.survey.scan import scan_survey

from .lasfiles import random_points, write_points

STATISTICS = ("zmax", "zmin", "count", "voxels", "water", "source")


def _pdal_imports() -> bool:
    try:
        import pdal  # noqa: F401
    except ImportError:
        return False
    return True


@pytest.fixture(scope="module")
def pdal():
    return pytest.importorskip("pdal")


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> list[str]:
    """Two LAZ tiles (LAS 1.4 format 6, LAS 1.2 format 1) with noise, water, buildings and withheld points."""
    folder = tmp_path_factory.mktemp("synthetic")
    rng = np.random.default_rng(11)
    paths = []
    for i, (version, bounds) in enumerate([("1.4", (1000, 2000, 1060, 2080)), ("1.2", (1050, 2000, 1100, 2080))]):
        x, y, z = random_points(rng, 30_000, bounds)
        classification = rng.choice(np.array([1, 2, 6, 7, 9], np.uint8), len(x), p=[0.4, 0.3, 0.2, 0.05, 0.05])
        withheld = rng.random(len(x)) < 0.02
        path = write_points(
            folder / f"tile_{i}.laz", x, y, z, classification=classification, withheld=withheld, version=version
        )
        paths.append(str(path))
    return paths


def bin_survey(inputs: list[str], tmp_path: Path, *overrides: str, crs: str = "", target_crs: str = "") -> dict:
    """Stage 1 on every tile, in this process: each tile's statistics, shared voxel keys and points read."""
    config = load_config(overrides=["grid.resolution_m=1.0", "rasterize.chunk_points=10000", *overrides])
    survey = scan_survey(inputs, crs=crs, target_crs=target_crs)
    plan = plan_survey(survey, config)
    out = tmp_path / f"bin_{len(list(tmp_path.iterdir()))}"
    staging = Staging.create(out, run_key="test")
    binned = {}
    for task in tile_tasks(plan, config, staging):
        result = rasterize_tile(task)
        stats = load_tile_statistics(task.output_dir, task.window, task.window)
        binned[Path(task.path).name] = {
            **{name: getattr(stats, name) for name in STATISTICS},
            "shared_keys": load_tile_shared_keys(task.output_dir),
            "points_read": result.points_read,
            "window": task.window,
            # the window's first column and top row on the absolute lattice
            "corner": (task.grid.col_min + task.window.col_off, task.grid.row_top - task.window.row_off),
        }
    staging.remove()
    return binned


def assert_same_statistics(got: dict, expected: dict) -> None:
    assert got.keys() == expected.keys()
    for name, tile in expected.items():
        assert got[name]["window"] == tile["window"], name
        for key in (*STATISTICS, "shared_keys"):
            np.testing.assert_array_equal(got[name][key], tile[key], err_msg=f"{name} {key}")


def write_pipeline(path: Path, stages) -> str:
    path.write_text(json.dumps(stages))
    return str(path)


# -- without python-pdal ---------------------------------------------------------------


@pytest.mark.skipif(_pdal_imports(), reason="python-pdal is installed: the install hint is not shown")
def test_reader_pdal_without_pdal_says_how_to_install(tmp_path, rng):
    path = write_points(tmp_path / "t.laz", *random_points(rng, 500))
    result = CliRunner().invoke(main, ["run", str(path), "--out", str(tmp_path / "o"), "--reader", "pdal"])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1
    assert "python-pdal cannot be imported" in lines[0] and "pip install 'holefill[pdal]'" in lines[0]
    assert "conda-forge" in lines[0]
    assert not (tmp_path / "o").exists()


def test_pdal_pipeline_needs_the_pdal_reader(tmp_path):
    pipeline = write_pipeline(tmp_path / "p.json", [{"type": "filters.range", "limits": "Z[0:100]"}])
    with pytest.raises(ConfigError, match="read.pdal_pipeline .* needs read.reader = 'pdal'"):
        load_config(overrides=[f"read.pdal_pipeline={pipeline}"])


# -- with python-pdal ------------------------------------------------------------------


def test_pdal_bins_what_laspy_bins_on_a_synthetic_survey(pdal, synthetic, tmp_path):
    expected = bin_survey(synthetic, tmp_path)
    got = bin_survey(synthetic, tmp_path, "read.reader='pdal'")
    assert_same_statistics(got, expected)
    assert [t["points_read"] for t in got.values()] == [laspy.read(p).header.point_count for p in synthetic]


@pytest.mark.realdata
@pytest.mark.parametrize(
    ("name", "crs", "target_crs"),
    [
        ("ign_crop1.laz", "", ""),  # LAS 1.4 format 6
        ("autzen_trim.laz", "", ""),  # LAS 1.2 format 3, US feet, a WKT CRS
        ("ahn_amsterdam_2386_9702.laz", "EPSG:28992", ""),  # no CRS in the file: --crs
        ("ign_crop2_water.laz", "", "EPSG:32631"),  # reprojected by holefill after PDAL
    ],
)
def test_pdal_bins_what_laspy_bins_on_real_files(pdal, shared_data, tmp_path, name, crs, target_crs):
    inputs = [str(shared_data / name)]
    expected = bin_survey(inputs, tmp_path, crs=crs, target_crs=target_crs)
    got = bin_survey(inputs, tmp_path, "read.reader='pdal'", crs=crs, target_crs=target_crs)
    assert_same_statistics(got, expected)
    assert got[name]["count"].sum() > 10_000


def test_streaming_yields_bounded_chunks(pdal, synthetic):
    total = laspy.read(synthetic[0]).header.point_count
    sizes = [len(c) for c in iter_pdal_chunks(synthetic[0], 4_000, PdalRead(None, None, total))]
    assert max(sizes) <= 4_000 and len(sizes) >= total // 4_000 and sum(sizes) == total


def test_filters_range_on_class_drops_what_drop_classes_drops(pdal, synthetic, tmp_path):
    pipeline = write_pipeline(tmp_path / "p.json", [{"type": "filters.range", "limits": "Classification![6:6]"}])
    plain = bin_survey(synthetic, tmp_path)
    expected = bin_survey(synthetic, tmp_path, "filter.drop_classes=[6, 7, 18]")
    got = bin_survey(synthetic, tmp_path, "read.reader='pdal'", f"read.pdal_pipeline='{pipeline}'")
    assert_same_statistics(got, expected)
    changed = sum(int((got[n]["zmax"] != plain[n]["zmax"]).sum()) for n in plain)
    assert changed > 100  # the buildings' points did matter


def test_filters_range_on_z_changes_exactly_the_pixels_of_the_removed_points(pdal, synthetic, tmp_path):
    """Expected: laspy on a copy of the tile holding only the kept points (same header scale and offset)."""
    pipeline = write_pipeline(tmp_path / "p.json", [{"type": "filters.range", "limits": "Z[:58]"}])
    kept = []
    for path in synthetic:
        las = laspy.read(path)
        las.points = las.points[np.asarray(las.z) <= 58]
        copy = tmp_path / "kept" / Path(path).name
        copy.parent.mkdir(exist_ok=True)
        las.write(copy)
        kept.append(str(copy))
    got = bin_survey(synthetic, tmp_path, "read.reader='pdal'", f"read.pdal_pipeline='{pipeline}'")
    # the copies' header bounds are smaller: compare on the absolute lattice
    full = bin_survey(synthetic, tmp_path)
    expected = bin_survey(kept, tmp_path)
    for name, tile in got.items():
        shape = expected[name]["count"].shape
        col = expected[name]["corner"][0] - tile["corner"][0]
        row = tile["corner"][1] - expected[name]["corner"][1]
        rows, cols = slice(row, row + shape[0]), slice(col, col + shape[1])
        for key in STATISTICS:
            np.testing.assert_array_equal(tile[key][rows, cols], expected[name][key], err_msg=f"{name} {key}")
        outside = np.ones(tile["count"].shape, bool)
        outside[rows, cols] = False
        assert not tile["count"][outside].any()
        assert (tile["zmax"][tile["count"] > 0] <= 58).all()
        assert (full[name]["zmax"] > 58).sum() > 100  # the filter removed points where they were highest


def test_filters_outlier_needs_whole_tiles_and_then_drops_the_outliers(pdal, tmp_path, rng):
    x, y, z = random_points(rng, 20_000, (0.0, 0.0, 60.0, 60.0))
    spikes = rng.choice(len(x), 15, replace=False)
    z = z.copy()
    z[spikes] += 200.0  # isolated returns far above everything (birds, multipath)
    path = str(write_points(tmp_path / "spiky.laz", x, y, z))
    stages = [{"type": "filters.outlier", "method": "statistical", "mean_k": 8, "multiplier": 3.0}]
    pipeline = write_pipeline(tmp_path / "outlier.json", stages)
    with pytest.raises(ConfigError, match=r"stage 1 \(filters.outlier\) cannot run in PDAL's streaming mode"):
        load_user_pipeline(pipeline)
    plain = bin_survey([path], tmp_path, "read.reader='pdal'")
    cleaned = bin_survey(
        [path], tmp_path, "read.reader='pdal'", f"read.pdal_pipeline='{pipeline}'", "read.pdal_streaming=false"
    )["spiky.laz"]
    assert (plain["spiky.laz"]["zmax"] > 200).sum() == 15
    assert np.nanmax(cleaned["zmax"]) < 200  # classified 7 (low noise) by PDAL, dropped by filter.drop_classes
    assert cleaned["count"].sum() >= plain["spiky.laz"]["count"].sum() - 15 - 200  # few real points lost


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ('[{"type": "filters.range",', "not valid JSON"),
        ('{"stages": []}', "expected a JSON list of filter stages"),
        ('["input.laz", {"type": "filters.range"}]', "stage 1 is a file name ('input.laz')"),
        ('[{"type": "readers.las", "filename": "a.laz"}]', "stage 1 (readers.las) is a reader"),
        ('[{"type": "filters.range"}, {"type": "writers.las"}]', "stage 2 (writers.las) is a writer"),
        ('[{"type": "filters.nosuchfilter"}]', "stage 1 (filters.nosuchfilter) is not a stage this PDAL knows"),
        ('[{"type": "filters.smrf"}]', "stage 1 (filters.smrf) cannot run in PDAL's streaming mode"),
        ('[{"type": "filters.reprojection"}]', "stage 1 (filters.reprojection) has no out_srs"),
        ('[{"type": "filters.reprojection", "out_srs": "EPSG:99999999"}]', "is not a CRS pyproj understands"),
    ],
)
def test_bad_pipeline_file_is_one_line_naming_file_and_stage(pdal, synthetic, tmp_path, content, message):
    bad = tmp_path / "bad.json"
    bad.write_text(content)
    result = CliRunner().invoke(main, ["run", synthetic[0], "--out", str(tmp_path / "o"), "--pdal-pipeline", str(bad)])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and str(bad) in lines[0] and message in lines[0], lines
    assert not (tmp_path / "o").exists()


@pytest.mark.realdata
def test_user_reprojection_becomes_the_survey_crs(pdal, shared_data, tmp_path):
    """filters.reprojection decides the survey CRS; the DSM equals holefill's own --target-crs one."""
    name = "ign_crop2_water.laz"
    inputs = [str(shared_data / name)]
    pipeline = write_pipeline(tmp_path / "utm.json", [{"type": "filters.reprojection", "out_srs": "EPSG:32631"}])
    with pytest.raises(ConfigError, match="is not the survey CRS: set survey.target_crs = 'EPSG:32631'"):
        bin_survey(inputs, tmp_path, "read.reader='pdal'", f"read.pdal_pipeline='{pipeline}'")
    expected = bin_survey(inputs, tmp_path, target_crs="EPSG:32631")[name]
    got = bin_survey(
        inputs, tmp_path, "read.reader='pdal'", f"read.pdal_pipeline='{pipeline}'", target_crs="EPSG:32631"
    )[name]
    assert got["window"] == expected["window"]
    np.testing.assert_array_equal(got["count"], expected["count"])
    np.testing.assert_array_equal(got["zmax"], expected["zmax"])

    runner = CliRunner()
    conflict = runner.invoke(
        main, ["run", *inputs, "--out", str(tmp_path / "o"), "--pdal-pipeline", pipeline, "--target-crs", "EPSG:2154"]
    )
    assert conflict.exit_code == 2
    assert "out_srs 'EPSG:32631' conflicts with survey.target_crs 'EPSG:2154'" in conflict.output


@pytest.mark.slow
@pytest.mark.realdata
def test_run_with_the_pdal_reader_writes_the_laspy_dsm(pdal, shared_data, tmp_path, dask_client):
    """End to end on a Dask cluster: the tasks carry the PDAL read to the workers."""
    from pipeline.io.raster import read_raster
    from pipeline.run import run_survey

    inputs = [str(shared_data / "ign_crop1.laz")]
    dsms = {}
    for reader in ("laspy", "pdal"):
        config = load_config(overrides=["grid.resolution_m=0.5", f"read.reader='{reader}'"])
        summary = run_survey(inputs, tmp_path / reader, config, client=dask_client)
        dsms[reader] = read_raster(tmp_path / reader / "dsm.vrt")[0]
        assert summary.points_read == 210_582
    assert np.isfinite(dsms["pdal"]).sum() > 0.9 * dsms["pdal"].size
    np.testing.assert_array_equal(dsms["pdal"], dsms["laspy"])
