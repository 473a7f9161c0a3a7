"""The public entry points: :func:`generate_survey`, :class:`SyntheticSurvey`, :func:`write_truth`."""

from __future__ import annotations

import concurrent.futures
import math
import os
import pathlib
import time
import warnings
from dataclasses import dataclass, field
from typing import Any

import affine
import numpy as np

from .draw import build_scene
from .flight import FlightLine, flight_lines
from .scene import Scene
from .spec import HoleCause, SurveySpec
from .tiles import _Layout, _layout, _simulate_tile, _Tile, _tile_name, _TileResult, _tiles, _TileTruth, write_tile

#: The default of :func:`generate_survey` (frozen, so one instance serves every call).
_DEFAULT_SPEC = SurveySpec()


@dataclass
class SyntheticSurvey:
    """A written synthetic survey and its truth.

    Attributes
    ----------
    spec : SurveySpec
    tiles : list of pathlib.Path
        Files written, west to east within south to north. Tiles without any
        point (e.g. entirely over water) are not written.
    truth_dsm : ndarray of float32, shape (rows, cols) or None
        Highest surface per truth pixel (max of the height field over the
        fine-grid cell centres): roofs, canopy, ground, and the water level over
        water. Defined everywhere, holes included, so fills can be scored.
    hole_cause : ndarray of uint8, shape (rows, cols) or None
        :class:`HoleCause` per pixel, nonzero exactly where the written points
        leave the pixel empty (binned from the very integers written). An
        empty pixel is WATER if at least half of its fine cells are water;
        otherwise MISSED_COVERAGE if more of its land cells lie outside every
        flown swath than inside a swath but unseen, else OCCLUSION.
    transform : affine.Affine
        ``from_origin(x_min, y_max, res, res)``.
    crs : str
    n_points : int
        Points written over all tiles.
    point_count : ndarray of uint32 or None
        Points per truth pixel (all returns).
    visible_fraction : ndarray of float32 or None
        Fraction of each pixel's fine cells that some flown line sees (not
        water). An empty pixel with a large visible fraction would be a
        sampling accident; the tests check there are essentially none.
    scene : Scene
        The scene, in local coordinates (metres from ``(x_min, y_min)``).
    flight_lines : list of FlightLine
        All planned lines, the dropped one with ``flown=False``.
    generation_seconds : float
        Wall time of the generation, LAZ writing included.
    """

    spec: SurveySpec
    tiles: list[pathlib.Path]
    truth_dsm: np.ndarray | None
    hole_cause: np.ndarray | None
    transform: affine.Affine
    crs: str
    n_points: int
    point_count: np.ndarray | None = None
    visible_fraction: np.ndarray | None = None
    scene: Scene | None = None
    flight_lines: list[FlightLine] = field(default_factory=list)
    generation_seconds: float = 0.0

    @property
    def hole_mask(self) -> np.ndarray | None:
        """True where the written points leave a truth pixel empty."""
        return None if self.hole_cause is None else self.hole_cause != HoleCause.NONE

    def water_polygon(self) -> Any:
        """The river's water outline over the extent as a shapely Polygon in CRS coordinates (None without water)."""
        if self.scene is None or self.scene.river is None:
            return None
        import shapely

        ring = self.scene.river.polygon(0.0, self.spec.width_m) + (self.spec.x_min, self.spec.y_min)
        return shapely.Polygon(ring)

    def water_polygons(self) -> list[tuple[str, Any]]:
        """Every water body's outline over the extent as (name, shapely Polygon in CRS coordinates).

        The river (as :meth:`water_polygon`), then ``lake 1``, ``lake 2`` ... and ``canal``.
        """
        if self.scene is None:
            return []
        import shapely

        origin = (self.spec.x_min, self.spec.y_min)
        named = [] if self.scene.river is None else [("river", self.water_polygon())]
        if self.scene.lakes is not None:
            for index, ring in enumerate(self.scene.lakes.polygons(), start=1):
                named.append((f"lake {index}", shapely.Polygon(ring + origin)))
        if self.scene.canal is not None:
            named.append(("canal", shapely.Polygon(self.scene.canal.polygon(0.0, self.spec.height_m) + origin)))
        return named

    def building_footprints(self) -> list[Any]:
        """Building footprints as shapely Polygons in CRS coordinates (same order as ``scene.buildings``)."""
        if self.scene is None:
            return []
        import shapely

        buildings = self.scene.buildings
        corners = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
        footprints = []
        for index in range(len(buildings)):
            along = corners[:, 0] * buildings.half_length[index]
            across = corners[:, 1] * buildings.half_width[index]
            cos, sin = math.cos(buildings.angle[index]), math.sin(buildings.angle[index])
            x = self.spec.x_min + buildings.center_u[index] + along * cos - across * sin
            y = self.spec.y_min + buildings.center_v[index] + along * sin + across * cos
            footprints.append(shapely.Polygon(np.column_stack([x, y])))
        return footprints

    def cause_counts(self) -> dict[HoleCause, int]:
        """Number of truth pixels per cause (``NONE`` included)."""
        if self.hole_cause is None:
            raise ValueError("the truth was not kept (generate_survey(..., keep_truth=False))")
        counts = np.bincount(self.hole_cause.ravel(), minlength=len(HoleCause))
        return {cause: int(counts[cause]) for cause in HoleCause}


def generate_survey(
    out_dir: str | os.PathLike,
    spec: SurveySpec = _DEFAULT_SPEC,
    *,
    keep_truth: bool = True,
    scene: Scene | None = None,
) -> SyntheticSurvey:
    """Simulate an airborne lidar survey, write it as LAZ tiles and return its truth.

    Tiles are generated and written one at a time, so memory is bounded by one
    tile (plus the truth arrays when ``keep_truth``). The result depends only
    on ``spec`` (and ``scene``), not on the tiling: the same pulses, points and
    truth come out for any ``tile_size_m``.

    Parameters
    ----------
    out_dir : path-like
        Folder for the tiles (created if needed); files ``synth_{x}_{y}.laz``
        named after their lower-left corner are overwritten.
    spec : SurveySpec
    keep_truth : bool
        Compute and return the truth rasters. False for huge benchmark surveys:
        the truth arrays are then None and nothing grows with the survey size.
    scene : Scene, optional
        Use this scene instead of :func:`build_scene(spec) <build_scene>`
        (e.g. a single hand-placed building in a test).

    Returns
    -------
    SyntheticSurvey

    Raises
    ------
    ValueError
        The spec is inconsistent (see :class:`SurveySpec` and
        :func:`flight_lines`) or the sensor does not clear the scene.
    """
    started = time.perf_counter()
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    scene = build_scene(spec) if scene is None else scene
    lines = flight_lines(spec)
    layout = _layout(spec, scene, lines)
    truth = _TruthGrid.empty(layout.n_rows, layout.n_cols) if keep_truth else None
    written, n_points = _simulate_and_write(spec, scene, lines, layout, out_dir, truth)
    _warn_stale_tiles(out_dir, written)
    return SyntheticSurvey(
        spec=spec,
        tiles=written,
        truth_dsm=None if truth is None else truth.dsm,
        hole_cause=None if truth is None else truth.cause,
        transform=spec.transform,
        crs=spec.crs,
        n_points=n_points,
        point_count=None if truth is None else truth.count,
        visible_fraction=None if truth is None else truth.visible_fraction,
        scene=scene,
        flight_lines=lines,
        generation_seconds=time.perf_counter() - started,
    )


@dataclass(frozen=True, eq=False)
class _TruthGrid:
    """The truth rasters of the whole survey (north-up, row 0 at ``y_max``), filled tile by tile."""

    dsm: np.ndarray  # float32
    cause: np.ndarray  # uint8
    count: np.ndarray  # uint32
    visible_fraction: np.ndarray  # float32

    @classmethod
    def empty(cls, rows: int, cols: int) -> _TruthGrid:
        shape = (rows, cols)
        return cls(
            dsm=np.empty(shape, dtype=np.float32),
            cause=np.empty(shape, dtype=np.uint8),
            count=np.empty(shape, dtype=np.uint32),
            visible_fraction=np.empty(shape, dtype=np.float32),
        )

    def place(self, tile: _Tile, truth: _TileTruth) -> None:
        """Copy a tile's south-up truth into its window of the north-up grid."""
        rows = self.dsm.shape[0]
        top, bottom = rows - tile.row1, rows - tile.row0
        window = (slice(top, bottom), slice(tile.col0, tile.col1))
        self.dsm[window] = truth.dsm[::-1]
        self.cause[window] = truth.cause[::-1]
        self.count[window] = truth.count[::-1]
        self.visible_fraction[window] = truth.visible_fraction[::-1]


def _simulate_and_write(
    spec: SurveySpec,
    scene: Scene,
    lines: list[FlightLine],
    layout: _Layout,
    out_dir: pathlib.Path,
    truth: _TruthGrid | None,
) -> tuple[list[pathlib.Path], int]:
    """Simulate every tile in order, write those with points, fill ``truth`` on the way.

    Returns the files written and the number of points in them.
    """
    written: list[pathlib.Path] = []
    n_points = 0
    # One background writer: the next tile is simulated (numpy releases the GIL)
    # while the previous one is compressed; at most two tiles are in memory.
    writer = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="synth-writer")
    pending: concurrent.futures.Future | None = None
    try:
        for tile in _tiles(layout):
            result = _simulate_tile(spec, scene, lines, layout, tile, truth is not None)
            if truth is not None and result.truth is not None:
                truth.place(tile, result.truth)
            n = len(result.points["x_cm"])
            if n == 0:
                continue
            path, points, origin = _tile_file(spec, layout, out_dir, result)
            if pending is not None:
                pending.result()
            pending = writer.submit(
                write_tile,
                path,
                points,
                origin=origin,
                crs=spec.crs,
                las_version=spec.las_version,
                compress=spec.compress,
            )
            written.append(path)
            n_points += n
        if pending is not None:
            pending.result()
    finally:
        writer.shutdown(wait=True, cancel_futures=True)
    return written, n_points


def _tile_file(
    spec: SurveySpec, layout: _Layout, out_dir: pathlib.Path, result: _TileResult
) -> tuple[pathlib.Path, dict[str, np.ndarray], tuple[float, float]]:
    """A tile's file, its points in centimetres from the tile's lower-left corner, and that corner."""
    tile = result.tile
    x0 = spec.x_min + tile.col0 * spec.resolution
    y0 = spec.y_min + tile.row0 * spec.resolution
    points = dict(result.points)
    points["x_cm"] = points["x_cm"] - tile.col0 * layout.resolution_cm
    points["y_cm"] = points["y_cm"] - tile.row0 * layout.resolution_cm
    return out_dir / _tile_name(x0, y0, spec.compress), points, (x0, y0)


def _warn_stale_tiles(out_dir: pathlib.Path, written: list[pathlib.Path]) -> None:
    """Warn (at the caller of :func:`generate_survey`) about synth_* tiles this survey did not write."""
    stale = sorted(set(out_dir.glob("synth_*.la[sz]")) - set(written))
    if stale:
        warnings.warn(
            f"{out_dir}: {len(stale)} synth_* tile(s) not written by this survey remain there "
            f"(e.g. {stale[0].name}); readers of the folder will mix surveys",
            stacklevel=3,
        )


def write_truth(survey: SyntheticSurvey, folder: str | os.PathLike) -> dict[str, pathlib.Path]:
    """Write a survey's truth beside its tiles, as GIS files a user can open and score against.

    Files: ``truth_dsm.tif`` (highest surface per pixel), ``truth_hole_cause.tif``
    (``HoleCause`` codes), ``survey_area.gpkg`` (the planned rectangle: the AOI) and
    ``water.gpkg`` (the river, lake and canal polygons, when there is water).

    Returns
    -------
    dict of str to pathlib.Path
        ``dsm``, ``hole_cause``, ``survey_area`` and, with water, ``water``.
    """
    import pyproj
    import shapely

    from ..io.raster import write_cog
    from ..io.vector import write_layer

    if survey.truth_dsm is None or survey.hole_cause is None:
        raise ValueError("the survey was generated with keep_truth=False: there is no truth to write")
    folder = pathlib.Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    crs = pyproj.CRS.from_user_input(survey.crs).to_wkt()
    spec = survey.spec
    paths = {
        "dsm": write_cog(folder / "truth_dsm.tif", survey.truth_dsm, transform=survey.transform, crs_wkt=crs),
        "hole_cause": write_cog(
            folder / "truth_hole_cause.tif",
            survey.hole_cause.astype(np.uint8),
            transform=survey.transform,
            crs_wkt=crs,
            nodata=None,
            description="0 none, 1 occlusion, 2 water, 3 missed coverage",
            categorical=True,
        ),  # fmt: skip
        "survey_area": write_layer(
            folder / "survey_area.gpkg",
            "survey_area",
            [{"name": "planned survey area"}],
            [shapely.box(spec.x_min, spec.y_min, spec.x_max, spec.y_max)],
            crs_wkt=crs,
        ),  # fmt: skip
    }
    waters = [(name, polygon) for name, polygon in survey.water_polygons() if not polygon.is_empty]
    if waters:
        paths["water"] = write_layer(
            folder / "water.gpkg",
            "water",
            [{"name": name} for name, _ in waters],
            [polygon for _, polygon in waters],
            crs_wkt=crs,
        )
    return paths
