"""Compiled ray casting (pure, numba): pulses of one flight line, and what one line can see.

Coordinates are *local*: ``u`` metres east and ``v`` metres north of the terrain's
lower-left corner; a raster's row 0 is its north edge, so the cell of ``(u, v)`` is
``(rows - 1 - floor(v / cell), floor(u / cell))``. A ray from the sensor is marched in
horizontal steps of half a cell (and at most half a metre of height) over a height
raster; the first sample at or below the raster is refined by bisection against the
previous one, which puts a hit on a wall where the ray entered a taller cell from the
side. Per-pulse randomness is a counter-based hash of (seed, line, pulse, purpose), so a
pulse's fate does not depend on the order of anything else.
"""

from __future__ import annotations

import numba
import numpy as np

#: Terrain kinds (``terrain.Surface``), repeated here as plain integers for the kernels.
GROUND, BUILDING, VEGETATION, WATER, OTHER = 0, 1, 2, 3, 4
#: Bits of a cell's visibility flags (:func:`line_visibility`).
IN_SWATH, SEEN_CLEAR, SEEN_THROUGH_VEGETATION = 1, 2, 4
#: Returns closer than this (metres along z) merge into one: the pulse cannot separate them.
MIN_RETURN_SEPARATION_M = 1.5
#: An intermediate return needs this much room between canopy and the last return.
MIN_INTERMEDIATE_ROOM_M = 4.0
#: Heights within this of the ray do not block it (roof planes, the target's own cell).
VISIBILITY_TOLERANCE_M = 0.1

_BITS_53 = 1.0 / 9007199254740992.0


@numba.njit(cache=True, nogil=True, inline="always")
def _mix(x: np.uint64) -> np.uint64:
    """splitmix64's finaliser."""
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


@numba.njit(cache=True, nogil=True)
def uniform(key: np.uint64, index: int, salt: int) -> float:
    """A uniform number in [0, 1) that depends only on ``(key, index, salt)``."""
    x = _mix(key + np.uint64(index) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(salt) * np.uint64(0xD1B54A32D192ED03))
    return float(x >> np.uint64(11)) * _BITS_53


@numba.njit(cache=True, nogil=True, inline="always")
def _height_at(raster: np.ndarray, u: float, v: float, cell: float) -> float:
    """The raster's height under ``(u, v)``, or -inf outside it."""
    rows, cols = raster.shape
    col = int(np.floor(u / cell))
    row = rows - 1 - int(np.floor(v / cell))
    if row < 0 or row >= rows or col < 0 or col >= cols:
        return -np.inf
    return raster[row, col]


@numba.njit(cache=True, nogil=True)
def cast_ray(
    raster: np.ndarray,
    origin: np.ndarray,
    direction: np.ndarray,
    t_from: float,
    cell: float,
    z_top: float,
    z_bottom: float,
) -> float:
    """Distance along the ray to its first sample at or below ``raster``, or -1.

    Parameters
    ----------
    raster : ndarray of shape (M, N)
        Heights (row 0 north).
    origin, direction : ndarray of shape (3,)
        Ray start ``(u, v, z)`` and unit direction (pointing down: ``direction[2] < 0``).
    t_from : float
        Start the march here (0, or just past a previous hit).
    cell : float
        Raster cell size.
    z_top, z_bottom : float
        The raster's highest and lowest heights: the march runs between them.
    """
    dz = direction[2]
    if dz >= 0.0:
        return -1.0
    t = max(t_from, (origin[2] - z_top) / -dz)
    t_end = (origin[2] - z_bottom) / -dz
    horizontal = np.sqrt(direction[0] ** 2 + direction[1] ** 2)
    step = 0.5 / -dz
    if horizontal > 1e-12:
        step = min(step, 0.5 * cell / horizontal)
    previous = t
    while t <= t_end + step:
        z = origin[2] + t * dz
        if _height_at(raster, origin[0] + t * direction[0], origin[1] + t * direction[1], cell) >= z:
            if t == previous:
                return t
            low, high = previous, t
            for _ in range(12):
                middle = 0.5 * (low + high)
                zm = origin[2] + middle * dz
                if _height_at(raster, origin[0] + middle * direction[0], origin[1] + middle * direction[1], cell) >= zm:
                    high = middle
                else:
                    low = middle
            return high
        previous = t
        t += step
    return -1.0


@numba.njit(cache=True, nogil=True, inline="always")
def _cell_of(raster: np.ndarray, u: float, v: float, cell: float) -> tuple[int, int]:
    """The cell under ``(u, v)``, clamped to the raster."""
    rows, cols = raster.shape
    row = min(max(rows - 1 - int(np.floor(v / cell)), 0), rows - 1)
    col = min(max(int(np.floor(u / cell)), 0), cols - 1)
    return row, col


@numba.njit(cache=True, nogil=True)
def _class_of(kind: int) -> int:
    """The ASPRS class of a return from a surface kind."""
    if kind == GROUND:
        return 2
    if kind == BUILDING:
        return 6
    if kind == VEGETATION:
        return 5
    if kind == WATER:
        return 9
    return 1


@numba.njit(cache=True, nogil=True)
def _intensity(cls: int, share: float, draw: float) -> int:
    """An intensity by class (buildings bright, water dark), split between a pulse's returns."""
    base = 300.0
    if cls == 2:
        base = 350.0
    elif cls == 6:
        base = 600.0
    elif cls == 5:
        base = 200.0
    elif cls == 9:
        base = 60.0
    return int(min(65535.0, base * share * (0.75 + 0.5 * draw)))


@numba.njit(cache=True, nogil=True)
def pulse_returns(
    surface: np.ndarray,
    solid: np.ndarray,
    kind: np.ndarray,
    dark: np.ndarray,
    edge: np.ndarray,
    origin: np.ndarray,
    direction: np.ndarray,
    scan_angle: float,
    cell: float,
    z_range: np.ndarray,
    settings: np.ndarray,
    key: np.uint64,
    pulse: int,
    out: np.ndarray,
) -> int:
    """The returns of one pulse, written into ``out`` rows ``(t, z, class)``; how many (0-3).

    ``settings`` = (single_returns, penetration, intermediate, water_nadir_rad,
    water_return, water_edge_return). The first surface is ``surface``; a pulse through
    vegetation may go on to ``solid`` (the ground under the trees). Dark cells and water
    return nothing, except water within ``water_nadir_rad`` of nadir, with chance
    ``water_return``, and water at its edge (``edge``: shallow water, wet banks), with chance
    ``water_edge_return`` (class 9).
    """
    t1 = cast_ray(surface, origin, direction, 0.0, cell, z_range[0], z_range[1])
    if t1 < 0.0:
        return 0
    row, col = _cell_of(surface, origin[0] + t1 * direction[0], origin[1] + t1 * direction[1], cell)
    first_kind = kind[row, col]
    if dark[row, col]:
        return 0
    z1 = origin[2] + t1 * direction[2]
    if first_kind == WATER:
        if (abs(scan_angle) <= settings[3] and uniform(key, pulse, 1) < settings[4]) or (
            edge[row, col] and uniform(key, pulse, 5) < settings[5]
        ):
            out[0, 0], out[0, 1], out[0, 2] = t1, z1, 9.0
            return 1
        return 0
    out[0, 0], out[0, 1], out[0, 2] = t1, z1, float(_class_of(first_kind))
    if first_kind != VEGETATION or settings[0] > 0.5 or uniform(key, pulse, 2) >= settings[1]:
        return 1
    t2 = cast_ray(solid, origin, direction, t1, cell, z_range[0], z_range[1])
    if t2 < 0.0:
        return 1
    z2 = origin[2] + t2 * direction[2]
    row2, col2 = _cell_of(solid, origin[0] + t2 * direction[0], origin[1] + t2 * direction[1], cell)
    second_kind = kind[row2, col2]
    if dark[row2, col2] or second_kind == WATER or z1 - z2 < MIN_RETURN_SEPARATION_M:
        return 1
    n = 1
    if z1 - z2 >= MIN_INTERMEDIATE_ROOM_M and uniform(key, pulse, 3) < settings[2]:
        tm = t1 + (t2 - t1) * (0.25 + 0.5 * uniform(key, pulse, 4))
        out[1, 0], out[1, 1], out[1, 2] = tm, origin[2] + tm * direction[2], 5.0
        n = 2
    out[n, 0], out[n, 1] = t2, z2
    out[n, 2] = 2.0 if second_kind == VEGETATION else float(_class_of(second_kind))
    return n + 1


@numba.njit(cache=True, nogil=True)
def cast_line_pulses(
    surface: np.ndarray,
    solid: np.ndarray,
    kind: np.ndarray,
    dark: np.ndarray,
    edge: np.ndarray,
    cell: float,
    line: np.ndarray,
    scanner: np.ndarray,
    settings: np.ndarray,
    key: np.uint64,
    first_pulse: int,
    n_pulses: int,
    points: np.ndarray,
    attributes: np.ndarray,
) -> int:
    """Fire pulses ``first_pulse .. first_pulse + n_pulses - 1`` of one line; the number of returns.

    Parameters
    ----------
    line : ndarray of shape (5,)
        ``(start_u, start_v, heading_rad, altitude, length)``.
    scanner : ndarray of shape (5,)
        ``(speed, pulse_rate, sweeps_per_second, half_fov_rad, phase)``: pulse ``i`` leaves at
        ``t = i / pulse_rate`` from ``start + speed t`` along the track, at scan angle
        ``half_fov * tri(sweeps t / 2 + phase)`` (a linear zigzag; positive to the right of
        the track, as LAS counts it).
    points : ndarray of shape (3 n_pulses, 4), float64
        Output rows ``(u, v, z, time since the line's start)``.
    attributes : ndarray of shape (3 n_pulses, 6), float32
        Output rows ``(class, return number, number of returns, scan angle degrees,
        intensity, flags)``; flags: bit 0 scan direction (mirror sweeping right), bit 1 edge
        of flight line (last pulse of a sweep).
    """
    along_u, along_v = np.sin(line[2]), np.cos(line[2])
    across_u, across_v = along_v, -along_u
    speed, rate, sweeps, half_fov, phase = scanner[0], scanner[1], scanner[2], scanner[3], scanner[4]
    rows, cols = surface.shape
    z_range = np.array([np.max(surface) + 0.01, np.min(solid) - 1.0])
    margin = (z_range[0] - z_range[1]) * np.tan(half_fov) + 2 * cell  # the landing point moves by this
    origin = np.empty(3)
    direction = np.empty(3)
    hits = np.empty((3, 3))
    written = 0
    for i in range(first_pulse, first_pulse + n_pulses):
        t = i / rate
        s = speed * t
        if s > line[4]:
            break
        position = sweeps * t * 0.5 + phase
        fraction = position - np.floor(position)
        angle = half_fov * (1.0 - 4.0 * abs(fraction - 0.5))
        origin[0], origin[1], origin[2] = line[0] + s * along_u, line[1] + s * along_v, line[3]
        sin_a, cos_a = np.sin(angle), np.cos(angle)
        direction[0], direction[1], direction[2] = sin_a * across_u, sin_a * across_v, -cos_a
        reach = (line[3] - z_range[1]) * sin_a / cos_a  # horizontal reach at the lowest height
        foot_u, foot_v = origin[0] + reach * across_u, origin[1] + reach * across_v
        if foot_u < -margin or foot_v < -margin or foot_u > cols * cell + margin or foot_v > rows * cell + margin:
            continue
        n = pulse_returns(
            surface, solid, kind, dark, edge, origin, direction, angle, cell, z_range, settings, key, i, hits
        )
        next_position = sweeps * (t + 1.0 / rate) * 0.5 + phase
        flags = float((fraction < 0.5) + 2 * ((fraction < 0.5) != (next_position - np.floor(next_position) < 0.5)))
        for k in range(n):
            points[written, 0] = origin[0] + hits[k, 0] * direction[0]
            points[written, 1] = origin[1] + hits[k, 0] * direction[1]
            points[written, 2] = hits[k, 1]
            points[written, 3] = t
            share = 1.0 if n == 1 else (0.6 if k == 0 else 0.4 / (n - 1))
            attributes[written, 0] = hits[k, 2]
            attributes[written, 1] = k + 1
            attributes[written, 2] = n
            attributes[written, 3] = np.degrees(angle)
            attributes[written, 4] = _intensity(int(hits[k, 2]), share, uniform(key, i, 10 + k))
            attributes[written, 5] = flags
            written += 1
    return written


@numba.njit(cache=True, nogil=True)
def _seen_from(
    surface: np.ndarray,
    solid: np.ndarray,
    cell: float,
    u: float,
    v: float,
    z: float,
    toward_u: float,
    toward_v: float,
    distance: float,
    rise: float,
    z_top: float,
) -> int:
    """Whether the line of sight from ``(u, v, z)`` to the sensor is free: 2 clear, 4 only
    through vegetation, 0 blocked. The sensor is ``distance`` away horizontally along the unit
    ``(toward_u, toward_v)`` and ``rise`` above."""
    through_vegetation = False
    step = 0.5 * cell
    d = 0.75 * cell
    while d < distance:
        zr = z + rise * d / distance
        if zr > z_top:
            break
        pu, pv = u + d * toward_u, v + d * toward_v
        if _height_at(solid, pu, pv, cell) > zr + VISIBILITY_TOLERANCE_M:
            return 0
        if _height_at(surface, pu, pv, cell) > zr + VISIBILITY_TOLERANCE_M:
            through_vegetation = True
        d += step
    return SEEN_THROUGH_VEGETATION if through_vegetation else SEEN_CLEAR


@numba.njit(cache=True, nogil=True)
def line_visibility(
    surface: np.ndarray, solid: np.ndarray, cell: float, line: np.ndarray, half_fov: float, flags: np.ndarray
) -> None:
    """OR into ``flags`` what one line sees of each cell's first surface.

    ``IN_SWATH``: the cell's top lies within the line's length and its scan angle is at
    most ``half_fov`` (the scan plane is perpendicular to the track, so the sensor that
    sees a cell is the one abeam of it); ``SEEN_CLEAR``: the line of sight to it crosses
    nothing; ``SEEN_THROUGH_VEGETATION``: it crosses only vegetation (``surface`` above
    ``solid``). ``line`` is as in :func:`cast_line_pulses`.
    """
    rows, cols = surface.shape
    along_u, along_v = np.sin(line[2]), np.cos(line[2])
    across_u, across_v = along_v, -along_u
    tan_half = np.tan(half_fov)
    z_top = np.max(surface) + 0.01
    for row in range(rows):
        v = (rows - 1 - row + 0.5) * cell
        for col in range(cols):
            u = (col + 0.5) * cell
            s = (u - line[0]) * along_u + (v - line[1]) * along_v
            if s < 0.0 or s > line[4]:
                continue
            d = (u - line[0]) * across_u + (v - line[1]) * across_v
            z = surface[row, col]
            rise = line[3] - z
            if rise <= 0.0 or abs(d) > rise * tan_half:
                continue
            flags[row, col] |= IN_SWATH
            if abs(d) < 1e-6:
                flags[row, col] |= SEEN_CLEAR
                continue
            sign = -1.0 if d > 0 else 1.0
            seen = _seen_from(surface, solid, cell, u, v, z, sign * across_u, sign * across_v, abs(d), rise, z_top)
            flags[row, col] |= seen
