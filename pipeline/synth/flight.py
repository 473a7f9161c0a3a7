"""Acquisition geometry: the N-S flight lines of a spec (:func:`flight_lines`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .spec import BASE_HEIGHT_M, LINE_INTERVAL_S, SURVEY_START_GPS_TIME, SurveySpec


@dataclass(frozen=True)
class FlightLine:
    """One N-S flight line.

    Attributes
    ----------
    index : int
        Position from west (0) to east.
    line_id : int
        ``index + 1``; written as the points' ``point_source_id``.
    u : float
        Sensor track, metres east of ``x_min``.
    x : float
        Sensor track in CRS metres.
    sensor_z : float
        Absolute sensor height.
    half_swath_m : float
        Half-width of the pulse pattern on the ground (``n_across * spacing / 2``).
    n_across, n_along : int
        Pulses per scan line and scan lines per flight line.
    northbound : bool
        Lines alternate direction; GPS time increases along the direction flown.
    start_time : float
        GPS time of the first scan line.
    flown : bool
        False for the dropped line (``SurveySpec.missed_line``), which yields no points.
    """

    index: int
    line_id: int
    u: float
    x: float
    sensor_z: float
    half_swath_m: float
    n_across: int
    n_along: int
    northbound: bool
    start_time: float
    flown: bool

    def covers(self, u: np.ndarray) -> np.ndarray:
        """Whether local eastings lie inside the swath."""
        return np.abs(np.asarray(u) - self.u) <= self.half_swath_m


def flight_lines(spec: SurveySpec) -> list[FlightLine]:
    """Lay out the flight lines of a spec, west to east, including the dropped one.

    Lines are spaced by ``swath * (1 - side_overlap)``; the westernmost
    swath starts 5 % of a swath west of the extent and lines are added until
    the extent is covered with the same margin in the east.

    Raises
    ------
    ValueError
        ``missed_line`` is not a line index, or dropping it leaves no
        uncovered strip of at least two truth pixels inside the extent (e.g.
        ``side_overlap >= 0.5``, where the neighbours' swaths still meet).
    """
    spacing_m = spec.pulse_spacing_m
    n_across = max(1, math.floor(spec.swath_width_m / spacing_m))
    half_swath = n_across * spacing_m / 2.0
    line_spacing = 2.0 * half_swath * (1.0 - spec.side_overlap)
    margin = 0.05 * 2.0 * half_swath
    first_u = half_swath - margin
    n_lines = max(1, math.ceil((spec.width_m + margin - (first_u + half_swath)) / line_spacing - 1e-9) + 1)
    n_along = math.floor(spec.height_m / spacing_m) + 2
    sensor_z = BASE_HEIGHT_M + spec.flight_altitude_m
    if spec.missed_line is not None and spec.missed_line >= n_lines:
        raise ValueError(
            f"SurveySpec.missed_line: line {spec.missed_line} does not exist; this survey has {n_lines} "
            f"flight lines (0..{n_lines - 1})"
        )
    lines = []
    for index in range(n_lines):
        u = first_u + index * line_spacing
        lines.append(
            FlightLine(
                index=index,
                line_id=index + 1,
                u=u,
                x=spec.x_min + u,
                sensor_z=sensor_z,
                half_swath_m=half_swath,
                n_across=n_across,
                n_along=n_along,
                northbound=index % 2 == 0,
                start_time=SURVEY_START_GPS_TIME + index * LINE_INTERVAL_S,
                flown=index != spec.missed_line,
            )
        )
    if spec.missed_line is not None:
        centres = (np.arange(spec.shape[1]) + 0.5) * spec.resolution
        covered = np.zeros(len(centres), dtype=bool)
        for line in lines:
            if line.flown:
                covered |= np.abs(centres - line.u) <= line.half_swath_m - spec.resolution / 2.0
        uncovered = int((~covered).sum())
        if uncovered < 2:
            raise ValueError(
                f"SurveySpec.missed_line: dropping line {spec.missed_line} leaves no uncovered strip in the "
                f"extent ({uncovered} truth pixel columns); swath {2 * half_swath:.1f} m with side_overlap="
                f"{spec.side_overlap} needs side_overlap < 0.5 and the line's gap inside the extent"
            )
    return lines
