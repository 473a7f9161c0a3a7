"""The flight-plan files: a run's holes and DSM read for planning, the plans written.

Reading: :func:`read_holes` (a ``holes.gpkg`` layer) and :func:`open_dsm` (a DSM
window, read block by block on request). Writing, in ``out_dir`` (docs/flightplans.md): ``flightplan.gpkg`` (layers
``holes_status``, ``flight_lines``, ``waypoints``, ``route``) and, per sortie,
``flightplan.plan``, ``flightplan.waypoints``, ``flightplan.kmz`` and
``flightplan.kml`` (:mod:`.flightplan_formats`); with several sorties the names carry
the sortie number (``flightplan_s1.plan``, ``flightplan_s2.plan``, ...). The planning
tool that reads, plans and writes is :func:`pipeline.flight_planning.plan_flights`.
"""

from __future__ import annotations

import contextlib
import math
import os
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyogrio
import rasterio
from rasterio.enums import MaskFlags
from shapely.geometry import LineString, Point

from ..errors import CRSError, InputDataError, OutputError
from ..flightplan.mission import FlightPlan, HoleInput
from ..grid import PixelWindow
from ..rasterize import merge_ground_sums
from .flightplan_formats import write_kml, write_kmz, write_plan, write_waypoints
from .intermediate import load_cell_ground
from .las import header_bounds, iter_point_chunks
from .vector import write_layer

__all__ = [
    "CellGround",
    "DsmWindows",
    "open_dsm",
    "read_cell_ground",
    "read_ground",
    "read_holes",
    "sortie_file_names",
    "write_flightplan",
]

#: ASPRS classes read for the take-off point: ground, and water (not to take off beside).
_GROUND, _WATER = 2, 9
_CHUNK_POINTS = 2_000_000


def read_holes(path: str | os.PathLike, *, layer: str = "holes") -> tuple[list[HoleInput], str]:
    """Holes of a ``holes.gpkg`` layer and the layer's CRS (WKT).

    An optional ``azimuth_deg`` field imposes each hole's lane direction.
    """
    path = Path(path)
    if not path.is_file():
        raise InputDataError(path, "holes file not found")
    try:
        frame = pyogrio.read_dataframe(path, layer=layer)
    except Exception as e:
        raise InputDataError(path, f"cannot read layer '{layer}': {e}") from None
    missing = [c for c in ("hole_id", "area_m2", "cause") if c not in frame.columns]
    if missing and len(frame):  # an empty layer may carry no fields at all
        raise InputDataError(path, f"layer '{layer}' lacks the field(s) {', '.join(missing)}")
    if frame.crs is None:
        raise CRSError(path, f"layer '{layer}' has no CRS")
    if not frame.crs.is_projected:
        raise CRSError(path, f"layer '{layer}' is in {frame.crs.name}, not a projected CRS in metres")
    azimuths = frame["azimuth_deg"] if "azimuth_deg" in frame.columns else [None] * len(frame)
    holes = [
        HoleInput(
            int(row.hole_id),
            row.geometry,
            str(row.cause),
            float(row.area_m2),
            None if az is None or (isinstance(az, float) and math.isnan(az)) else float(az),
        )
        for row, az in zip(frame.itertuples(), azimuths)
    ]
    return holes, frame.crs.to_wkt()


@contextlib.contextmanager
def open_dsm(
    path: str | os.PathLike, bounds: tuple[float, float, float, float] | None = None
) -> Iterator[tuple[DsmWindows, Any, str]]:
    """A DSM window (``bounds``: minx, miny, maxx, maxy; None: the whole raster) to be read on
    request (:class:`DsmWindows`), its transform and CRS WKT; the file stays open in the block."""
    path = Path(path)
    try:
        source = rasterio.open(path)
    except rasterio.errors.RasterioError as e:
        raise InputDataError(path, f"cannot read the DSM: {e}") from None
    with source:
        window = rasterio.windows.Window(0, 0, source.width, source.height)
        t = source.transform
        if bounds is not None:
            if t.b != 0 or t.d != 0:
                raise InputDataError(path, "rotated DSM rasters are not supported")
            cols = sorted(((bounds[0] - t.c) / t.a, (bounds[2] - t.c) / t.a))
            rows = sorted(((bounds[1] - t.f) / t.e, (bounds[3] - t.f) / t.e))
            col0, col1 = math.floor(cols[0]), math.ceil(cols[1])
            row0, row1 = math.floor(rows[0]), math.ceil(rows[1])
            col0, row0 = max(0, col0), max(0, row0)
            col1, row1 = min(source.width, col1), min(source.height, row1)
            if col1 <= col0 or row1 <= row0:
                raise InputDataError(path, f"the DSM does not cover the holes (bounds {bounds})")
            window = rasterio.windows.Window(col0, row0, col1 - col0, row1 - row0)
        transform = type(t)(t.a, t.b, t.c + t.a * window.col_off, t.d, t.e, t.f + t.e * window.row_off)
        crs = source.crs.to_wkt() if source.crs else ""
        if not crs:
            raise CRSError(path, "the DSM has no CRS")
        try:
            yield DsmWindows(source, window), transform, crs
        except (rasterio.errors.RasterioError, rasterio.errors.WindowError) as e:
            raise InputDataError(path, f"cannot read the DSM: {e}") from None


class DsmWindows:
    """A DSM read block by block on request: what the flight planner reads of a survey's span.

    Indexed as a float64 array of the span (NaN where the DSM's mask says no data): ``dsm[r, c]``,
    ``dsm[r0:r1, c0:c1]``, ``dsm[rows, cols]`` (index arrays), ``np.asarray(dsm)`` (the whole span:
    the rare fallback). Blocks of :attr:`BLOCK` pixels are read through rasterio as they are
    first touched and kept while they fit in :attr:`CACHE_BYTES` (least recently used first out),
    so memory follows what the plan reads (the lanes, the take-off windows), not the span (holes
    10 km apart: 100 M pixels, 800 MB read whole). The values are those one read of the span gives.
    """

    BLOCK = 1024
    CACHE_BYTES = 256 << 20

    def __init__(self, source: Any, window: Any) -> None:
        self._source = source  # an open rasterio dataset (the caller closes it)
        self.path = Path(source.name)
        self._row_off, self._col_off = int(window.row_off), int(window.col_off)
        self.shape = (int(window.height), int(window.width))
        self._blocks: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self._cached_bytes = 0
        # float32 rasters (holefill's DSMs) are kept as they are: twice the blocks in the cache, the same values
        self._dtype = np.float32 if np.dtype(source.dtypes[0]) == np.float32 else np.float64
        # a mask that only says "nodata" is the nodata value itself: no second read of the block for it
        flags = source.mask_flag_enums[0]
        self._nodata = source.nodata if list(flags) == [MaskFlags.nodata] else None

    @property
    def size(self) -> int:
        return self.shape[0] * self.shape[1]

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        whole = self._read(0, self.shape[0], 0, self.shape[1])
        return whole if dtype is None else whole.astype(dtype)

    def __getitem__(self, key: Any) -> Any:
        rows, cols = key
        if isinstance(rows, (int, np.integer)) and isinstance(cols, (int, np.integer)):
            return self._read(int(rows), int(rows) + 1, int(cols), int(cols) + 1)[0, 0]
        if isinstance(rows, slice) and isinstance(cols, slice):
            r0, r1, step_r = rows.indices(self.shape[0])
            c0, c1, step_c = cols.indices(self.shape[1])
            if step_r != 1 or step_c != 1:
                raise IndexError("DsmWindows reads contiguous windows only")
            return self._read(r0, max(r1, r0), c0, max(c1, c0))
        rows, cols = np.asarray(rows), np.asarray(cols)
        if rows.size == 0:
            return np.empty(rows.shape)
        r0, c0 = int(rows.min()), int(cols.min())
        window = self._read(r0, int(rows.max()) + 1, c0, int(cols.max()) + 1)
        return window[rows - r0, cols - c0]

    def _read(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        out = np.empty((max(r1 - r0, 0), max(c1 - c0, 0)))
        if out.size == 0:
            return out
        b = self.BLOCK
        for bi in range(r0 // b, (r1 - 1) // b + 1):
            for bj in range(c0 // b, (c1 - 1) // b + 1):
                block = self._block(bi, bj)
                a0, a1 = max(r0, bi * b), min(r1, bi * b + block.shape[0])
                d0, d1 = max(c0, bj * b), min(c1, bj * b + block.shape[1])
                out[a0 - r0 : a1 - r0, d0 - c0 : d1 - c0] = block[a0 - bi * b : a1 - bi * b, d0 - bj * b : d1 - bj * b]
        return out

    def _block(self, bi: int, bj: int) -> np.ndarray:
        key = (bi, bj)
        if key in self._blocks:
            self._blocks.move_to_end(key)
            return self._blocks[key]
        b = self.BLOCK
        height, width = min(b, self.shape[0] - bi * b), min(b, self.shape[1] - bj * b)
        window = rasterio.windows.Window(self._col_off + bj * b, self._row_off + bi * b, width, height)
        block = self._source.read(1, window=window).astype(self._dtype)
        if self._nodata is not None:
            block[np.isnan(block) if math.isnan(self._nodata) else block == self._dtype(self._nodata)] = np.nan
        else:
            block[self._source.read_masks(1, window=window) == 0] = np.nan
        self._blocks[key] = block
        self._cached_bytes += block.nbytes
        while self._cached_bytes > self.CACHE_BYTES and len(self._blocks) > 1:
            self._cached_bytes -= self._blocks.popitem(last=False)[1].nbytes
        return block


def file_bounds(point_files: list[str | os.PathLike]) -> list[tuple[float, float, float, float]]:
    """Each file's header bounds (minx, miny, maxx, maxy): read once for every window :func:`read_ground` reads."""
    return [header_bounds(path) for path in point_files]


def read_ground(
    point_files: list[str | os.PathLike],
    transform,
    shape: tuple[int, int],
    bounds: list[tuple[float, float, float, float]] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Ground-class points binned on a DSM window: mean height per pixel (NaN: none) and water points.

    Only files whose header bounds (``bounds``, from :func:`file_bounds`; read here when not
    given) meet the window are decoded; withheld points are left out. Used for the take-off
    height (:mod:`pipeline.flightplan.takeoff`), which must be the ground, never the DSM's top
    of a roof or tree.
    """
    t = transform
    rows, cols = shape
    x0, x1 = sorted((t.c, t.c + t.a * cols))
    y0, y1 = sorted((t.f, t.f + t.e * rows))
    place = _lattice_of(t)
    total = np.zeros(rows * cols)
    count = np.zeros(rows * cols)
    water = np.zeros(rows * cols)
    for path, b in zip(point_files, bounds if bounds is not None else file_bounds(point_files), strict=True):
        if b[2] < x0 or b[0] > x1 or b[3] < y0 or b[1] > y1:
            continue
        # on every core: a run's client plans beside the workers' last tasks, then alone; `holefill plan` has the machine
        for chunk in iter_point_chunks(path, _CHUNK_POINTS, parallel=True):
            x, y, z = chunk.coordinates()
            r, c = place(x, y)
            inside = (r >= 0) & (r < rows) & (c >= 0) & (c < cols) & ~chunk.withheld
            index = r * cols + c
            is_ground = inside & (chunk.classification == _GROUND)
            total += np.bincount(index[is_ground], weights=z[is_ground], minlength=total.size)
            count += np.bincount(index[is_ground], minlength=count.size)
            is_water = inside & (chunk.classification == _WATER)
            water += np.bincount(index[is_water], minlength=water.size)
    with np.errstate(invalid="ignore", divide="ignore"):
        ground = np.where(count > 0, total / np.maximum(count, 1.0), np.nan)
    return ground.reshape(shape), water.reshape(shape)


@dataclass(frozen=True)
class CellGround:
    """Where a run's stage 1 kept the ground sums: each cell's statistics file and core window, on the grid.

    ``transform``: the grid's (its top-left pixel), to place a DSM window's pixels on it.
    """

    cells: tuple[tuple[str, PixelWindow], ...]
    transform: Any


def read_cell_ground(
    source: CellGround, transform: Any, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`read_ground`'s grids from the ground sums stage 1 kept with the cells: no point decoded again.

    The mean height of the ground points per pixel, and the water-class points per pixel
    (the cells' ``water`` statistic: the water points the DSM kept and those its class filter
    left out). None where the window is not on the grid's lattice or a cell it meets kept no
    sums (a run that did not plan flights): the caller reads the points instead.
    """
    grid = source.transform
    if not (math.isclose(transform.a, grid.a) and math.isclose(transform.e, grid.e)):
        return None
    col, row = (transform.c - grid.c) / grid.a, (transform.f - grid.f) / grid.e
    if not (math.isclose(col, round(col), abs_tol=1e-6) and math.isclose(row, round(row), abs_tol=1e-6)):
        return None
    box = PixelWindow(round(row), round(col), *shape)
    parts = []
    water = np.zeros(shape)
    for path, core in source.cells:
        overlap = core.intersection(box)
        if overlap.is_empty:
            continue
        kept = load_cell_ground(path)
        if kept is None or kept[0].window != core:
            return None
        ground, cell_water = kept
        parts.append(ground)
        water[overlap.slices_within(box)] = cell_water[overlap.slices_within(core)]
    return merge_ground_sums(box, parts).mean_height(), water


def _lattice_of(transform: Any):
    """Row and column of points in a north-up raster, placed as stage 1 places them on its grid.

    A point on a pixel edge goes to the pixel east of it and the one *north* of it
    (``floor(y / resolution + offset)``, :meth:`pipeline.grid.Grid.pixel_rows_cols`), not to the
    row below as ``floor((y - top) / -resolution)`` would: the ground binned here is then binned
    like the DSM it stands under, and like the sums a run keeps (:func:`read_cell_ground`).
    """
    t = transform
    if t.b != 0 or t.d != 0 or t.e >= 0 or not math.isclose(t.a, -t.e):
        # not a north-up raster of square pixels: the raster's own pixel edges
        def by_transform(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            return np.floor((y - t.f) / t.e).astype(np.int64), np.floor((x - t.c) / t.a).astype(np.int64)

        return by_transform
    resolution = t.a
    offset = -(t.c / resolution) % 1.0  # pixel edges on multiples of the pixel (0), or its centres (0.5)
    for lattice in (0.0, 0.5, 1.0):
        if abs(offset - lattice) < 1e-6:
            offset = lattice % 1.0
    col_min = round(t.c / resolution + offset)
    row_top = round(t.f / resolution + offset) - 1

    def on_lattice(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cols = np.floor(x / resolution + offset).astype(np.int64) - col_min
        return row_top - np.floor(y / resolution + offset).astype(np.int64), cols

    return on_lattice


def sortie_file_names(n_sorties: int) -> list[str]:
    """``flightplan`` for one sortie; ``flightplan_s1``, ``flightplan_s2``, ... for several."""
    return ["flightplan"] if n_sorties == 1 else [f"flightplan_s{k}" for k in range(1, n_sorties + 1)]


def write_flightplan(
    plan: FlightPlan, out_dir: str | os.PathLike, *, drone_enum: int = 89, payload_enum: int = 84
) -> list[Path]:
    """Write ``flightplan.gpkg`` and the drone files of every sortie into ``out_dir``."""
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{out_dir}: cannot create the output folder: {e}") from None
    gpkg = out_dir / "flightplan.gpkg"
    gpkg.unlink(missing_ok=True)
    _write_gpkg(gpkg, plan)
    files = [gpkg]
    for stem, sortie in zip(sortie_file_names(len(plan.sorties)), plan.sorties):
        files.append(write_plan(out_dir / f"{stem}.plan", plan, sortie))
        files.append(write_waypoints(out_dir / f"{stem}.waypoints", plan, sortie))
        files.append(write_kmz(out_dir / f"{stem}.kmz", plan, sortie, drone_enum=drone_enum, payload_enum=payload_enum))
        files.append(write_kml(out_dir / f"{stem}.kml", plan, sortie))
    return files


def _write_gpkg(path: Path, plan: FlightPlan) -> None:
    """``flightplan.gpkg``: the layers flight_lines, waypoints, route and holes_status, in that order."""
    _write_flight_lines_layer(path, plan)
    _write_waypoints_layer(path, plan)
    _write_route_layer(path, plan)
    _write_holes_status_layer(path, plan)


#: The ``altitude_ref`` attribute of the waypoints layer, per altitude reference (``{home}``: where the
#: take-off point's height comes from, ``FlightPlan.home_source``).
_ALTITUDE_REFERENCE_LABELS = {
    "takeoff": "relative to take-off ({home} at home)",
    "amsl": "AMSL (DSM datum)",
    "ellipsoid": "WGS84 ellipsoid",
}


def _write_flight_lines_layer(path: Path, plan: FlightPlan) -> None:
    lines = [(s, lane) for s in plan.sorties for lane in s.lanes]
    write_layer(
        path,
        "flight_lines",
        [
            {
                "hole_ids": ",".join(map(str, fl.hole_ids)),
                "pattern_id": fl.pattern_id,
                "sortie": fl.sortie,
                "lane_index": fl.lane.index,
                "length_m": round(fl.lane.length_m, 2),
                "azimuth_deg": round(fl.lane.azimuth_deg, 2),
            }
            for _, fl in lines
        ],
        [LineString([fl.lane.start, fl.lane.end]) for _, fl in lines],
        crs_wkt=plan.crs_wkt,
        geometry_type="LineString",
    )


def _write_waypoints_layer(path: Path, plan: FlightPlan) -> None:
    reference = _ALTITUDE_REFERENCE_LABELS[plan.altitude_reference].format(home=plan.home_source)
    points = [w for s in plan.sorties for w in s.waypoints]
    write_layer(
        path,
        "waypoints",
        [
            {
                "sortie": w.sortie,
                "sequence": w.sequence,
                "altitude_m": round(w.altitude_m, 2),
                "altitude_ref": reference,
                "height_dsm_m": round(w.height_m, 2),
                "action": ",".join(w.actions),
                "pattern_id": w.pattern_id,
                "lane_index": w.lane_index,
                "lon": w.lon,
                "lat": w.lat,
            }
            for w in points
        ],
        [Point(w.x, w.y) for w in points],
        crs_wkt=plan.crs_wkt,
        geometry_type="Point",
    )


def _write_route_layer(path: Path, plan: FlightPlan) -> None:
    write_layer(
        path,
        "route",
        [
            {
                "sortie": s.number,
                "length_m": round(s.length_m, 1),
                "duration_s": round(s.duration_s, 1),
                "waypoints": len(s.waypoints),
                "min_clearance_m": round(s.least_clearance_m, 1) if math.isfinite(s.least_clearance_m) else None,
            }
            for s in plan.sorties
        ],
        [LineString([(w.x, w.y) for w in s.waypoints]) for s in plan.sorties],
        crs_wkt=plan.crs_wkt,
        geometry_type="LineString",
    )


def _write_holes_status_layer(path: Path, plan: FlightPlan) -> None:
    write_layer(
        path,
        "holes_status",
        [
            {
                "hole_id": d.hole_id,
                "cause": d.cause,
                "area_m2": round(d.area_m2, 2),
                "planned": d.planned,
                "reason": d.reason,
                "pattern_id": d.pattern_id,
                "visible_share": _share(d.visible_share),
            }
            for d in plan.decisions
        ],
        [d.geometry for d in plan.decisions],
        crs_wkt=plan.crs_wkt,
        geometry_type="MultiPolygon",
    )


def _share(value: float | None) -> float | None:
    """A visible share rounded for the layer; None where not planned or not measured (NaN)."""
    return round(value, 4) if value is not None and math.isfinite(value) else None
