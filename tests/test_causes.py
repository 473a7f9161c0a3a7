"""Tests of pipeline.holes.causes: the cause rules are configuration data ([causes])."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.config import SECTIONS, Config, load_config
from pipeline.errors import ConfigError
from pipeline.holes import CauseRules, classify_causes
from pipeline.holes.causes import RULES
from pipeline.parameters import CONFIG_KEYS, cause_rules, default_cause_rules

from .test_holes import run


def big_hole_cause(catalog, rules: CauseRules):
    causes = classify_causes(catalog.stats, rules)
    return causes[np.argmax(catalog.holes["area_px"])]


def rules_for(config: Config) -> CauseRules:
    return cause_rules(config, pixel_size_m=1.0, vertical_unit_m=1.0)


def test_every_cause_rule_field_maps_to_a_config_key():
    fields = [f.name for f in dataclasses.fields(CauseRules)]
    assert list(CONFIG_KEYS) == fields
    for field, key in CONFIG_KEYS.items():
        section, name = key.split(".")
        assert name in {f.name for f in dataclasses.fields(SECTIONS[section])}, f"{field}: no config key {key}"
    # and every [causes] key is a threshold of the rules
    used = {key for key in CONFIG_KEYS.values() if key.startswith("causes.")}
    assert used == {f"causes.{f.name}" for f in dataclasses.fields(SECTIONS["causes"])}


def test_cause_rules_from_config_are_in_survey_units():
    config = load_config(overrides=["holes.jump_threshold_m=3.0", "causes.max_shadow_ratio=0.6"])
    rules = cause_rules(config, pixel_size_m=2.0, vertical_unit_m=0.3048)
    assert rules.jump_threshold == 3.0 / 0.3048
    assert rules.pixel_size == 2.0 / 0.3048
    assert rules.max_shadow_ratio == 0.6
    assert rules.pixel_area_m2 == 4.0  # areas stay in m2 (water_min_rim_area_m2)
    for field, key in CONFIG_KEYS.items():
        if key.startswith("causes."):
            assert getattr(rules, field) == getattr(config.causes, field)
    # the defaults are those of the configuration
    defaults = default_cause_rules(
        pixel_size=2.0 / 0.3048, jump_threshold=3.0 / 0.3048, max_shadow_ratio=0.6, pixel_area_m2=4.0
    )
    assert defaults == rules


def test_a_changed_config_key_changes_a_cause():
    rng = np.random.default_rng(1)
    z = 100 + rng.normal(0, 0.03, (96, 96))
    count = np.ones((96, 96), np.uint32)
    z[20:60, 20:45] += 12.0  # a 12 m building
    count[20:60, 45:51] = 0  # its scan shadow: 6 px wide band along the east wall
    _, _, catalog = run(count, z, cell_px=64, min_area_px=10)
    assert big_hole_cause(catalog, rules_for(load_config()))["cause"] == "occlusion"
    # a 6 px band beside a 12 m wall is no shadow if shadows must be under 0.1 x the wall's height
    narrow = rules_for(load_config(overrides=["causes.max_shadow_ratio=0.1"]))
    assert big_hole_cause(catalog, narrow)["cause"] != "occlusion"


def strip_catalog():
    """A 12 px straight void across a flat 200 px field: a strip."""
    rng = np.random.default_rng(5)
    n = 200
    z = 50 + rng.normal(0, 0.05, (n, n))
    count = np.ones((n, n), np.uint32)
    count[90:102, :] = 0
    return run(count, z, cell_px=64, min_area_px=10)[2]


def test_a_changed_strip_key_changes_missed_coverage():
    catalog = strip_catalog()
    assert big_hole_cause(catalog, rules_for(load_config()))["cause"] == "missed_coverage"
    longer = rules_for(load_config(overrides=["causes.strip_min_length_px=500"]))
    assert big_hole_cause(catalog, longer)["cause"] != "missed_coverage"


def test_rule_order_is_one_table():
    assert [rule for rule, _ in RULES] == [
        "water_mask",
        "covered",
        "water_ring",
        "missing_tile",
        "coverage_gap",
        "water_points",
        "line_of_sight",
        "water_edge",
        "jumps",
        "shadow",
        "strip",
        "level_rim",
        "flat_low_rim",
        "river_rim",
        "seen",
    ]


@pytest.mark.parametrize(
    "override, words",
    [
        ("causes.low_quantile=1.5", ["causes.low_quantile", "<= 1"]),
        ("causes.strip_min_fill=-1", ["causes.strip_min_fill", ">= 0"]),
        ("causes.low_quantile=0.99", ["causes.low_quantile", "below", "causes.high_quantile"]),
    ],
)
def test_bad_cause_thresholds_are_refused(override, words):
    with pytest.raises(ConfigError) as info:
        load_config(overrides=[override])
    for word in words:
        assert word in str(info.value)


def test_a_straight_void_is_no_strip_where_the_flight_lines_bands_are_known():
    # with bands, a missed strip is a coverage gap checked against the pixels; a straight void
    # that is none (a canal along the seam of two lines) is not missed coverage
    catalog = strip_catalog()
    rules = rules_for(load_config())
    assert big_hole_cause(catalog, rules)["rule"] == "strip"
    causes = classify_causes(catalog.stats, rules, bands_known=True)
    assert causes[np.argmax(catalog.holes["area_px"])]["cause"] != "missed_coverage"


def test_a_level_rim_is_no_water_on_heights_above_the_ground():
    """On heights above the ground the ground is z = 0 everywhere: a void in a bare field has a
    level, low rim (``flat_low_rim``: water on elevations) and is no water there
    (lidR's Megaplot: two cut voids in a clearing were flattened as lakes)."""
    rng = np.random.default_rng(3)
    z = np.abs(rng.normal(0, 0.02, (96, 96)))  # bare ground at 0, a few centimetres of noise
    count = np.ones((96, 96), np.uint32)
    count[30:50, 30:50] = 0  # a 400 px void
    _, _, catalog = run(count, z, cell_px=64, min_area_px=10)
    rules = rules_for(load_config())
    assert big_hole_cause(catalog, rules)["cause"] == "water"
    above = classify_causes(catalog.stats, rules, above_ground=True)[np.argmax(catalog.holes["area_px"])]
    assert above["cause"] == "unknown"
