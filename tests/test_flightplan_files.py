"""Flight-plan files end to end: holes.gpkg + DSM COG -> plan_flights -> every format read back."""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

import numpy as np
import pytest
import rasterio
import rasterio.windows
import shapely
from affine import Affine
from pyproj import CRS

from pipeline.config import load_config
from pipeline.errors import ConfigError
from pipeline.flight_planning import plan_flights
from pipeline.io.flightplan_files import DsmWindows, open_dsm, sortie_file_names
from pipeline.io.raster import write_cog
from pipeline.io.vector import list_layers, read_layer, write_layer

from .conftest import REPO

SCHEMA = REPO.parent / "shared" / "formats" / "qgc_plan.schema.json"
X0, Y0 = 700000.0, 6600000.0  # Lambert-93 origin: 3 deg E, 46.5 deg N
WPML = "{http://www.dji.com/wpmz/1.0.2}"
KML = "{http://www.opengis.net/kml/2.2}"


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    """Four holes (one occluded) over a sloping DSM COG in EPSG:2154."""
    folder = tmp_path_factory.mktemp("flightplan")
    crs = CRS("EPSG:2154").to_wkt()
    transform = Affine(1.0, 0, X0 - 500, 0, -1.0, Y0 + 1500)
    cols = np.arange(2000)[None, :]
    dsm = (100 + 20 * np.sin(cols / 200.0) + np.zeros((2000, 1))).astype(np.float32)
    dsm[300:330, 700:900] = np.nan  # a void in the DSM itself
    holes = [
        shapely.affinity.rotate(shapely.box(X0 + 100, Y0 + 200, X0 + 400, Y0 + 230), 25),
        shapely.box(X0 + 600, Y0 + 800, X0 + 700, Y0 + 900),
        shapely.box(X0 + 620, Y0 + 950, X0 + 700, Y0 + 980),
        shapely.box(X0 - 200, Y0 + 1000, X0 - 150, Y0 + 1100),
    ]
    causes = ["missed_coverage", "missed_coverage", "missed_coverage", "occlusion"]
    write_layer(
        folder / "holes.gpkg",
        "holes",
        [{"hole_id": i + 1, "area_m2": h.area, "cause": c} for i, (h, c) in enumerate(zip(holes, causes))],
        [shapely.MultiPolygon([h]) for h in holes],
        crs_wkt=crs,
        geometry_type="MultiPolygon",
    )
    write_cog(folder / "dsm.tif", dsm, transform=transform, crs_wkt=crs)
    return folder, holes


@pytest.fixture(scope="module", params=[1, 3], ids=["one-sortie", "several-sorties"])
def planned(request, survey):
    folder, holes = survey
    limit = 2000.0 if request.param == 1 else 260.0
    config = load_config(overrides=[f"flightplan.max_flight_time_s={limit}", "flightplan.setup_time_s=30"])
    out = folder / f"out{request.param}"
    summary = plan_flights(folder / "holes.gpkg", folder / "dsm.tif", config, out)
    return out, summary, holes


def test_summary_and_layers(planned):
    out, summary, _ = planned
    assert summary["holes"] == 4 and summary["holes_planned"] == 3
    assert (summary["sorties"] == 1) == (out.name == "out1")
    assert all(t <= (2000.0 if out.name == "out1" else 260.0) for t in summary["sortie_durations_s"])
    assert "occlusion" in summary["holes_not_planned"][4]
    assert summary["improved_route_m"] <= summary["greedy_route_m"] + 1e-6
    assert set(list_layers(out / "flightplan.gpkg")) >= {"flight_lines", "waypoints", "route", "holes_status"}
    route = read_layer(out / "flightplan.gpkg", "route")
    assert len(route) == summary["sorties"]
    lines = read_layer(out / "flightplan.gpkg", "flight_lines")
    assert {"hole_ids", "pattern_id", "sortie", "lane_index", "length_m", "azimuth_deg"} <= set(lines.columns)
    waypoints = read_layer(out / "flightplan.gpkg", "waypoints")
    assert {"sortie", "sequence", "altitude_m", "altitude_ref", "action"} <= set(waypoints.columns)
    assert (
        waypoints["altitude_ref"]
        .str.fullmatch(r"relative to take-off \((ground points|DSM \(no ground points\)) at home\)")
        .all()
    )
    status = read_layer(out / "flightplan.gpkg", "holes_status")
    assert status.set_index("hole_id").loc[4, "planned"] == 0


def test_files_per_sortie_are_named_by_sortie(planned):
    out, summary, _ = planned
    n = summary["sorties"]
    assert (n == 1) == (sortie_file_names(n) == ["flightplan"])
    for stem in sortie_file_names(n):
        for ext in ("plan", "waypoints", "kmz", "kml"):
            assert (out / f"{stem}.{ext}").is_file()


def test_waypoints_files_load_in_pymavlink(planned):
    mavwp = pytest.importorskip("pymavlink.mavwp")
    out, summary, _ = planned
    for stem in sortie_file_names(summary["sorties"]):
        path = out / f"{stem}.waypoints"
        lines = path.read_text().splitlines()
        assert lines[0] == "QGC WPL 110"
        loader = mavwp.MAVWPLoader()
        count = loader.load(str(path))
        assert count == len(lines) - 1 == loader.count()
        home = loader.wp(0)
        assert (home.x, home.y) == pytest.approx((float(lines[1].split("\t")[8]), float(lines[1].split("\t")[9])))
        for i, line in enumerate(lines[1:]):
            fields = line.split("\t")
            wp = loader.wp(i)
            assert wp.seq == i and wp.command == int(fields[3])
            assert wp.x == pytest.approx(float(fields[8]), abs=1e-6) and wp.y == pytest.approx(
                float(fields[9]), abs=1e-6
            )
            if wp.command == 16:
                assert 46.4 < wp.x < 46.6 and 2.9 < wp.y < 3.1


def test_plan_validates_against_the_qgc_schema_and_round_trips(planned):
    jsonschema = pytest.importorskip("jsonschema")
    if not SCHEMA.is_file():
        pytest.skip(f"QGC plan schema not found at {SCHEMA}")
    schema = json.loads(SCHEMA.read_text())
    out, summary, _ = planned
    gpkg = read_layer(out / "flightplan.gpkg", "waypoints")
    for k, stem in enumerate(sortie_file_names(summary["sorties"]), start=1):
        text = (out / f"{stem}.plan").read_text()
        assert "NaN" not in text
        plan = json.loads(text)
        jsonschema.validate(plan, schema)
        items = plan["mission"]["items"]
        assert all(len(item["params"]) == 7 for item in items)
        commands = [item["command"] for item in items]
        assert commands[0] == 22 and commands[-1] == 20 and 178 in commands
        assert commands.count(206) == 2 * len(
            read_layer(out / "flightplan.gpkg", "flight_lines").query(f"sortie == {k}")
        )
        home = plan["mission"]["plannedHomePosition"]
        assert home[2] == pytest.approx(summary["home_ground_m"], abs=0.01) and home[2] > 50
        ours = gpkg[gpkg["sortie"] == k].sort_values("sequence")
        positions = [
            (item["params"][4], item["params"][5], item["params"][6]) for item in items if item["command"] in (16, 22)
        ]
        assert len(positions) == len(ours)
        for (lat, lon, alt), row in zip(positions, ours.itertuples()):
            assert lat == pytest.approx(row.lat, abs=1e-8) and lon == pytest.approx(row.lon, abs=1e-8)
            assert alt == pytest.approx(row.altitude_m, abs=0.01)


def test_kmz_holds_both_wpml_files_with_consecutive_indices(planned):
    out, summary, _ = planned
    for stem in sortie_file_names(summary["sorties"]):
        with zipfile.ZipFile(out / f"{stem}.kmz") as archive:
            assert {"wpmz/template.kml", "wpmz/waylines.wpml"} <= set(archive.namelist())
            for name in ("wpmz/template.kml", "wpmz/waylines.wpml"):
                root = ET.fromstring(archive.read(name))
                indices = [int(e.text) for e in root.iter(f"{WPML}index")]
                assert indices == list(range(len(indices))) and indices
            waylines = ET.fromstring(archive.read("wpmz/waylines.wpml"))
            assert waylines.find(f".//{WPML}executeHeightMode").text == "relativeToStartPoint"
            operations = [e.text for e in waylines.iter(f"{WPML}recordPointCloudOperate")]
            assert operations and operations[0] == "startRecord" and operations[-1] == "stopRecord"
            assert operations.count("startRecord") == operations.count("stopRecord")


def test_kml_parses_with_explicit_altitude_mode(planned):
    out, summary, _ = planned
    for stem in sortie_file_names(summary["sorties"]):
        root = ET.parse(out / f"{stem}.kml").getroot()
        modes = {e.text for e in root.iter(f"{KML}altitudeMode")}
        assert modes == {"absolute"}
        for coords in root.iter(f"{KML}coordinates"):
            for triple in coords.text.split():
                lon, lat, alt = map(float, triple.split(","))
                assert 2.9 < lon < 3.1 and 46.4 < lat < 46.6 and math.isfinite(alt)


def test_every_planned_hole_is_covered_by_the_written_lanes(planned):
    out, summary, holes = planned
    lines = read_layer(out / "flightplan.gpkg", "flight_lines")
    config = load_config()
    spacing = (
        2
        * config.flightplan.altitude_agl_m
        * math.tan(math.radians(config.flightplan.fov_deg / 2))
        * (1 - config.flightplan.side_overlap)
    )
    covered = shapely.union_all([g.buffer(spacing / 2 + 1e-3) for g in lines.geometry])
    for hole in holes[:3]:
        assert covered.contains(hole)


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        ("flightplan.side_overlap=0.95", r"flightplan\.side_overlap = 0\.95 is invalid; expected a number <= 0\.9"),
        ("flightplan.side_overlap=-0.1", r"flightplan\.side_overlap .* expected a number >= 0"),
        ("flightplan.fov_deg=180", r"flightplan\.fov_deg = 180\.0 is invalid; expected a number < 180"),
        ("flightplan.fov_deg=0", r"flightplan\.fov_deg .* expected a number > 0"),
        ("flightplan.home=[1.0]", r"flightplan\.home = \[1\.0\] is invalid; expected a list of 0 or 2 items"),
        ("flightplan.home=[1.0, 2.0, 3.0]", r"flightplan\.home .* a list of 0 or 2 items"),
    ],
)
def test_bad_flightplan_settings_are_refused_when_the_configuration_is_loaded(override, expected):
    """The ranges the planning relies on are the configuration's rules: no run starts with them wrong."""
    with pytest.raises(ConfigError, match=expected):
        load_config(overrides=[override])


def test_flightplan_settings_at_their_limits_are_accepted():
    config = load_config(
        overrides=["flightplan.side_overlap=0.9", "flightplan.fov_deg=179.9", "flightplan.home=[1, 2]"]
    )
    assert config.flightplan.side_overlap == 0.9 and config.flightplan.home == [1.0, 2.0]
    assert load_config(overrides=["flightplan.home=[]"]).flightplan.home == []


def test_bad_flightplan_causes_name_the_key():
    with pytest.raises(ConfigError, match="items among"):
        load_config(overrides=['flightplan.causes=["shadow"]'])


def test_ellipsoid_reference_is_refused_without_a_vertical_datum(survey, tmp_path):
    from pipeline.errors import CRSError

    folder, _ = survey
    config = load_config(overrides=['flightplan.altitude_reference="ellipsoid"'])
    with pytest.raises(CRSError, match="vertical"):
        plan_flights(folder / "holes.gpkg", folder / "dsm.tif", config, tmp_path)
    config = load_config(overrides=['flightplan.altitude_reference="ellipsoid"', 'flightplan.vertical_crs="EPSG:5720"'])
    try:
        plan_flights(folder / "holes.gpkg", folder / "dsm.tif", config, tmp_path)
    except CRSError as e:  # no geoid grid here: refused, nothing written
        assert "geoid grid" in str(e)
        assert not (Path(tmp_path) / "flightplan.plan").exists()


def test_holefill_plan_replans_into_a_folder_and_replaces_older_sorties(survey, tmp_path):
    from click.testing import CliRunner

    from pipeline.cli import main

    folder, _ = survey
    out = tmp_path / "replan"
    runner = CliRunner()
    args = ["plan", str(folder / "holes.gpkg"), "--dsm", str(folder / "dsm.tif"), "--out", str(out)]
    result = runner.invoke(
        main, [*args, "--set", "flightplan.max_flight_time_s=260", "--set", "flightplan.setup_time_s=30"]
    )
    assert result.exit_code == 0, result.output
    several = sorted(p.name for p in out.glob("flightplan_s*.plan"))
    assert len(several) >= 2
    # another drone, one sortie: the older sortie files go, nothing else is left behind
    result = runner.invoke(main, [*args, "--set", "flightplan.altitude_agl_m=90", "--home", f"{X0 + 600},{Y0 + 700}"])
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == [
        "flightplan.gpkg", "flightplan.kml", "flightplan.kmz", "flightplan.plan", "flightplan.waypoints",
    ]  # fmt: skip
    result = runner.invoke(main, [*args, "--home", "somewhere"])
    assert result.exit_code == 2 and "--home somewhere: expected X,Y" in result.output
    result = runner.invoke(
        main, ["plan", str(tmp_path / "none.gpkg"), "--dsm", str(folder / "dsm.tif"), "--out", str(tmp_path / "o")]
    )
    assert result.exit_code == 3 and "none.gpkg: holes file not found" in result.output
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("nodata", [-9999.0, float("nan"), None])
def test_the_dsm_read_block_by_block_is_the_dsm_read_whole(tmp_path, monkeypatch, nodata):
    """The planner reads the DSM of a wide survey block by block as it needs it (DsmWindows):
    pixels, windows and index arrays hold what one read of the span holds, evicted blocks read
    again the same, NaN where the DSM has no data (its nodata value, NaN as nodata, or none)."""
    rng = np.random.default_rng(5)
    heights = rng.normal(100, 5, (300, 420)).astype(np.float32)
    heights[rng.random(heights.shape) < 0.05] = np.nan
    path = write_cog(
        tmp_path / "dsm.tif", heights, transform=Affine(0.5, 0, 1000, 0, -0.5, 2000), crs_wkt="EPSG:2154", nodata=nodata
    )
    bounds = (1010.0, 1880.0, 1190.0, 1990.0)
    with rasterio.open(path) as src:  # one read of the span: columns 20-380, rows 20-240 at 0.5 m
        window = rasterio.windows.Window(20, 20, 360, 220)
        whole = src.read(1, window=window).astype(np.float64)
        whole[src.read_masks(1, window=window) == 0] = np.nan
        transform = src.transform @ Affine.translation(20, 20)
    monkeypatch.setattr(DsmWindows, "BLOCK", 64)
    monkeypatch.setattr(DsmWindows, "CACHE_BYTES", 3 * 64 * 64 * 4)  # three float32 blocks: most reads evict
    with open_dsm(path, bounds) as (dsm, same_transform, _):
        assert same_transform == transform and dsm.shape == whole.shape
        for _ in range(20):
            r0, c0 = rng.integers(0, whole.shape[0] - 1), rng.integers(0, whole.shape[1] - 1)
            r1, c1 = r0 + rng.integers(1, 150), c0 + rng.integers(1, 150)
            assert np.array_equal(dsm[r0:r1, c0:c1], whole[r0:r1, c0:c1], equal_nan=True)
            rows, cols = rng.integers(0, whole.shape[0], 40), rng.integers(0, whole.shape[1], 40)
            assert np.array_equal(dsm[rows, cols], whole[rows, cols], equal_nan=True)
            r, c = int(r0), int(c0)
            assert np.array_equal(dsm[r, c], whole[r, c], equal_nan=True)
        assert np.array_equal(np.asarray(dsm), whole, equal_nan=True)
        assert np.isnan(whole).any()
        assert dsm[0:5, 0:5].dtype == np.float64
