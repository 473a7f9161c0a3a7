"""Reading points through PDAL (optional): one tile, streamed through the user's filter stages.

The only module that imports ``pdal`` (python-pdal, the ``holefill[pdal]`` extra), and
only inside functions, so the core install never needs it. A tile is read by
``readers.las`` followed by the filter stages of the user's pipeline file
(``read.pdal_pipeline``), in PDAL's streaming mode, and handed to the binning as the
same :class:`~pipeline.io.las.PointChunk` the laspy reader yields, so stage 1 is shared.

The pipeline file is checked once, on the client, by :func:`load_user_pipeline`: valid
JSON, filter stages only (holefill supplies the reader of each tile and writes the
products itself), every stage known to PDAL and, unless ``read.pdal_streaming = false``,
streamable. The last ``filters.reprojection`` decides the CRS the points arrive in.
"""

from __future__ import annotations

import importlib
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, InputDataError
from .las import PointChunk, PulseFields, TileHeader

#: The dimensions the binning reads (PDAL is asked for these only when no user stage runs).
BINNING_DIMENSIONS = ["X", "Y", "Z", "Classification", "Withheld", "PointSourceId"]

#: How to get python-pdal: the extra, and the PDAL library it builds against.
INSTALL_HINT = (
    "install it with: pip install 'holefill[pdal]' (python-pdal; it needs the PDAL library >= 2.7: "
    "conda install -c conda-forge pdal python-pdal, or PDAL built from source)"
)


def import_pdal(source: str = "read.reader = 'pdal'") -> Any:
    """The ``pdal`` module, or one :class:`ConfigError` line saying how to install it."""
    try:
        import pdal
    except ImportError as e:
        raise ConfigError(f"{source}: python-pdal cannot be imported ({e}); {INSTALL_HINT}") from None
    return pdal


@dataclass(frozen=True)
class UserPipeline:
    """The user's filter stages, checked: what runs between each tile's reader and the binning."""

    path: str
    stages_json: str  # the filter stages as a JSON list, key order kept (part of each tile's fingerprint)
    out_srs: str | None  # the CRS of the last filters.reprojection, None when no stage reprojects
    streaming: bool  # every stage streams (else each tile is read whole)


@dataclass(frozen=True)
class PdalRead:
    """How one tile is read through PDAL (part of a stage-1 task: small and picklable)."""

    pipeline: UserPipeline | None
    override_srs: str | None  # the tile's CRS when its file has none (--crs)
    expected_points: int | None  # the header count, checked when no user stage can drop points

    @property
    def reprojects(self) -> bool:
        """The user's stages bring the points into another CRS (``filters.reprojection``)."""
        return self.pipeline is not None and self.pipeline.out_srs is not None


def load_user_pipeline(path: str | os.PathLike, *, streaming: bool = True) -> UserPipeline:
    """Read and check a pipeline file of filter stages.

    The file holds a JSON list of stages, or PDAL's ``{"pipeline": [...]}``. Each
    stage is an object whose ``type`` is a PDAL filter (``filters.range``,
    ``filters.reprojection``, ...).

    Raises
    ------
    ConfigError
        Naming the file, the stage (its position and type) and what is wrong: not
        JSON, a reader or writer or file name, an unknown stage, a stage that cannot
        stream while ``streaming`` is asked for, or python-pdal missing.
    """
    import_pdal(f"read.pdal_pipeline = {str(path)!r}")
    where = f"{path} (read.pdal_pipeline)"
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))  # JSON is UTF-8 (RFC 8259), whatever the locale
    except OSError as e:
        raise ConfigError(f"{where}: cannot be read: {e.strerror or e}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"{where}: not valid JSON: {e}") from None
    stages = data.get("pipeline") if isinstance(data, dict) else data
    if not isinstance(stages, list) or not stages:
        raise ConfigError(f'{where}: expected a JSON list of filter stages, or {{"pipeline": [...]}}')
    known = {driver["name"]: driver for driver in importlib.import_module("pdal.libpdalpython").getDrivers()}
    out_srs = None
    streams = True
    for number, stage in enumerate(stages, start=1):
        name = _check_stage(stage, number, where, known)
        if not known[name]["streamable"]:
            if streaming:
                raise ConfigError(
                    f"{where}: stage {number} ({name}) cannot run in PDAL's streaming mode; remove it, or set "
                    "read.pdal_streaming = false to read each tile whole (memory: the whole tile)"
                )
            streams = False
        if name == "filters.reprojection":
            if not stage.get("out_srs"):
                raise ConfigError(f"{where}: stage {number} (filters.reprojection) has no out_srs")
            out_srs = str(stage["out_srs"])
            _same_crs(out_srs, out_srs, where=f"{where}: stage {number} (filters.reprojection)")
    return UserPipeline(str(path), json.dumps(stages), out_srs, streams)


def _check_stage(stage: object, number: int, where: str, known: dict[str, Any]) -> str:
    """One stage's type, after the checks that make it a filter holefill can chain."""
    if isinstance(stage, str):
        raise ConfigError(
            f"{where}: stage {number} is a file name ({stage!r}); holefill reads each input tile itself: "
            "give filter stages only"
        )
    if not isinstance(stage, dict) or not isinstance(stage.get("type"), str):
        raise ConfigError(f'{where}: stage {number} is not an object with a "type" (e.g. "filters.range")')
    name = stage["type"]
    if name.startswith(("readers.", "writers.")):
        what = "reader" if name.startswith("readers.") else "writer"
        raise ConfigError(
            f"{where}: stage {number} ({name}) is a {what}; holefill reads each input tile and writes its "
            "products itself: give filter stages only"
        )
    if "inputs" in stage:
        raise ConfigError(f'{where}: stage {number} ({name}) has "inputs"; stages are chained in file order')
    if name not in known:
        raise ConfigError(f"{where}: stage {number} ({name}) is not a stage this PDAL knows")
    return name


def pdal_pipeline_json(path: str, read: PdalRead) -> str:
    """The PDAL pipeline that reads one tile: ``readers.las`` and the user's stages."""
    reader: dict[str, Any] = {"type": "readers.las", "filename": str(path)}
    if read.override_srs:
        reader["override_srs"] = read.override_srs
    stages = json.loads(read.pipeline.stages_json) if read.pipeline else []
    return json.dumps([reader, *stages])


def iter_pdal_chunks(path: str | os.PathLike, chunk_points: int, read: PdalRead) -> Iterator[PointChunk]:
    """Read one tile through PDAL, ``chunk_points`` points at a time, as float coordinates.

    In streaming mode memory is bounded by the chunk; with stages that cannot stream
    (``read.pdal_streaming = false``) PDAL holds the whole tile and it is cut into chunks
    afterwards. Without a user pipeline, fewer points than the header declares raise
    :class:`InputDataError` (as the laspy reader does); a user's filters may drop points.
    """
    pdal = import_pdal()
    decoded = 0
    try:
        pipeline = pdal.Pipeline(pdal_pipeline_json(str(path), read))
        dims = BINNING_DIMENSIONS if read.pipeline is None else []  # a user's stage may use any dimension
        if read.pipeline is None or read.pipeline.streaming:
            arrays: Iterator[np.ndarray] = pipeline.iterator(chunk_size=chunk_points, allowed_dims=dims)
        else:
            pipeline.execute(allowed_dims=dims)
            arrays = _slices(pipeline.arrays, chunk_points)
        for array in arrays:
            if len(array) == 0:
                continue
            decoded += len(array)
            yield _chunk(array)
    except (InputDataError, ConfigError):
        raise
    except Exception as e:  # PDAL raises RuntimeError for bad files and failing stages alike
        message = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise InputDataError(path, f"PDAL cannot read it after {decoded:,} points: {message}") from None
    if read.expected_points is not None and decoded != read.expected_points:
        raise InputDataError(path, f"header point count is {read.expected_points:,} but PDAL read {decoded:,} points")


def _slices(arrays: list[np.ndarray], chunk_points: int) -> Iterator[np.ndarray]:
    for array in arrays:
        for start in range(0, len(array), chunk_points):
            yield array[start : start + chunk_points]


def _chunk(array: np.ndarray) -> PointChunk:
    """PDAL's dimensions as a :class:`PointChunk` (scale 1, offset 0: the floats as they are)."""
    names = array.dtype.names or ()
    n = len(array)

    def column(name: str, dtype: type, default: int) -> np.ndarray:
        return np.ascontiguousarray(array[name], dtype) if name in names else np.full(n, default, dtype)

    return PointChunk(
        X=np.ascontiguousarray(array["X"], np.float64),
        Y=np.ascontiguousarray(array["Y"], np.float64),
        Z=np.ascontiguousarray(array["Z"], np.float64),
        scales=(1.0, 1.0, 1.0),
        offsets=(0.0, 0.0, 0.0),
        classification=column("Classification", np.uint8, 0),
        withheld=column("Withheld", np.uint8, 0) != 0,
        point_source_id=column("PointSourceId", np.uint16, 0),
        pulses=PulseFields(
            gps_time=column("GpsTime", np.float64, 0),
            return_number=column("ReturnNumber", np.uint8, 1),
            number_of_returns=column("NumberOfReturns", np.uint8, 1),
            scan_angle_deg=(
                column("ScanAngleRank", np.float32, 0) if "ScanAngleRank" in names else np.full(n, np.nan, np.float32)
            ),
        ),
    )


def settle_target_crs(pipeline: UserPipeline, target_crs: str) -> str:
    """The survey's target CRS given a user pipeline: its ``filters.reprojection`` decides it.

    Without a reprojecting stage ``target_crs`` stands; with one, an empty
    ``target_crs`` becomes the stage's ``out_srs`` and a different one is refused
    (the points arrive from PDAL already in ``out_srs``).
    """
    if pipeline.out_srs is None:
        return target_crs
    if not target_crs:
        return pipeline.out_srs
    if not _same_crs(pipeline.out_srs, target_crs):
        raise ConfigError(
            f"{pipeline.path} (read.pdal_pipeline): filters.reprojection out_srs {pipeline.out_srs!r} "
            f"conflicts with survey.target_crs {target_crs!r}: give one of them, or the same CRS in both"
        )
    return target_crs


def tile_read(pipeline: UserPipeline | None, survey_crs_wkt: str, header: TileHeader, tile_crs_wkt: str) -> PdalRead:
    """How stage 1 reads one tile through PDAL.

    Raises
    ------
    ConfigError
        The user's ``filters.reprojection`` leads to another CRS than the survey's
        (a library caller that did not pass it through :func:`settle_target_crs`).
    """
    if pipeline is not None and pipeline.out_srs is not None and not _same_crs(pipeline.out_srs, survey_crs_wkt):
        raise ConfigError(
            f"{pipeline.path} (read.pdal_pipeline): filters.reprojection out_srs {pipeline.out_srs!r} is not "
            f"the survey CRS: set survey.target_crs = {pipeline.out_srs!r}"
        )
    return PdalRead(
        pipeline=pipeline,
        override_srs=None if header.crs_wkt is not None else tile_crs_wkt,
        expected_points=None if pipeline is not None else header.point_count,
    )


def _same_crs(a: str, b: str, where: str = "filters.reprojection") -> bool:
    from pyproj import CRS
    from pyproj.exceptions import CRSError as ProjCRSError

    try:
        return CRS.from_user_input(a).equals(CRS.from_user_input(b), ignore_axis_order=True)
    except ProjCRSError as e:
        raise ConfigError(f"{where}: out_srs {a!r} is not a CRS pyproj understands ({e})") from None


__all__ = [
    "INSTALL_HINT",
    "PdalRead",
    "UserPipeline",
    "import_pdal",
    "iter_pdal_chunks",
    "load_user_pipeline",
    "settle_target_crs",
    "tile_read",
]
