"""Named scenes for measuring hole causes one at a time (``bench/bench_causes.py``, the tests).

Each is the ``unit`` preset's 2 m pixels at 0.75 m pulse spacing -- 1.8 pulses/m2, so
that ``grid.resolution_m = "auto"`` picks the truth's 2 m pixels even with a missed
strip -- flown as the default survey (300 m above ground, 20 degree scan: a 218 m
swath, lines 152 m apart), on 100 m or 50 m tiles (sizes a tile grid is recognised by),
with one kind of hole made on purpose; building shadows come with every scene.
"""

from __future__ import annotations

from typing import Any

from .spec import SurveySpec, preset

#: Acquisition shared by the scenes.
_BASE: dict[str, Any] = dict(
    resolution=2.0, pulse_spacing_m=0.75, flight_altitude_m=300.0, tile_size_m=100.0, missed_line=None
)

#: Scene name -> the fields it sets over ``_BASE`` (the ``unit`` preset underneath).
CAUSE_SCENES: dict[str, dict[str, Any]] = {
    # three lakes, 20-80 m across, in rolling terrain with buildings and trees
    "lakes": dict(width_m=400.0, height_m=300.0, water=False, lakes=3),
    # a 12 m river whose water falls west to east, 500 m long (and the same river flat: the control);
    # 300 m along track, as every scene here: the bands of the flight lines need length / width
    # >= 1.4 (holes/coverage.py) before a hole can count as inside a swath (level_rim)
    "river_flat": dict(width_m=500.0, height_m=300.0, water_width_m=12.0),
    "river_fall_2": dict(width_m=500.0, height_m=300.0, water_width_m=12.0, river_fall_m_per_km=2.0),
    "river_fall_5": dict(width_m=500.0, height_m=300.0, water_width_m=12.0, river_fall_m_per_km=5.0),
    "river_fall_10": dict(width_m=500.0, height_m=300.0, water_width_m=12.0, river_fall_m_per_km=10.0),
    # a N-S canal between rows of 10-20 m houses; 10 % side overlap: the canal is seen by one
    # line, off nadir, so the houses' scan shadows fall on the street and the water
    "canal": dict(width_m=300.0, height_m=300.0, water=False, canal=True, side_overlap=0.1),
    # line 1 dropped: its strip (u 207-294 m) runs N-S across the tile rows, inside one tile column
    "strip_across_tiles": dict(width_m=400.0, height_m=300.0, water=False, missed_line=1),
    # the same scene on 50 m tiles: the tile boundary u = 250 m runs along the strip, inside it, so
    # the tiles' header bounds stop at the strip on both sides (a gap between the tiles' extents)
    "strip_along_tile_edge": dict(width_m=400.0, height_m=300.0, tile_size_m=50.0, water=False, missed_line=1),
    # a 12 m river crossing the missed strip
    "river_across_strip": dict(width_m=400.0, height_m=300.0, water_width_m=12.0, missed_line=1),
}


def cause_scene(name: str, seed: int = 0) -> SurveySpec:
    """The spec of a named scene of :data:`CAUSE_SCENES` with a seed."""
    try:
        fields = CAUSE_SCENES[name]
    except KeyError:
        raise ValueError(f"unknown cause scene {name!r}; choose one of {sorted(CAUSE_SCENES)}") from None
    return preset("unit", **{**_BASE, **fields, "seed": seed})
