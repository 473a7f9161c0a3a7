"""Scanning a survey: find the input files, read their headers, settle the CRS.

Only headers are read here. The result, a :class:`Survey`, says which tiles
take part, in which CRS the work is done, whether points must be reprojected
while streaming, and how metres convert to the CRS's horizontal and vertical
units (surveys in feet exist: see ``autzen_trim``, ``nebraska_wkt_geotiff``).
"""

from __future__ import annotations

import glob
import logging
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import shapely
from pyproj import CRS, Transformer
from pyproj.exceptions import CRSError as ProjCRSError

from ..errors import CRSError, InputDataError
from ..io.las import TileHeader, read_header
from .blocks import FootprintDensity
from .density import Density, pulse_count

logger = logging.getLogger(__name__)

POINT_CLOUD_SUFFIXES = (".las", ".laz")


@dataclass(frozen=True)
class Tile:
    """One input tile as the run sees it."""

    index: int
    header: TileHeader
    source_crs_wkt: str  # the CRS its coordinates are in (from the file or --crs)
    bounds: tuple[float, float, float, float]  # in the survey CRS

    @property
    def path(self) -> str:
        return self.header.path

    @property
    def name(self) -> str:
        return Path(self.header.path).name


@dataclass
class Survey:
    """The tiles of a run and the CRS the run works in."""

    tiles: list[Tile]
    crs_wkt: str
    reproject: bool
    horizontal_unit_m: float  # metres per CRS horizontal unit
    vertical_unit_m: float  # metres per z unit
    skipped: list[dict[str, str]] = field(default_factory=list)
    footprint: FootprintDensity | None = None  # the density measured on the data (pipeline.survey.footprint_density)

    @property
    def crs(self) -> CRS:
        return CRS.from_wkt(self.crs_wkt)

    @property
    def point_count(self) -> int:
        return sum(t.header.point_count for t in self.tiles)

    def tile_density(self, tile: Tile) -> Density:
        """A tile's density from its header counts over its bounds (in the survey CRS)."""
        pulses, first = pulse_count(tile.header.point_count, tile.header.points_by_return)
        minx, miny, maxx, maxy = tile.bounds
        area = max(maxx - minx, 0.0) * max(maxy - miny, 0.0) * self.horizontal_unit_m**2
        return Density(tile.header.point_count, pulses, area, first)

    @cached_property
    def density(self) -> Density:
        """The survey's density: on the data footprint when measured (:func:`pipeline.survey.footprint_density.measure_footprint`), else :attr:`header_density`."""
        return self.footprint.density() if self.footprint is not None else self.header_density

    @cached_property
    def header_density(self) -> Density:
        """Header counts over the union of the tile bounds (overlaps count once).

        First returns only when every tile's header can tell them (see
        :func:`pipeline.survey.density.pulse_count`). The bounds are an upper bound of the
        data footprint, so the density is a lower bound (``ign_laspy_appendbug``:
        0.04 first returns/m² over its box, 3.85 on its data).
        """
        counts = [pulse_count(t.header.point_count, t.header.points_by_return) for t in self.tiles]
        first = all(f for _, f in counts)
        pulses = sum(c for c, _ in counts) if first else self.point_count
        area = shapely.union_all([shapely.box(*t.bounds) for t in self.tiles]).area * self.horizontal_unit_m**2
        return Density(self.point_count, pulses, area, first)


def find_inputs(inputs: list[str] | tuple[str, ...], *, exclude: tuple[Path, ...] = ()) -> list[Path]:
    """Expand files, folders (their ``*.las``/``*.laz``, recursively) and globs.

    ``exclude``: folders holefill writes (the output's ``points/``, ``work/``, partial
    folders): a folder or glob never yields a file under them, so a result written
    inside an input folder is never read back as input; a file named there is refused.

    Raises
    ------
    InputDataError
        When an input names nothing, or when the whole list yields no file.
    """
    excluded = tuple(folder.resolve() for folder in exclude)

    def written_here(path: Path) -> bool:
        return any(path.resolve().is_relative_to(folder) for folder in excluded)

    found: list[Path] = []
    for item in inputs:
        path = Path(item)
        if path.is_dir():
            candidates = [p for p in path.rglob("*") if p.suffix.lower() in POINT_CLOUD_SUFFIXES]
            matches = sorted(p for p in candidates if p.is_file() or (p.is_symlink() and not p.exists()))
            matches = [p for p in matches if not written_here(p)]
            if not matches:
                raise InputDataError(path, "folder holds no .las or .laz file")
            found.extend(matches)
        elif path.is_file():
            if written_here(path):
                raise InputDataError(path, "lies in a folder this run writes (--out): it cannot be an input")
            found.append(path)
        elif glob.has_magic(item):
            matches = sorted(Path(p) for p in glob.glob(item, recursive=True) if Path(p).is_file())
            matches = [p for p in matches if not written_here(p)]
            if not matches:
                raise InputDataError(item, "pattern matches no file")
            found.extend(matches)
        else:
            raise InputDataError(path, "no such file or folder")
    unique = list(dict.fromkeys(p if p.is_symlink() and not p.exists() else p.resolve() for p in found))
    if not unique:
        raise InputDataError("INPUT", "no input files given")
    return unique


def scan_survey(
    inputs: list[str] | tuple[str, ...],
    *,
    crs: str = "",
    target_crs: str = "",
    on_error: str = "fail",
    exclude: tuple[Path, ...] = (),
) -> Survey:
    """Read every header and decide the survey CRS.

    Parameters
    ----------
    inputs : list of str
        Files, folders or glob patterns.
    crs : str
        CRS for tiles that have none (or an unreadable one).
    target_crs : str
        If given, every tile is reprojected to it while streaming.
    on_error : {"fail", "skip"}
        Whether a bad tile stops the scan or is skipped and listed.
    exclude : tuple of Path
        Folders whose files are never inputs (what the run writes: :func:`find_inputs`).

    Raises
    ------
    InputDataError, CRSError
        With the file named; a survey left with no tile raises too.
    """
    paths = find_inputs(inputs, exclude=exclude)
    assigned = _parse_crs(crs, "--crs") if crs else None
    target = _parse_crs(target_crs, "--target-crs") if target_crs else None
    headers, skipped = _read_headers(paths, assigned, on_error)
    survey_crs = _survey_crs(headers, target)
    tiles = []
    reproject = False
    for index, (header, tile_crs) in enumerate(headers):
        same = tile_crs.equals(survey_crs, ignore_axis_order=True)
        reproject |= not same
        bounds = header.bounds if same else _transform_bounds(header, tile_crs, survey_crs)
        tiles.append(Tile(index=index, header=header, source_crs_wkt=tile_crs.to_wkt(), bounds=bounds))
    horizontal = survey_crs.axis_info[0].unit_conversion_factor
    return Survey(
        tiles=tiles,
        crs_wkt=survey_crs.to_wkt(),
        reproject=reproject,
        horizontal_unit_m=horizontal,
        vertical_unit_m=_vertical_unit(survey_crs, horizontal),
        skipped=skipped,
    )


def _scan_one(path: Path) -> TileHeader | InputDataError:
    """A tile's header, or the error that makes it unusable (returned, for the caller's policy)."""
    if path.is_symlink() and not path.exists():
        return InputDataError(path, f"broken symbolic link (to {os.readlink(path)})")
    try:
        header = read_header(path)
    except InputDataError as e:
        return e
    if header.point_count == 0:
        return InputDataError(path, "tile has zero points (header point count is 0)")
    return header


def _read_headers(
    paths: list[Path], assigned: CRS | None, on_error: str
) -> tuple[list[tuple[TileHeader, CRS]], list[dict[str, str]]]:
    """Every usable tile's header and CRS, in input order, and the skipped tiles (``on_error="skip"``)."""
    with ThreadPoolExecutor(max_workers=min(8, len(paths))) as pool:
        scanned = list(pool.map(_scan_one, paths))

    skipped: list[dict[str, str]] = []
    headers: list[tuple[TileHeader, CRS]] = []
    for path, result in zip(paths, scanned):
        try:
            if isinstance(result, InputDataError):
                raise result
            headers.append((result, _tile_crs(result, assigned)))
        except InputDataError as e:
            if on_error != "skip":
                raise
            logger.warning("skipping %s", e)
            skipped.append({"path": str(path), "reason": e.reason})
    if not headers:
        raise InputDataError("INPUT", "no usable tile: every input was skipped")
    return headers, skipped


def _survey_crs(headers: list[tuple[TileHeader, CRS]], target: CRS | None) -> CRS:
    """``target``, or else the one CRS all tiles share; it must be projected."""
    survey_crs = target if target is not None else headers[0][1]
    if target is None:
        for header, tile_crs in headers[1:]:
            if not tile_crs.equals(survey_crs, ignore_axis_order=True):
                raise CRSError(
                    header.path,
                    f"CRS '{tile_crs.name}' differs from '{survey_crs.name}' of {Path(headers[0][0].path).name}; "
                    "pass --target-crs to reproject every tile to one CRS",
                )
    if not survey_crs.is_projected:
        raise CRSError(
            headers[0][0].path,
            f"CRS '{survey_crs.name}' is not projected; a DSM grid needs metric or foot units: "
            "pass --target-crs with a projected CRS (e.g. the local UTM zone)",
        )
    return survey_crs


def _parse_crs(text: str, option: str) -> CRS:
    try:
        return CRS.from_user_input(text)
    except ProjCRSError as e:
        raise CRSError(option, f"'{text}' is not a CRS pyproj understands ({e})") from None


def _tile_crs(header: TileHeader, assigned: CRS | None) -> CRS:
    if header.crs_wkt is not None:
        return CRS.from_wkt(header.crs_wkt)
    if assigned is not None:
        return assigned
    problem = header.crs_problem or "it has no CRS (no WKT or GeoTIFF-key VLR)"
    raise CRSError(header.path, f"{problem}; pass --crs (e.g. --crs EPSG:28992) to say which CRS it is in")


def _transform_bounds(header: TileHeader, source: CRS, target: CRS) -> tuple[float, float, float, float]:
    transformer = Transformer.from_crs(source, target, always_xy=True)
    try:
        minx, miny, maxx, maxy = transformer.transform_bounds(*header.bounds, densify_pts=21)
    except Exception as e:
        raise CRSError(header.path, f"bounds cannot be reprojected to the survey CRS: {e}") from None
    return (minx, miny, maxx, maxy)


def _vertical_unit(crs: CRS, horizontal_unit_m: float) -> float:
    """Metres per z unit: the vertical CRS's unit when there is one, else the horizontal unit."""
    for axis in crs.axis_info:
        if axis.direction in ("up", "down"):
            return axis.unit_conversion_factor
    return horizontal_unit_m


def tile_index_records(survey: Survey) -> list[dict[str, object]]:
    """Attributes of each tile for the ``tiles`` layer (geometry added by the writer)."""
    densities = [survey.tile_density(t) for t in survey.tiles]
    return [
        {
            "tile_id": t.index,
            "name": t.name,
            "path": t.path,
            "format": t.header.format,
            "las_version": t.header.version,
            "point_format": t.header.point_format,
            "point_count": t.header.point_count,
            "z_min": t.header.z_range[0],
            "z_max": t.header.z_range[1],
            "points_per_m2": round(d.points_per_m2, 4),
            "first_returns_per_m2": round(d.pulses_per_m2, 4) if d.first_returns else None,
            "reprojected": not CRS.from_wkt(t.source_crs_wkt).equals(survey.crs, ignore_axis_order=True),
            "bounds": t.bounds,
        }
        for t, d in zip(survey.tiles, densities)
    ]


def source_crs_for_task(tile: Tile, survey: Survey) -> str | None:
    """The CRS a tile's points must be reprojected from, or None when none is needed."""
    if not survey.reproject:
        return None
    if CRS.from_wkt(tile.source_crs_wkt).equals(survey.crs, ignore_axis_order=True):
        return None
    return tile.source_crs_wkt


__all__ = ["Survey", "Tile", "find_inputs", "scan_survey", "source_crs_for_task", "tile_index_records"]
