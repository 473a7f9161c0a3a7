"""Tiles: the layout shared by every tile, the simulation of one tile and its truth, the LAZ writer."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from .flight import FlightLine
from .pulses import _concatenate, _line_pulses, _visibility
from .scene import Scene, SceneRaster
from .spec import _CENTIMETRES_PER_METRE, _COORDINATE_SCALE, MAX_FINE_CELL_M, HoleCause, SurfaceKind, SurveySpec


@dataclass(frozen=True)
class _Layout:
    """Derived geometry shared by every tile of a survey."""

    resolution_cm: int
    fine_per_pixel: int  # fine cells per truth pixel along each axis
    fine_cell: float
    pad_cells: int
    n_rows: int
    n_cols: int
    tile_pixels: int


def _layout(spec: SurveySpec, scene: Scene, lines: list[FlightLine]) -> _Layout:
    resolution_cm = round(spec.resolution * _CENTIMETRES_PER_METRE)
    fine_per_pixel = max(2, math.ceil(spec.resolution / MAX_FINE_CELL_M - 1e-9))
    fine_cell = spec.resolution / fine_per_pixel
    z_low, z_high = scene.height_range()
    sensor_z = lines[0].sensor_z
    if sensor_z - z_high < 10.0:
        raise ValueError(
            f"SurveySpec.flight_altitude_m: the sensor ({sensor_z:.1f} m) must fly at least 10 m above the "
            f"highest surface ({z_high:.1f} m)"
        )
    farthest = lines[0].half_swath_m + spec.pulse_spacing_m
    pad_m = (z_high - z_low) * farthest / (sensor_z - z_high) + 2.0 * fine_cell
    rows, cols = spec.shape
    return _Layout(
        resolution_cm=resolution_cm,
        fine_per_pixel=fine_per_pixel,
        fine_cell=fine_cell,
        pad_cells=math.ceil(pad_m / fine_cell),
        n_rows=rows,
        n_cols=cols,
        tile_pixels=round(spec.tile_size_m / spec.resolution),
    )


@dataclass(frozen=True)
class _Tile:
    """A tile as truth-pixel ranges: columns from the west, rows from the *south*."""

    col0: int
    col1: int
    row0: int
    row1: int


def _tiles(layout: _Layout) -> list[_Tile]:
    step = layout.tile_pixels
    return [
        _Tile(c, min(c + step, layout.n_cols), r, min(r + step, layout.n_rows))
        for r in range(0, layout.n_rows, step)
        for c in range(0, layout.n_cols, step)
    ]


@dataclass(frozen=True, eq=False)
class _TileTruth:
    """The truth rasters of one tile, south-up (row 0 is the tile's southernmost row)."""

    dsm: np.ndarray  # float32
    cause: np.ndarray  # uint8
    count: np.ndarray  # uint32
    visible_fraction: np.ndarray  # float32


@dataclass(frozen=True, eq=False)
class _TileResult:
    tile: _Tile
    points: dict[str, np.ndarray]  # integer centimetre coordinates and attributes
    truth: _TileTruth | None = None


def _simulate_tile(
    spec: SurveySpec, scene: Scene, lines: list[FlightLine], layout: _Layout, tile: _Tile, keep_truth: bool
) -> _TileResult:
    """The points of one tile (all flown lines, in GPS time order) and, with ``keep_truth``, its truth."""
    k = layout.fine_per_pixel
    cell = layout.fine_cell
    res_cm = layout.resolution_cm
    n_core_cols = (tile.col1 - tile.col0) * k
    column0 = tile.col0 * k - layout.pad_cells
    raster = scene.rasterize(
        column0, tile.row0 * k, n_core_cols + 2 * layout.pad_cells, (tile.row1 - tile.row0) * k, cell
    )
    cell_u = (np.arange(column0, column0 + raster.surface.shape[1]) + 0.5) * cell
    u0, u1 = tile.col0 * spec.resolution, tile.col1 * spec.resolution
    bounds_cm = (tile.col0 * res_cm, tile.col1 * res_cm, tile.row0 * res_cm, tile.row1 * res_cm)

    flown = [
        line for line in lines if line.flown and line.u + line.half_swath_m >= u0 and line.u - line.half_swath_m < u1
    ]
    core = slice(layout.pad_cells, layout.pad_cells + n_core_cols)
    visible_any = np.zeros((raster.surface.shape[0], n_core_cols), dtype=bool)  # seen by some line, core only
    has_trees = bool(np.any(raster.kind == SurfaceKind.TREE))
    chunks = []
    for line in flown:
        reach = line.half_swath_m + cell
        visible = _visibility(raster.surface, cell_u, line.u, line.sensor_z, reach)
        visible_hard = _visibility(raster.hard_surface, cell_u, line.u, line.sensor_z, reach) if has_trees else visible
        chunk = _line_pulses(
            spec,
            scene,
            line,
            raster,
            visible,
            visible_hard,
            resolution_cm=res_cm,
            fine_per_pixel=k,
            bounds_cm=bounds_cm,
        )
        if chunk is not None:
            chunks.append(chunk)
        if keep_truth:
            visible_any |= visible[:, core] & line.covers(cell_u[core])[None, :]

    points = _concatenate(chunks)
    if not keep_truth:
        return _TileResult(tile, points)
    truth = _tile_truth(tile, lines, layout, raster, cell_u[core], visible_any, points)
    return _TileResult(tile, points, truth)


def _tile_truth(
    tile: _Tile,
    lines: list[FlightLine],
    layout: _Layout,
    raster: SceneRaster,
    core_u: np.ndarray,
    visible_any: np.ndarray,
    points: dict[str, np.ndarray],
) -> _TileTruth:
    """Truth DSM, hole causes, point counts and visible fraction per truth pixel of a tile.

    ``core_u`` are the local eastings of the fine columns of the tile's core (the
    raster without its occlusion padding); ``visible_any`` is, over the core, whether
    some flown line sees a fine cell within its swath (modified here: water is removed).
    """
    k = layout.fine_per_pixel
    res_cm = layout.resolution_cm
    core = slice(layout.pad_cells, layout.pad_cells + len(core_u))
    n_rows, n_cols = tile.row1 - tile.row0, tile.col1 - tile.col0
    pixel = (points["y_cm"] // res_cm - tile.row0) * n_cols + (points["x_cm"] // res_cm - tile.col0)
    count = np.bincount(pixel, minlength=n_rows * n_cols).reshape(n_rows, n_cols).astype(np.uint32)

    def per_pixel(values: np.ndarray, reduce: str) -> np.ndarray:
        blocks = values.reshape(n_rows, k, n_cols, k)
        return blocks.max(axis=(1, 3)) if reduce == "max" else blocks.sum(axis=(1, 3))

    water = raster.kind[:, core] == SurfaceKind.WATER
    covered = np.zeros(len(core_u), dtype=bool)
    for line in lines:
        if line.flown:
            covered |= line.covers(core_u)
    visible_any &= ~water
    uncovered = ~covered[None, :] & ~water
    occluded = covered[None, :] & ~visible_any & ~water
    cells_per_pixel = k * k
    water_count = per_pixel(water, "sum")
    uncovered_count = per_pixel(uncovered, "sum")
    occluded_count = per_pixel(occluded, "sum")
    cause = np.where(
        2 * water_count >= cells_per_pixel,
        HoleCause.WATER,
        np.where(uncovered_count > occluded_count, HoleCause.MISSED_COVERAGE, HoleCause.OCCLUSION),
    ).astype(np.uint8)
    cause[count > 0] = HoleCause.NONE
    return _TileTruth(
        dsm=per_pixel(raster.surface[:, core], "max").astype(np.float32),
        cause=cause,
        count=count,
        visible_fraction=(per_pixel(visible_any, "sum") / cells_per_pixel).astype(np.float32),
    )


def write_tile(
    path: str | os.PathLike,
    points: dict[str, np.ndarray],
    *,
    origin: tuple[float, float],
    crs: str,
    las_version: str = "1.4",
    compress: bool = True,
) -> None:
    """Write one tile's points as LAS/LAZ with the CRS embedded.

    Parameters
    ----------
    path : path-like
        File to (over)write.
    points : dict of ndarray
        ``x_cm``, ``y_cm`` (integer centimetres from ``origin``), ``z_cm``
        (integer centimetres) and the point attributes produced by the
        simulation.
    origin : (float, float)
        CRS coordinates of centimetre 0; becomes the header's x/y offset, so
        the stored integers are the centimetres (scales 0.01).
    crs : str
        Embedded as a WKT VLR for point format 6 (LAS 1.4); as GeoTIFF keys
        for point format 1 (LAS 1.2), as the LAS 1.2 specification requires.
    las_version : {"1.4", "1.2"}
    compress : bool
        LAZ through the lazrs backend if true.
    """
    import laspy
    import pyproj

    point_format = 6 if las_version == "1.4" else 1
    header = laspy.LasHeader(point_format=point_format, version=las_version)
    header.scales = np.array([_COORDINATE_SCALE] * 3)
    header.offsets = np.array([origin[0], origin[1], 0.0])
    header.add_crs(pyproj.CRS(crs))
    header.global_encoding.gps_time_type = True  # adjusted standard GPS time
    header.system_identifier = "holefill synthetic"
    header.generating_software = "holefill pipeline.synth"
    las = laspy.LasData(header)
    n = len(points["x_cm"])
    las.points = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    las.X = points["x_cm"].astype(np.int32)
    las.Y = points["y_cm"].astype(np.int32)
    las.Z = points["z_cm"].astype(np.int32)
    las.intensity = points["intensity"]
    las.return_number = points["return_number"]
    las.number_of_returns = points["number_of_returns"]
    las.classification = points["classification"]
    las.point_source_id = points["point_source_id"]
    las.gps_time = points["gps_time"]
    las.scan_direction_flag = points["scan_direction_flag"]
    las.edge_of_flight_line = points["edge_of_flight_line"]
    if point_format == 6:
        las.scan_angle = np.rint(points["scan_angle"] / 0.006).astype(np.int16)  # 0.006 degree units
    else:
        las.scan_angle_rank = np.rint(points["scan_angle"]).astype(np.int8)
    las.write(os.fspath(path), laz_backend=laspy.LazBackend.Lazrs if compress else None)


def _tile_name(x: float, y: float, compress: bool) -> str:
    def coordinate(value: float) -> str:
        rounded = round(value)
        return str(rounded) if abs(value - rounded) < 1e-6 else f"{value:.2f}".rstrip("0").rstrip(".")

    return f"synth_{coordinate(x)}_{coordinate(y)}.{'laz' if compress else 'las'}"
