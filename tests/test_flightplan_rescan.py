"""Re-scans of occlusions: lanes where the hole's ground is in the lidar's sight (pipeline.flightplan.rescan)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
from affine import Affine
from pyproj import CRS

from pipeline.config import load_config
from pipeline.flight_planning import plan_flights
from pipeline.flightplan import CoverageParams, FlightParams, HoleInput, plan_mission, plan_pattern
from pipeline.flightplan.rescan import SightParams, place_pattern
from pipeline.io.raster import write_cog
from pipeline.io.vector import read_layer, write_layer

from . import test_flightplan_files as file_checks

X0, Y0 = 700000.0, 6600000.0  # Lambert-93: 3 deg E, 46.5 deg N, as in test_flightplan_files
ROOF_M = 30.0


def _building_scene(x0: float = 0.0, y0: float = 0.0, *, west: float = 125.0, east: float = 145.0):
    """Flat ground at 0 m, 300 x 300 m at 1 m; a block building ``ROOF_M`` high from x ``west`` to ``east``."""
    dsm = np.zeros((300, 300), np.float32)
    dsm[100:200, int(west) : int(east)] = ROOF_M  # rows 100..200: y 100..200 from the top (y0 + 300)
    return dsm, Affine(1.0, 0, x0, 0, -1.0, y0 + 300)


def _placed(holes, pattern, dsm, transform, *, rescan):
    placement = place_pattern(pattern, holes, dsm, transform, params=SightParams(CoverageParams()), rescan=rescan)
    return placement


def test_an_occlusion_behind_a_building_is_seen_from_its_rescan():
    """The shadow east of the building (ground at 0, behind a 30 m wall) is seen from the lanes chosen."""
    dsm, transform = _building_scene()
    hole = shapely.box(145, 110, 153, 190)
    params = FlightParams(causes=("missed_coverage", "occlusion"))
    plan = plan_mission(
        [HoleInput(1, hole, "occlusion", hole.area)], dsm, transform, crs_wkt="EPSG:2154", params=params,
        home=(20.0, 20.0),
    )  # fmt: skip
    (decision,) = plan.decisions
    assert decision.planned and decision.visible_share >= 0.95
    assert all(s.least_clearance_m >= params.min_clearance_m for s in plan.sorties)
    heights = {
        (w.pattern_id, w.lane_index): w.height_m for s in plan.sorties for w in s.waypoints if w.lane_index is not None
    }
    assert min(heights.values()) >= ROOF_M + params.coverage.altitude_agl_m - 1e-6  # level, above the roof


def test_shadows_on_both_sides_get_a_lane_on_each_side_instead_of_one_over_the_roof():
    """One lane over the roof sees neither foot of the walls; the re-scan puts a lane beside each wall."""
    dsm, transform = _building_scene()
    holes = [shapely.box(145, 110, 153, 190), shapely.box(117, 110, 125, 190)]
    pattern = plan_pattern(shapely.union_all(holes), params=CoverageParams(), hole_ids=(1, 2))
    assert len(pattern.lanes) == 1 and 125 < pattern.lanes[0].start[0] < 145  # the regular lane: over the roof
    regular = _placed(holes, pattern, dsm, transform, rescan=False)
    assert max(regular.shares.values()) < 0.8 and not regular.placed
    placed = _placed(holes, pattern, dsm, transform, rescan=True)
    assert placed.placed and min(placed.shares.values()) >= 0.95
    xs = sorted(lane.start[0] for lane in placed.pattern.lanes)
    assert len(xs) == 2 and xs[0] < 135 < xs[1]  # one lane on each side of the roof's middle
    assert placed.pattern.azimuth_deg == pattern.azimuth_deg  # parallel to the holes' long axis


def test_a_lane_out_of_the_field_of_view_sees_nothing():
    """The lidar's half field of view bounds what a lane sees: a narrow scanner far off sees none of the hole."""
    dsm, transform = _building_scene()
    hole = shapely.box(145, 110, 153, 190)
    narrow = CoverageParams(fov_deg=10.0, margin_m=0.0)
    pattern = plan_pattern(hole, params=narrow, hole_ids=(1,))
    far = pattern.lanes[0]
    shifted = type(pattern)(
        pattern.pattern_id, pattern.hole_ids, pattern.area, pattern.rectangle, pattern.azimuth_deg, pattern.spacing_m,
        (type(far)(0, (far.start[0] + 60, far.start[1]), (far.end[0] + 60, far.end[1])),), pattern.turnaround_m,
    )  # fmt: skip
    placement = place_pattern(shifted, [hole], dsm, transform, params=SightParams(narrow), rescan=False)
    assert placement.shares[1] == 0.0
    rescanned = place_pattern(shifted, [hole], dsm, transform, params=SightParams(narrow), rescan=True)
    assert rescanned.shares[1] >= 0.95


def test_missed_coverage_lanes_keep_their_pattern_and_report_their_share():
    dsm, transform = _building_scene()
    hole = shapely.box(200, 110, 230, 190)  # open ground, away from the building
    params = FlightParams()
    plan = plan_mission(
        [HoleInput(1, hole, "missed_coverage", hole.area)], dsm, transform, crs_wkt="EPSG:2154", params=params,
        home=(20.0, 20.0),
    )  # fmt: skip
    assert plan.patterns[0].lanes == plan_pattern(hole, params=params.coverage, pattern_id=1, hole_ids=(1,)).lanes
    assert plan.decisions[0].visible_share == 1.0


@pytest.fixture(scope="module")
def rescan_survey(tmp_path_factory):
    """The building scene in EPSG:2154 on disk, with its shadow as an occlusion hole."""
    folder = tmp_path_factory.mktemp("rescan")
    crs = CRS("EPSG:2154").to_wkt()
    dsm, transform = _building_scene(X0, Y0)
    dsm += 100.0  # ground at 100 m
    hole = shapely.box(X0 + 145, Y0 + 110, X0 + 153, Y0 + 190)
    write_layer(
        folder / "holes.gpkg", "holes", [{"hole_id": 1, "area_m2": hole.area, "cause": "occlusion"}],
        [shapely.MultiPolygon([hole])], crs_wkt=crs, geometry_type="MultiPolygon",
    )  # fmt: skip
    write_cog(folder / "dsm.tif", dsm, transform=transform, crs_wkt=crs)
    config = load_config(overrides=['flightplan.causes=["missed_coverage","occlusion"]'])
    out = folder / "out"
    summary = plan_flights(folder / "holes.gpkg", folder / "dsm.tif", config, out, home=(X0 + 20, Y0 + 20))
    return out, summary, [hole]


def test_the_rescan_share_is_in_the_layer_and_the_summary(rescan_survey):
    out, summary, _ = rescan_survey
    assert summary["holes_planned"] == 1 and summary["hole_visible_share"][1] >= 0.95
    status = read_layer(out / "flightplan.gpkg", "holes_status").set_index("hole_id")
    assert status.loc[1, "visible_share"] == pytest.approx(summary["hole_visible_share"][1])
    assert math.isfinite(min(summary["sortie_min_clearance_m"]))


@pytest.mark.parametrize(
    "check",
    [
        file_checks.test_waypoints_files_load_in_pymavlink,
        file_checks.test_plan_validates_against_the_qgc_schema_and_round_trips,
        file_checks.test_kmz_holds_both_wpml_files_with_consecutive_indices,
        file_checks.test_kml_parses_with_explicit_altitude_mode,
    ],
    ids=lambda f: f.__name__.removeprefix("test_"),
)
def test_the_rescan_plan_files_pass_their_format_loaders(rescan_survey, check):
    check(rescan_survey)


def test_a_pattern_shared_with_missed_coverage_keeps_its_lanes_and_gains_one():
    """Missed coverage keeps its lanes (spacing, overlap); what they do not see, beside the walls, gets lanes of its own."""
    dsm, transform = _building_scene()
    holes = [shapely.box(145, 110, 153, 190), shapely.box(117, 110, 125, 190)]  # occlusion, missed coverage
    pattern = plan_pattern(shapely.union_all(holes), params=CoverageParams(), hole_ids=(1, 2))
    placed = place_pattern(
        pattern, holes, dsm, transform, params=SightParams(CoverageParams()), rescan=True, keep_lanes=True
    )
    assert set(pattern.lanes[0].start) <= {c for lane in placed.pattern.lanes for c in lane.start}
    assert len(placed.pattern.lanes) == 3 and min(placed.shares.values()) >= 0.95


def test_candidate_lanes_off_the_survey_are_no_candidates():
    """A hole at the survey's edge: lanes with no DSM under their swath have no height, and are skipped."""
    dsm, transform = _building_scene()
    dsm[:, :200] = np.nan  # no survey west of x = 200 m: the hole lies at its edge
    hole = shapely.box(200, 110, 210, 190)
    pattern = plan_pattern(hole, params=CoverageParams(), hole_ids=(1,))
    placed = place_pattern(pattern, [hole], dsm, transform, params=SightParams(CoverageParams()), rescan=True)
    assert placed.shares[1] >= 0.95
