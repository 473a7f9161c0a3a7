"""Heights above the ground ("normalised") are recognised from the ground-class points."""

from __future__ import annotations

import json

import numpy as np

from pipeline.config import load_config
from pipeline.run import run_survey
from pipeline.survey.ground_level import MIN_GROUND_POINTS, GroundLevel, count_ground_at_zero

from .lasfiles import write_points


def ground(z):
    return count_ground_at_zero(np.asarray(z, np.float64), np.ones(len(z), bool))


def test_ground_at_zero_is_counted_and_adds_up():
    z = np.array([0.0, 0.05, -0.1, 0.11, -0.3, 12.0])
    assert ground(z) == GroundLevel(points=6, at_zero=3)
    assert ground(z) + ground(np.zeros(4)) == GroundLevel(points=10, at_zero=7)
    is_ground = np.array([True, True, False, True, True, True])
    assert count_ground_at_zero(z, is_ground) == GroundLevel(points=5, at_zero=2)


def test_raw_integers_count_as_their_heights():
    # LAS integers: z = raw * scale + offset; the bounds are taken in integers
    raw = np.array([-10, 9, 10, 11, 990, -2_000_000_000, 2_000_000_000], np.int32)
    assert count_ground_at_zero(raw, np.ones(7, bool), scale=0.01) == GroundLevel(points=7, at_zero=3)
    # an offset far from 0 puts the bounds outside int32: nothing is at zero, and nothing overflows
    assert count_ground_at_zero(raw, np.ones(7, bool), scale=0.001, offset=6e6).at_zero == 0
    shifted = np.array([-1000, -1001, -999, -1011], np.int32)  # 10.00, 9.99, 10.01, 9.89 - 10
    assert count_ground_at_zero(shifted, np.ones(4, bool), scale=0.01, offset=10.0).at_zero == 3


def test_normalised_needs_nearly_all_ground_at_zero_and_enough_of_it():
    rng = np.random.default_rng(0)
    assert ground(rng.normal(0.0, 0.01, 5000)).normalised
    # ground near sea level is no normalised survey (AHN3 Delft: 0.35 +- 0.28 m)
    assert not ground(rng.normal(0.35, 0.28, 5000)).normalised
    # nor one tile of polder at 0 among tiles of hills: the survey's share decides
    assert not (ground(np.zeros(5000)) + ground(rng.normal(40.0, 5.0, 5000))).normalised
    assert not ground(np.zeros(MIN_GROUND_POINTS - 1)).normalised
    assert not GroundLevel().normalised


def _scene(tmp_path, base_height: float):
    """A 120 x 100 m field with a 12 m building and a 25 x 12 m void on open ground; ground class 2."""
    rng = np.random.default_rng(3)
    x = np.round(rng.uniform(1000.0, 1120.0, 60_000), 2)
    y = np.round(rng.uniform(2000.0, 2100.0, 60_000), 2)
    building = (np.abs(x - 1030) < 8) & (np.abs(y - 2070) < 6)
    void = (np.abs(x - 1080) < 12.5) & (np.abs(y - 2030) < 6)
    x, y, building = x[~void], y[~void], building[~void]
    z = np.where(building, 12.0, np.round(rng.normal(0.0, 0.02, len(x)), 2)) + base_height
    classes = np.where(building, 6, 2).astype(np.uint8)
    return write_points(tmp_path / f"field_{base_height:g}.laz", x, y, z, classification=classes)


def test_a_run_on_heights_above_ground_says_so_and_plans_no_flight(tmp_path, dask_client):
    config = load_config(overrides=["grid.resolution_m=1"])
    out = tmp_path / "normalised"
    summary = run_survey([str(_scene(tmp_path, 0.0))], out, config, client=dask_client)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["heights"]["heights"] == "above_ground"
    assert summary.holes["listed"] >= 1
    assert "terrain is unknown" in manifest["flightplan"]["not_planned"]
    assert not list(out.glob("flightplan*"))
    assert "no re-flight plan" in (out / "report.html").read_text()
    # the same field 80 m above the sea: elevations, and the flight planner decides on the void
    out = tmp_path / "elevations"
    run_survey([str(_scene(tmp_path, 80.0))], out, config, client=dask_client)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["heights"]["heights"] == "elevation"
    assert manifest["flightplan"]["holes"] >= 1 and "not_planned" not in manifest["flightplan"]
    assert (out / "flightplan.gpkg").exists()
