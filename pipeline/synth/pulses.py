"""The returns of one flight line's pulses over a tile.

Per-pulse randomness is a counter-based hash of (seed, line, pulse indices), not a
sequential generator, so a pulse is the same whatever the tiling. Visibility is the
running maximum of the elevation slope outward from the sensor (:func:`_visibility`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .flight import FlightLine
from .scene import Scene, SceneRaster
from .spec import (
    _CENTIMETRES_PER_METRE,
    BASE_HEIGHT_M,
    CLASS_BUILDING,
    CLASS_GROUND,
    CLASS_HIGH_VEGETATION,
    FLIGHT_SPEED_M_S,
    PULSE_JITTER_FRACTION,
    SurfaceKind,
    SurveySpec,
)

_MASK64 = (1 << 64) - 1
_GOLDEN64 = 0x9E3779B97F4A7C15


def _mix64(z: np.ndarray) -> np.ndarray:
    """SplitMix64 finaliser on a uint64 array (wrapping arithmetic)."""
    z = z ^ (z >> np.uint64(30))
    z *= np.uint64(0xBF58476D1CE4E5B9)
    z ^= z >> np.uint64(27)
    z *= np.uint64(0x94D049BB133111EB)
    z ^= z >> np.uint64(31)
    return z


def _mix64_int(z: int) -> int:
    z &= _MASK64
    z ^= z >> 30
    z = (z * 0xBF58476D1CE4E5B9) & _MASK64
    z ^= z >> 27
    z = (z * 0x94D049BB133111EB) & _MASK64
    return z ^ (z >> 31)


def _pulse_keys(seed: int, line_index: int, across: np.ndarray, along: np.ndarray) -> np.ndarray:
    """A well-mixed 64-bit key per pulse, a pure function of (seed, line, indices)."""
    line_key = _mix64_int(_mix64_int(seed * _GOLDEN64 + 0x5EED) + line_index * _GOLDEN64)
    keys = (across.astype(np.uint64) << np.uint64(32)) | along.astype(np.uint64)
    return _mix64(keys ^ np.uint64(line_key))


def _uniform(keys: np.ndarray, stream: int) -> np.ndarray:
    """Uniform [0, 1) numbers, independent for each ``stream``."""
    z = _mix64(keys + np.uint64((stream + 1) * _GOLDEN64 & _MASK64))
    return (z >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))


def _approximately_normal(keys: np.ndarray, stream: int) -> np.ndarray:
    """Standard-normal-like numbers: the sum of the four 16-bit parts of one hash.

    An Irwin-Hall(4) variable rescaled to unit variance: bell-shaped, bounded
    at +-3.46, and several times cheaper than Box-Muller (no logarithm or
    trigonometry), which matters at millions of points per second.
    """
    z = _mix64(keys + np.uint64((stream + 1) * _GOLDEN64 & _MASK64))
    low16 = np.uint64(0xFFFF)
    total = (z & low16) + ((z >> np.uint64(16)) & low16) + ((z >> np.uint64(32)) & low16) + (z >> np.uint64(48))
    return (total.astype(np.float64) * (1.0 / 65536.0) - 2.0) * math.sqrt(3.0)


(
    _STREAM_JITTER_U,
    _STREAM_JITTER_V,
    _STREAM_PENETRATION,
    _STREAM_NOISE_FIRST,
    _STREAM_NOISE_SECOND,
    _STREAM_INTENSITY,
    _STREAM_WATER_EDGE,
) = range(7)

#: Real surveys get returns from the water's edge (shallow or turbid water, wet banks, floating
#: debris) and classify them as water: AHN3 Delft's canals hold class-9 returns on 5-45 % of their
#: rims. A pulse on water within this distance of land returns, with ``WATER_EDGE_RETURN_SHARE``.
WATER_EDGE_M = 1.0
WATER_EDGE_RETURN_SHARE = 0.5
#: ASPRS class of water returns.
CLASS_WATER = 9


def _quantize_off_edges(metres: np.ndarray, resolution_cm: int) -> np.ndarray:
    """Round to whole centimetres, moving points that land on a pixel edge 1 cm back to their side."""
    scaled = metres * _CENTIMETRES_PER_METRE
    quantized = np.rint(scaled).astype(np.int64)
    on_edge = quantized % resolution_cm == 0
    if on_edge.any():
        quantized[on_edge] += np.where(scaled[on_edge] < quantized[on_edge], -1, 1)
    return quantized


def _visibility(surface: np.ndarray, cell_u: np.ndarray, sensor_u: float, sensor_z: float, reach: float) -> np.ndarray:
    """Which cells a sensor at ``(sensor_u, sensor_z)`` sees, scanning along each row.

    A cell is visible iff the slope ``(h - sensor_z) / |u - sensor_u|`` of the
    ray to it is at least every such slope between the sensor and it (a
    running maximum outward from the sensor on each side). Only cells within
    ``reach`` of the sensor track are evaluated (the rest are reported hidden):
    what lies between the sensor and a cell is always nearer than the cell.
    """
    visible = np.zeros(surface.shape, dtype=bool)
    distance = cell_u - sensor_u
    first = int(np.searchsorted(distance, -reach, side="left"))
    stop = int(np.searchsorted(distance, reach, side="right"))
    west = int(np.searchsorted(distance, 0.0, side="left"))  # cells [.., west) lie strictly west
    east = int(np.searchsorted(distance, 0.0, side="right"))  # cells [east, ..) lie strictly east
    visible[:, west:east] = True  # directly below the sensor
    if east < stop:
        slope = (surface[:, east:stop] - sensor_z) / distance[east:stop]
        visible[:, east:stop] = slope >= np.maximum.accumulate(slope, axis=1)
    if first < west:
        columns = slice(west - 1, first - 1 if first > 0 else None, -1)  # outward, westwards
        slope = (surface[:, columns] - sensor_z) / -distance[columns]
        visible[:, columns] = slope >= np.maximum.accumulate(slope, axis=1)
    return visible


_POINT_FIELDS = {
    "x_cm": np.int64,
    "y_cm": np.int64,
    "z_cm": np.int64,
    "intensity": np.uint16,
    "return_number": np.uint8,
    "number_of_returns": np.uint8,
    "classification": np.uint8,
    "scan_angle": np.float32,
    "point_source_id": np.uint16,
    "gps_time": np.float64,
    "scan_direction_flag": np.uint8,
    "edge_of_flight_line": np.uint8,
}


def _concatenate(chunks: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    if not chunks:
        return {name: np.zeros(0, dtype=dtype) for name, dtype in _POINT_FIELDS.items()}
    points = {name: np.concatenate([c[name] for c in chunks]) for name in _POINT_FIELDS}
    order = np.argsort(points["gps_time"], kind="stable")
    return {name: values[order] for name, values in points.items()}


def _index_range(low: float, high: float, origin: float, spacing: float, count: int) -> tuple[int, int]:
    """Indices ``i`` in ``[0, count)`` whose nominal position ``origin + (i + 0.5) * spacing`` may jitter into [low, high)."""
    first = max(0, math.floor((low - spacing - origin) / spacing - 0.5))
    last = min(count - 1, math.ceil((high + spacing - origin) / spacing - 0.5))
    return first, last


def _line_pulses(
    spec: SurveySpec,
    scene: Scene,
    line: FlightLine,
    raster: SceneRaster,
    visible: np.ndarray,
    visible_hard: np.ndarray,
    *,
    resolution_cm: int,
    fine_per_pixel: int,
    bounds_cm: tuple[int, int, int, int],
) -> dict[str, np.ndarray] | None:
    """The returns of one flight line's pulses that land in a tile, as a point record (``_POINT_FIELDS``).

    ``raster`` is the tile's fine-grid window (``fine_per_pixel`` cells per truth pixel
    of ``resolution_cm``); ``visible`` and ``visible_hard`` say which of its cells the
    line sees over the top surface and over the surface without tree crowns;
    ``bounds_cm`` is the tile ``(x0, x1, y0, y1)`` in local centimetres.
    """
    grid = _pulse_grid(spec, line, resolution_cm, bounds_cm)
    if grid is None:
        return None
    hits = _select_returns(spec, scene, grid, raster, visible, visible_hard, resolution_cm, fine_per_pixel)
    if hits is None:
        return None
    pulse = hits.pulse
    u_q = grid.x_cm[pulse] / 100.0
    v_q = grid.y_cm[pulse] / 100.0
    z = _return_heights(spec, scene, grid.keys, hits, u_q, v_q)

    classification = np.select(
        [hits.kind == SurfaceKind.BUILDING, hits.kind == SurfaceKind.TREE, hits.kind == SurfaceKind.WATER],
        [CLASS_BUILDING, CLASS_HIGH_VEGETATION, CLASS_WATER],
        CLASS_GROUND,
    ).astype(np.uint8)
    return_number = np.where(hits.is_second, 2, 1).astype(np.uint8)
    number_of_returns = np.where(hits.is_second, 2, 1).astype(np.uint8)
    number_of_returns[: hits.n_first][hits.first_has_second] = 2

    horizontal = u_q - line.u
    height_above = line.sensor_z - z
    intensity = _intensity(line, grid.keys, hits, horizontal, height_above)
    across, along = grid.across[pulse], grid.along[pulse]
    gps_time, forward = _scan_timing(spec, line, across, along)
    return {
        "x_cm": grid.x_cm[pulse],
        "y_cm": grid.y_cm[pulse],
        "z_cm": np.rint(z * _CENTIMETRES_PER_METRE).astype(np.int64),
        "intensity": intensity,
        "return_number": return_number,
        "number_of_returns": number_of_returns,
        "classification": classification,
        "scan_angle": np.degrees(np.arctan2(horizontal, height_above)).astype(np.float32),
        "point_source_id": np.full(len(pulse), line.line_id, dtype=np.uint16),
        "gps_time": gps_time,
        "scan_direction_flag": forward.astype(np.uint8),
        "edge_of_flight_line": ((across == 0) | (across == line.n_across - 1)).astype(np.uint8),
    }


@dataclass(frozen=True, eq=False)
class _PulseGrid:
    """The pulses of one line that may land in a tile: grid indices, hash keys, positions.

    Attributes
    ----------
    across, along : ndarray of int64
        Pulse index across track (from the swath's west edge) and scan-line index.
    keys : ndarray of uint64
        The per-pulse hash keys (:func:`_pulse_keys`).
    x_cm, y_cm : ndarray of int64
        Jittered position in local centimetres, off truth-pixel edges.
    inside : ndarray of bool
        The pulse lands in the tile.
    """

    across: np.ndarray
    along: np.ndarray
    keys: np.ndarray
    x_cm: np.ndarray
    y_cm: np.ndarray
    inside: np.ndarray


def _pulse_grid(
    spec: SurveySpec, line: FlightLine, resolution_cm: int, bounds_cm: tuple[int, int, int, int]
) -> _PulseGrid | None:
    """The jittered pulses of ``line`` near a tile (None when the swath misses it)."""
    spacing = spec.pulse_spacing_m
    x0_cm, x1_cm, y0_cm, y1_cm = bounds_cm
    swath_west = line.u - line.half_swath_m
    i_first, i_last = _index_range(x0_cm / 100.0, x1_cm / 100.0, swath_west, spacing, line.n_across)
    j_first, j_last = _index_range(y0_cm / 100.0, y1_cm / 100.0, 0.0, spacing, line.n_along)
    if i_first > i_last or j_first > j_last:
        return None
    across_range = np.arange(i_first, i_last + 1, dtype=np.int64)
    along_range = np.arange(j_first, j_last + 1, dtype=np.int64)
    across = np.tile(across_range, len(along_range))
    along = np.repeat(along_range, len(across_range))

    keys = _pulse_keys(spec.seed, line.index, across, along)
    jitter = 2.0 * PULSE_JITTER_FRACTION * spacing
    u = swath_west + (across + 0.5) * spacing + (_uniform(keys, _STREAM_JITTER_U) - 0.5) * jitter
    v = (along + 0.5) * spacing + (_uniform(keys, _STREAM_JITTER_V) - 0.5) * jitter
    x_cm = _quantize_off_edges(u, resolution_cm)
    y_cm = _quantize_off_edges(v, resolution_cm)
    inside = (x_cm >= x0_cm) & (x_cm < x1_cm) & (y_cm >= y0_cm) & (y_cm < y1_cm)
    return _PulseGrid(across, along, keys, x_cm, y_cm, inside)


@dataclass(frozen=True, eq=False)
class _Returns:
    """The returns of a pulse grid: first returns, then ground (last) returns.

    Attributes
    ----------
    first_idx, ground_idx : ndarray of int
        Pulse-grid indices of the first returns and of the ground returns.
    pulse : ndarray of int
        ``first_idx`` then ``ground_idx``: the pulse of each return.
    n_first : int
        ``len(first_idx)``.
    kind : ndarray of uint8
        :class:`SurfaceKind` each return comes from (GROUND for the ground returns).
    obj : ndarray of int32
        Building or tree index of the fine cell each return's pulse aims at, -1 if none.
    is_second : ndarray of bool
        A second return, from the ground under a crown the pulse first hit.
    first_has_second : ndarray of bool, one per first return
        Its pulse also gives a second return.
    """

    first_idx: np.ndarray
    ground_idx: np.ndarray
    pulse: np.ndarray
    n_first: int
    kind: np.ndarray
    obj: np.ndarray
    is_second: np.ndarray
    first_has_second: np.ndarray


def _select_returns(
    spec: SurveySpec,
    scene: Scene,
    grid: _PulseGrid,
    raster: SceneRaster,
    visible: np.ndarray,
    visible_hard: np.ndarray,
    res_cm: int,
    k: int,
) -> _Returns | None:
    """Which pulses return, from what (None when none does)."""
    x_cm, y_cm, inside = grid.x_cm, grid.y_cm, grid.inside
    n_raster_cols = raster.surface.shape[1]
    fine = (y_cm * k // res_cm - raster.row0) * n_raster_cols + (x_cm * k // res_cm - raster.column0)
    fine = np.where(inside, fine, 0)
    kind = raster.kind.ravel()[fine]
    sees_top = visible.ravel()[fine]
    sees_hard = visible_hard.ravel()[fine]
    penetrates = _uniform(grid.keys, _STREAM_PENETRATION) < spec.canopy_penetration
    land = inside & (kind != SurfaceKind.WATER)
    on_water = np.flatnonzero(inside & (kind == SurfaceKind.WATER) & sees_top)
    edge = np.zeros(len(kind), bool)
    edge[on_water] = _at_water_edge(scene, grid.x_cm[on_water] / 100.0, grid.y_cm[on_water] / 100.0)
    weak = _uniform(grid.keys, _STREAM_WATER_EDGE) < WATER_EDGE_RETURN_SHARE
    first = (land | (edge & weak)) & sees_top
    # a second (last) return from the ground under a crown the pulse first hit
    under_crown = first & (kind == SurfaceKind.TREE) & penetrates
    # a pulse whose target is hidden only by a tree crown reaches the ground sometimes
    through_crown = land & ~sees_top & sees_hard & penetrates

    first_idx = np.flatnonzero(first)
    ground_idx = np.flatnonzero(under_crown | through_crown)
    if len(first_idx) + len(ground_idx) == 0:
        return None
    pulse = np.concatenate([first_idx, ground_idx])
    n_first = len(first_idx)
    point_kind = np.concatenate([kind[first_idx], np.full(len(ground_idx), SurfaceKind.GROUND, dtype=np.uint8)])
    is_second = np.zeros(len(pulse), dtype=bool)
    is_second[n_first:] = under_crown[ground_idx]
    return _Returns(
        first_idx=first_idx,
        ground_idx=ground_idx,
        pulse=pulse,
        n_first=n_first,
        kind=point_kind,
        obj=raster.object_index.ravel()[fine[pulse]],
        is_second=is_second,
        first_has_second=under_crown[first_idx],
    )


def _at_water_edge(scene: Scene, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Whether land lies within ``WATER_EDGE_M`` of each point (east, west, north or south).

    Evaluated on the scene itself, not a tile's raster, so a pulse is the same whatever the tiling.
    """
    edge = np.zeros(len(u), bool)
    for du, dv in ((WATER_EDGE_M, 0.0), (-WATER_EDGE_M, 0.0), (0.0, WATER_EDGE_M), (0.0, -WATER_EDGE_M)):
        edge |= ~scene.water_level(u + du, v + dv)[0]
    return edge


def _return_heights(
    spec: SurveySpec, scene: Scene, keys: np.ndarray, hits: _Returns, u_q: np.ndarray, v_q: np.ndarray
) -> np.ndarray:
    """Height of each return at its quantized position, noise included."""
    # surfaces: ground everywhere, then roofs and canopies for first returns on them
    point_kind, obj = hits.kind, hits.obj
    z = scene.ground_height(u_q, v_q)
    on_roof = np.flatnonzero(point_kind == SurfaceKind.BUILDING)
    z[on_roof] = scene.buildings.roof_height(obj[on_roof], u_q[on_roof], v_q[on_roof])
    on_canopy = np.flatnonzero(point_kind == SurfaceKind.TREE)
    z[on_canopy] = np.maximum(z[on_canopy], scene.trees.canopy_height(obj[on_canopy], u_q[on_canopy], v_q[on_canopy]))
    on_water = np.flatnonzero(point_kind == SurfaceKind.WATER)
    if len(on_water):
        level = scene.water_level(u_q[on_water], v_q[on_water])[1]  # NaN: the return lands just ashore
        z[on_water] = np.where(np.isnan(level), z[on_water], level)
    if spec.noise_m > 0:
        n_first = hits.n_first
        z[:n_first] += spec.noise_m * _approximately_normal(keys[hits.first_idx], _STREAM_NOISE_FIRST)
        z[n_first:] += spec.noise_m * _approximately_normal(keys[hits.ground_idx], _STREAM_NOISE_SECOND)
    return z


def _intensity(
    line: FlightLine, keys: np.ndarray, hits: _Returns, horizontal: np.ndarray, height_above: np.ndarray
) -> np.ndarray:
    """Intensity: material reflectance, falling with range squared, speckled."""
    point_kind = hits.kind
    reflectance = np.select(
        [point_kind == SurfaceKind.BUILDING, point_kind == SurfaceKind.TREE],
        [700.0 + 600.0 * ((hits.obj * 0.6180339887) % 1.0), 180.0],
        420.0,
    )
    reflectance = np.where(hits.is_second, 0.45 * reflectance, reflectance)
    range_factor = (line.sensor_z - BASE_HEIGHT_M) ** 2 / (horizontal**2 + height_above**2)
    speckle = 0.8 + 0.4 * _uniform(keys[hits.pulse], _STREAM_INTENSITY)
    return np.clip(reflectance * range_factor * speckle, 1, 65535).astype(np.uint16)


def _scan_timing(
    spec: SurveySpec, line: FlightLine, across: np.ndarray, along: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """GPS time of each pulse and whether its scan line sweeps forward (the scan direction flag)."""
    scan_line = along if line.northbound else line.n_along - 1 - along
    forward = scan_line % 2 == 0
    position_in_scan = np.where(forward, across, line.n_across - 1 - across)
    scan_period = spec.pulse_spacing_m / FLIGHT_SPEED_M_S
    gps_time = line.start_time + (scan_line + position_in_scan / line.n_across) * scan_period
    return gps_time, forward
