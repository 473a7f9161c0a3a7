"""Simulating a scan: :func:`simulate_scan` fires every line's pulses and writes LAZ tiles.

The pulses of each line are cast in chunks (``_kernels.cast_line_pulses``), their returns
kept where they land inside the terrain's rectangle, rounded to centimetres and written
as square tiles (``pipeline.synth.write_tile``: LAS 1.4 point format 6, or LAS 1.2 point
format 1, CRS embedded). The visibility of every terrain cell from every flown line
(``_kernels.line_visibility``) gives the cells' causes (:func:`.truth.cell_causes`); the
truth raster at a run's pixel size is :func:`write_truth`.
"""

from __future__ import annotations

import json
import math
import os
import pathlib
from dataclasses import asdict, dataclass, field

import numpy as np

from . import _kernels
from .params import FlightLine, ScanParams, dark_mask
from .terrain import Surface, Terrain
from .truth import cell_causes, truth_causes

#: Pulses cast per kernel call (bounds the buffers: 3 returns each).
CHUNK_PULSES = 200_000
_CM = 100.0


@dataclass(eq=False)
class ScanResult:
    """What :func:`simulate_scan` made.

    Attributes
    ----------
    terrain : Terrain
    params : ScanParams
    tiles : list of pathlib.Path
        The LAZ tiles written.
    x, y : ndarray of shape (P,)
        Every point written, as a LAS reader decodes it (``X * 0.01 + offset``).
    point_source_id : ndarray of shape (P,)
    causes : ndarray of shape (M, N), uint8
        ``HoleCause`` of each terrain cell if no point landed on it (:func:`.truth.cell_causes`).
    dark : ndarray of bool, shape (M, N)
    points_per_line : dict of int to int
    """

    terrain: Terrain
    params: ScanParams
    tiles: list[pathlib.Path]
    x: np.ndarray
    y: np.ndarray
    point_source_id: np.ndarray
    causes: np.ndarray
    dark: np.ndarray
    points_per_line: dict[int, int] = field(default_factory=dict)

    @property
    def n_points(self) -> int:
        return len(self.x)

    def truth(self, resolution: float) -> tuple[np.ndarray, tuple[float, ...]]:
        """``HoleCause`` codes on the pixel lattice of ``resolution`` (:func:`.truth.truth_causes`)."""
        t = self.terrain
        return truth_causes(
            self.causes, cell_m=t.cell_m, x_min=t.x_min, y_min=t.y_min, x=self.x, y=self.y, resolution=resolution
        )


def simulate_scan(terrain: Terrain, params: ScanParams, out_dir: str | os.PathLike) -> ScanResult:
    """Fly ``params`` over ``terrain`` and write the returns as LAZ tiles under ``out_dir/tiles``.

    Parameters
    ----------
    terrain : Terrain
        The surface; its corner and size should lie on multiples of ``params.tile_m``.
    params : ScanParams
        From :func:`.params.random_scan_params`, or built by hand.
    out_dir : path-like
        Created if needed; receives ``tiles/*.laz`` and ``scan.json`` (the parameters).

    Returns
    -------
    ScanResult
    """
    out = pathlib.Path(out_dir)
    (out / "tiles").mkdir(parents=True, exist_ok=True)
    dark = dark_mask(terrain, params.dark_patches)
    solid = terrain.solid
    columns: dict[str, list[np.ndarray]] = {}
    counts = {}
    for line in params.lines:
        returns = line_returns(terrain, solid, dark, params, line)
        counts[line.source_id] = len(returns["x_cm"])
        for key, values in returns.items():
            columns.setdefault(key, []).append(values)
    points = {key: np.concatenate(values) for key, values in columns.items()} if columns else _no_points()
    flags = np.zeros(terrain.shape, np.uint8)
    half_fov = math.radians(params.fov_deg) / 2
    for line in params.lines:
        _kernels.line_visibility(terrain.surface, solid, terrain.cell_m, _line_array(terrain, line), half_fov, flags)
    tiles = write_tiles(out / "tiles", points, terrain, params)
    (out / "scan.json").write_text(json.dumps(scan_record(terrain, params, counts), indent=1, default=float) + "\n")
    return ScanResult(
        terrain=terrain,
        params=params,
        tiles=tiles,
        x=points["x_cm"] * 0.01 + terrain.x_min,
        y=points["y_cm"] * 0.01 + terrain.y_min,
        point_source_id=points["point_source_id"],
        causes=cell_causes(terrain.kind, dark, flags),
        dark=dark,
        points_per_line=counts,
    )


def _line_array(terrain: Terrain, line: FlightLine) -> np.ndarray:
    """``(start_u, start_v, heading_rad, altitude, length)`` in the terrain's local coordinates."""
    return np.array(
        [
            line.start[0] - terrain.x_min,
            line.start[1] - terrain.y_min,
            math.radians(line.heading_deg),
            line.altitude_m,
            line.length_m,
        ]
    )


#: Real surveys get returns from the water's edge (shallow or turbid water, wet banks, floating
#: debris) and classify them as water: AHN3 Delft's canals hold class-9 returns on 5-45 % of their
#: rims. Water cells within this distance of land may return (``ScanParams.water_edge_return``).
WATER_EDGE_M = 1.0


def water_edge(terrain: Terrain) -> np.ndarray:
    """The water cells within ``WATER_EDGE_M`` of land."""
    import scipy.ndimage as ndi

    water = terrain.kind == Surface.WATER
    if not water.any():
        return water
    return water & (ndi.distance_transform_edt(water) * terrain.cell_m <= WATER_EDGE_M)


def line_returns(
    terrain: Terrain, solid: np.ndarray, dark: np.ndarray, params: ScanParams, line: FlightLine
) -> dict[str, np.ndarray]:
    """The returns of one line that land inside the terrain's rectangle, as LAS fields.

    Coordinates are integer centimetres from the terrain's lower-left corner (``x_cm``,
    ``y_cm``; ``z_cm`` from 0), the other fields as :func:`pipeline.synth.write_tile` takes
    them.
    """
    phase = float(np.random.default_rng([params.seed, line.source_id]).uniform())
    scanner = np.array(
        [params.speed_m_s, params.pulse_rate_hz, params.scan_rate_hz, math.radians(params.fov_deg) / 2, phase]
    )
    settings = np.array(
        [
            float(params.single_returns),
            params.penetration,
            params.intermediate,
            math.radians(params.water_nadir_deg),
            params.water_return,
            params.water_edge_return,
        ]
    )
    edge = water_edge(terrain)
    key = np.uint64((params.seed * 1_000_003 + line.source_id) % (1 << 63))
    n_pulses = int(line.length_m / params.speed_m_s * params.pulse_rate_hz)
    chunk = min(CHUNK_PULSES, max(n_pulses, 1))
    points = np.empty((3 * chunk, 4))
    attributes = np.empty((3 * chunk, 6), np.float32)
    parts = []
    line_array = _line_array(terrain, line)
    for first in range(0, n_pulses, chunk):
        count = min(chunk, n_pulses - first)
        written = _kernels.cast_line_pulses(
            terrain.surface, solid, terrain.kind, dark, edge, terrain.cell_m, line_array, scanner, settings, key,
            first, count, points, attributes,
        )  # fmt: skip
        parts.append(_as_fields(points[:written], attributes[:written], terrain, line, params))
    return {key: np.concatenate([part[key] for part in parts]) for key in parts[0]} if parts else _no_points()


def _as_fields(
    points: np.ndarray, attributes: np.ndarray, terrain: Terrain, line: FlightLine, params: ScanParams
) -> dict[str, np.ndarray]:
    """Kernel output rows -> LAS fields, keeping the returns inside the rectangle."""
    x_cm = np.rint(points[:, 0] * _CM).astype(np.int64)
    y_cm = np.rint(points[:, 1] * _CM).astype(np.int64)
    inside = (x_cm >= 0) & (y_cm >= 0) & (x_cm < round(terrain.width_m * _CM)) & (y_cm < round(terrain.height_m * _CM))
    a = attributes[inside]
    flags = a[:, 5].astype(np.uint8)
    angle = a[:, 3] if params.scan_angles else np.zeros(int(inside.sum()), np.float32)
    return {
        "x_cm": x_cm[inside].astype(np.int32),
        "y_cm": y_cm[inside].astype(np.int32),
        "z_cm": np.rint(points[inside, 2] * _CM).astype(np.int32),
        "classification": a[:, 0].astype(np.uint8),
        "return_number": a[:, 1].astype(np.uint8),
        "number_of_returns": a[:, 2].astype(np.uint8),
        "gps_time": line.gps_start + points[inside, 3],
        "scan_angle": angle.astype(np.float32),
        "intensity": a[:, 4].astype(np.uint16),
        "scan_direction_flag": (flags & 1).astype(np.uint8),
        "edge_of_flight_line": ((flags >> 1) & 1).astype(np.uint8),
        "point_source_id": np.full(int(inside.sum()), line.source_id, np.uint16),
    }


def _no_points() -> dict[str, np.ndarray]:
    dtypes = {
        "x_cm": np.int32, "y_cm": np.int32, "z_cm": np.int32, "classification": np.uint8,
        "return_number": np.uint8, "number_of_returns": np.uint8, "gps_time": np.float64,
        "scan_angle": np.float32, "intensity": np.uint16, "scan_direction_flag": np.uint8,
        "edge_of_flight_line": np.uint8, "point_source_id": np.uint16,
    }  # fmt: skip
    return {key: np.zeros(0, dtype) for key, dtype in dtypes.items()}


def write_tiles(
    folder: pathlib.Path, points: dict[str, np.ndarray], terrain: Terrain, params: ScanParams
) -> list[pathlib.Path]:
    """One LAZ file per ``params.tile_m`` square holding points, named by its lower-left corner."""
    from ..synth.tiles import write_tile

    tile_cm = int(round(params.tile_m * _CM))
    tile_col = points["x_cm"] // tile_cm
    tile_row = points["y_cm"] // tile_cm
    order = np.lexsort((points["gps_time"], tile_col, tile_row))
    keys = tile_row[order] * 1_000_000 + tile_col[order]
    starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]]) if len(keys) else np.zeros(0, np.int64)
    paths = []
    for begin, end in zip(starts, np.r_[starts[1:], len(keys)]):
        index = order[begin:end]
        x0 = terrain.x_min + tile_col[index[0]] * params.tile_m
        y0 = terrain.y_min + tile_row[index[0]] * params.tile_m
        path = folder / f"sim_{round(x0)}_{round(y0)}.laz"
        write_tile(
            path,
            {key: values[index] for key, values in points.items()},
            origin=(terrain.x_min, terrain.y_min),
            crs=terrain.crs,
            las_version="1.4" if params.point_format == 6 else "1.2",
        )
        paths.append(path)
    return paths


def scan_record(terrain: Terrain, params: ScanParams, counts: dict[int, int]) -> dict:
    """The parameters and a few figures of a scan, JSON-ready."""
    record = asdict(params)
    record["terrain"] = {"name": terrain.name, "bounds": terrain.bounds, "cell_m": terrain.cell_m, "crs": terrain.crs}
    record["pulse_rate_hz"] = params.pulse_rate_hz
    record["scan_rate_hz"] = params.scan_rate_hz
    record["points_per_line"] = {str(k): v for k, v in counts.items()}
    return record


def write_truth(scan: ScanResult, resolution: float, path: str | os.PathLike) -> pathlib.Path:
    """Write the truth of ``scan`` at ``resolution`` as a uint8 GeoTIFF of ``HoleCause`` codes."""
    import affine
    import pyproj

    from ..io.raster import write_cog

    truth, transform = scan.truth(resolution)
    return write_cog(
        path,
        truth,
        transform=affine.Affine(*transform),
        crs_wkt=pyproj.CRS.from_user_input(scan.terrain.crs).to_wkt(),
        nodata=None,
        description="0 none, 1 occlusion, 2 water, 3 missed coverage, 4 no return",
        categorical=True,
    )
