"""Reading LAS/LAZ/COPC: headers for the survey scan, points in bounded chunks.

The only module that imports laspy. Every failure is turned into an
:class:`~pipeline.errors.InputDataError` that names the file and what is wrong.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import laspy
import numpy as np

from ..errors import CRSError, InputDataError
from .copc_octree import CopcOctree, read_copc_octree

logger = logging.getLogger(__name__)

LAS_SIGNATURE = b"LASF"

#: LAZ layers the rasterizer needs (the point source id tells flight lines apart). Point formats 6-10 compress each field in its own
#: layer, so the others (intensity, GPS time, colour, ...) are never decompressed;
#: formats 0-5 compress whole points and ignore the selection.
NEEDED_LAYERS = (
    laspy.DecompressionSelection.base()
    | laspy.DecompressionSelection.Z
    | laspy.DecompressionSelection.CLASSIFICATION
    | laspy.DecompressionSelection.FLAGS
    | laspy.DecompressionSelection.POINT_SOURCE_ID
)
#: ... and, where hole causes are wanted, the layers of the sensor's geometry: the GPS time
#: orders a line's pulses and pairs the returns of one pulse; the scan angle places a
#: return in the scan plane (return numbers travel in the base layer).
SENSOR_LAYERS = NEEDED_LAYERS | laspy.DecompressionSelection.GPS_TIME | laspy.DecompressionSelection.SCAN_ANGLE


@dataclass(frozen=True)
class TileHeader:
    """What the header of one LAS/LAZ/COPC file says (nothing is decoded)."""

    path: str
    format: str  # "LAS", "LAZ" or "COPC"
    version: str
    point_format: int
    point_count: int
    bounds: tuple[float, float, float, float]  # minx, miny, maxx, maxy in the file's CRS
    z_range: tuple[float, float]
    crs_wkt: str | None
    crs_problem: str | None  # why a CRS record could not be used, if there is one
    file_size: int
    points_by_return: tuple[int, ...] = ()  # the header's per-return counts, as written
    copc: CopcOctree | None = None  # a COPC file's octree nodes (hierarchy only), for split reads


@dataclass(frozen=True)
class PointChunk:
    """Decoded points of one chunk, as stored: integer coordinates with their scale and offset.

    Materialising scaled float coordinates and bit fields through laspy's
    accessors costs almost as much as decoding; the rasterizer reads the
    integer views directly and applies ``scale * X + offset`` itself.
    """

    X: np.ndarray  # int32 views into the decoded record array
    Y: np.ndarray
    Z: np.ndarray
    scales: tuple[float, float, float]
    offsets: tuple[float, float, float]
    classification: np.ndarray  # uint8
    withheld: np.ndarray  # bool
    point_source_id: np.ndarray  # uint16: the flight line
    pulses: PulseFields | None = None  # decoded only where hole causes need the sensor's geometry
    return_number: np.ndarray | None = None  # uint8, where the reader decoded it (stage 1 counts first returns)

    def __len__(self) -> int:
        return len(self.X)

    def coordinates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Scaled float64 coordinates, as laspy computes them (``X * scale + offset``)."""
        return tuple(  # type: ignore[return-value]
            raw * scale + offset for raw, scale, offset in zip((self.X, self.Y, self.Z), self.scales, self.offsets)
        )


@dataclass(frozen=True)
class PulseFields:
    """Per point, what ties a return to its pulse and its pulse to the sensor (LAS 1.4 R15, tables 7 and 15).

    ``scan_angle_deg`` is NaN where the point format has none; a file that writes zeros
    everywhere is recognised later, from the spread of the angles.
    """

    gps_time: np.ndarray  # float64 seconds; all zero where the format has no GPS time
    return_number: np.ndarray  # uint8
    number_of_returns: np.ndarray  # uint8
    scan_angle_deg: np.ndarray  # float32 degrees from nadir


def pulse_fields(records: np.ndarray) -> PulseFields:
    """Return numbers, GPS time and scan angle from the raw records of any point format."""
    names = records.dtype.names or ()
    bits = np.asarray(records["bit_fields"])
    n = len(bits)
    if "scan_angle" in names:  # formats 6-10: 4-bit return fields, scan angle in 0.006 degree steps
        return_number, number_of_returns = bits & np.uint8(0x0F), bits >> np.uint8(4)
        angle = records["scan_angle"].astype(np.float32) * np.float32(0.006)
    else:  # formats 0-5: 3-bit return fields, whole degrees
        return_number, number_of_returns = bits & np.uint8(0x07), (bits >> np.uint8(3)) & np.uint8(0x07)
        angle = records["scan_angle_rank"].astype(np.float32)
    time = np.asarray(records["gps_time"], np.float64) if "gps_time" in names else np.zeros(n)
    return PulseFields(time, return_number, number_of_returns, angle)


def read_header(path: str | os.PathLike) -> TileHeader:
    """Read and check one file's header.

    Raises
    ------
    InputDataError
        The file is missing, not a LAS file, or its header contradicts the file
        (e.g. an uncompressed file shorter than its declared point count needs).
    """
    path = Path(path)
    try:
        file_size = path.stat().st_size
        with path.open("rb") as fh:
            signature = fh.read(4)
    except OSError as e:
        raise InputDataError(path, f"cannot be read: {e.strerror or e}") from None
    if signature != LAS_SIGNATURE:
        raise InputDataError(path, f"not a LAS/LAZ file: file signature is {signature!r}, expected b'LASF'")
    try:
        with laspy.open(path) as reader:
            header = reader.header
            is_copc = any(getattr(v, "user_id", "") == "copc" for v in header.vlrs)
    except Exception as e:  # laspy raises several unrelated types for corrupt headers
        raise InputDataError(path, f"header cannot be read: {e}") from None

    compressed = (
        header.are_points_compressed if hasattr(header, "are_points_compressed") else path.suffix.lower() == ".laz"
    )
    count = int(header.point_count)
    if not compressed:
        record_length = header.point_format.size
        data_end = header.offset_to_point_data + count * record_length
        evlrs = int(getattr(header, "number_of_evlrs", 0) or 0)
        if not evlrs and file_size - data_end >= record_length:
            held = (file_size - header.offset_to_point_data) // record_length
            raise InputDataError(
                path,
                f"header point count is {count:,} but the file holds {held:,} point records: the header "
                f"under-reports its points (refused rather than dropping {held - count:,}; repair the header)",
            )
        if file_size < data_end:
            held = max(0, (file_size - header.offset_to_point_data) // record_length)
            raise InputDataError(
                path,
                f"header point count is {count:,} but the file holds only {held:,} complete point "
                f"records (file truncated or header wrong)",
            )
    elif file_size <= header.offset_to_point_data:
        raise InputDataError(path, "LAZ file ends before its point data starts (truncated)")
    elif not is_copc:  # a COPC file's count is checked against its hierarchy
        _check_laz_count(path, header, count)
    _check_legacy_count(path, header, count)

    crs_wkt, crs_problem = None, None
    try:
        crs = header.parse_crs()
        if crs is not None:
            crs_wkt = crs.to_wkt()
    except Exception as e:
        crs_problem = f"its CRS record cannot be parsed ({e})"
    mins, maxs = header.mins, header.maxs
    _check_bounds(path, mins, maxs, count)
    copc = _copc_octree(path, count) if is_copc else None
    return TileHeader(
        path=str(path),
        format="COPC" if is_copc else ("LAZ" if compressed else "LAS"),
        version=f"{header.version.major}.{header.version.minor}",
        point_format=int(header.point_format.id),
        point_count=count,
        bounds=(float(mins[0]), float(mins[1]), float(maxs[0]), float(maxs[1])),
        z_range=(float(mins[2]), float(maxs[2])),
        crs_wkt=crs_wkt,
        crs_problem=crs_problem,
        file_size=file_size,
        points_by_return=tuple(int(c) for c in header.number_of_points_by_return),
        copc=copc,
    )


#: Byte offsets of the header's bounds, the same in LAS 1.0 to 1.4 (R15 table 3): max x, min x, max y, min y.
_BOUNDS_OFFSET = 179


def header_bounds(path: str | os.PathLike) -> tuple[float, float, float, float]:
    """A LAS/LAZ file's header bounds ``(minx, miny, maxx, maxy)``, read from the header's bytes alone.

    For a survey already read (the flight plan's ground points): 50 times quicker than
    :func:`read_header`, which parses the whole header and its records and checks them.
    """
    path = Path(path)
    try:
        with path.open("rb") as fh:
            head = fh.read(_BOUNDS_OFFSET + 32)
    except OSError as e:
        raise InputDataError(path, f"cannot be read: {e.strerror or e}") from None
    if head[:4] != LAS_SIGNATURE or len(head) < _BOUNDS_OFFSET + 32:
        raise InputDataError(path, "not a LAS/LAZ file (no complete LAS header)")
    max_x, min_x, max_y, min_y = np.frombuffer(head, "<f8", 4, _BOUNDS_OFFSET)
    return float(min_x), float(min_y), float(max_x), float(max_y)


def _check_laz_count(path: Path, header: Any, count: int) -> None:
    """Refuse a LAZ header that declares fewer points than its chunk table holds.

    laspy decodes exactly the declared count, so an under-reporting header would drop
    the rest silently. The chunk table (a seek and a few bytes) says how many chunks
    the file holds: of ``chunk_size`` points each but the last (or their own counts,
    with variable-size chunks). A file without a readable table is decoded as declared.
    """
    import lazrs

    laszip = next((v for v in header.vlrs if getattr(v, "record_id", None) == 22204), None)
    if laszip is None:
        return
    try:
        vlr = lazrs.LazVlr(laszip.record_data)
        with path.open("rb") as fh:
            fh.seek(header.offset_to_point_data)
            table = lazrs.read_chunk_table(fh, vlr)
    except Exception:  # no table (a streaming writer's file) or an unreadable one: nothing to compare
        return
    if not table:
        return
    if vlr.uses_variable_size_chunks():
        at_least = sum(int(points) for points, _ in table)
    else:
        at_least = (len(table) - 1) * int(vlr.chunk_size()) + 1
    if count < at_least:
        raise InputDataError(
            path,
            f"header point count is {count:,} but the file's LAZ chunk table holds at least {at_least:,} points: "
            f"the header under-reports its points (refused rather than dropping them; repair the header)",
        )


#: Byte offset of the legacy 32-bit point count in every LAS header (LAS 1.4 R15, table 3).
LEGACY_COUNT_OFFSET = 107


def _check_legacy_count(path: Path, header: Any, count: int) -> None:
    """Refuse a LAS 1.4 header whose legacy 32-bit point count (when set) contradicts its 64-bit one."""
    if (header.version.major, header.version.minor) < (1, 4):
        return
    try:
        with path.open("rb") as fh:
            fh.seek(LEGACY_COUNT_OFFSET)
            legacy = int.from_bytes(fh.read(4), "little")
    except OSError:
        return
    if legacy and legacy != count:
        raise InputDataError(
            path,
            f"header declares {count:,} points (LAS 1.4 count) but {legacy:,} (legacy count): the header "
            "contradicts itself (repair it)",
        )


def _copc_octree(path: Path, count: int) -> CopcOctree:
    """A COPC file's octree (nodes, offsets, counts), checked against the header's point count."""
    copc = read_copc_octree(path)
    listed = int(copc.nodes["point_count"].sum())
    if listed != count:
        raise InputDataError(path, f"COPC hierarchy lists {listed:,} points but the header declares {count:,}")
    return copc


def iter_point_chunks(
    path: str | os.PathLike,
    chunk_points: int,
    *,
    selection: laspy.DecompressionSelection = NEEDED_LAYERS,
    pulses: bool = False,
    parallel: bool = False,
) -> Iterator[PointChunk]:
    """Decode a file once, ``chunk_points`` points at a time.

    Memory is bounded by the chunk size, never the whole tile. Only the LAZ
    layers in ``selection`` are decompressed (coordinates, class and flags by
    default). A file that ends early, or decodes fewer points than its header
    declares, raises :class:`InputDataError`. With ``pulses``, the sensor's layers
    (``SENSOR_LAYERS``) are decoded too and each chunk carries its :class:`PulseFields`.
    With ``parallel``, the LAZ chunks of each read are decompressed on every core (lazrs's
    threads): for a process that decodes while the cores are otherwise free (the flight
    planner's ground), never for a worker, whose cores the other workers use.
    """
    if pulses:
        selection = selection | SENSOR_LAYERS
    for records, scales, offsets in _iter_records(path, chunk_points, selection, parallel=parallel):
        yield point_chunk(records, scales, offsets, pulses=pulses)


def iter_xy(path: str | os.PathLike, chunk_points: int, *, first_only: bool) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Scaled x, y of a file's points (first returns only with ``first_only``), ``chunk_points`` at a time.

    Decompresses the coordinate and return layer alone where the point format
    keeps layers apart (LAS 1.4 formats 6-10); the density pre-pass
    (:mod:`pipeline.survey.footprint_density`) reads nothing else. Errors as
    :func:`iter_point_chunks`.
    """
    for records, scales, offsets in _iter_records(path, chunk_points, laspy.DecompressionSelection.base()):
        x, y = records["X"], records["Y"]
        if first_only:
            keep = _return_numbers(records) == 1
            x, y = x[keep], y[keep]
        yield x * scales[0] + offsets[0], y * scales[1] + offsets[1]


def _return_numbers(records: np.ndarray) -> np.ndarray:
    """Return numbers from the raw bit fields (bits 0-2 in formats 0-5, 0-3 in formats 6-10; LAS 1.4 R15)."""
    mask = np.uint8(0x0F) if "classification_flags" in (records.dtype.names or ()) else np.uint8(0x07)
    return records["bit_fields"] & mask


def _iter_records(
    path: str | os.PathLike, chunk_points: int, selection: laspy.DecompressionSelection, *, parallel: bool = False
) -> Iterator[tuple[np.ndarray, tuple[float, float, float], tuple[float, float, float]]]:
    """A file's raw point records, chunk by chunk, with the header's scales and offsets."""
    path = Path(path)
    decoded = 0
    expected = None
    try:
        backend = _laz_backend(parallel)
        with laspy.open(path, laz_backend=backend, decompression_selection=selection) as reader:
            header = reader.header
            expected = int(header.point_count)
            sx, sy, sz = (float(v) for v in header.scales)
            ox, oy, oz = (float(v) for v in header.offsets)
            scales, offsets = (sx, sy, sz), (ox, oy, oz)
            for chunk in reader.chunk_iterator(chunk_points):
                n = len(chunk)
                if n == 0:
                    break
                decoded += n
                yield chunk.array, scales, offsets
    except InputDataError:
        raise
    except Exception as e:
        where = f"after {decoded:,} of {expected:,} points" if expected is not None else "while opening"
        raise InputDataError(path, f"point data cannot be decoded {where}: {e} (file corrupt or truncated)") from None
    if expected is not None and decoded < expected:
        raise InputDataError(path, f"header point count is {expected:,} but only {decoded:,} points could be decoded")


def _laz_backend(parallel: bool) -> laspy.LazBackend | None:
    """lazrs, on every core with ``parallel`` (None: laspy picks whatever backend is installed)."""
    if parallel and laspy.LazBackend.LazrsParallel.is_available():
        return laspy.LazBackend.LazrsParallel
    return laspy.LazBackend.Lazrs if laspy.LazBackend.Lazrs.is_available() else None


#: A header whose box leaves more than this area (CRS units squared) per point is not believed.
IMPLAUSIBLE_AREA_PER_POINT = 1e4
#: ... when the box is also larger than this (a few sparse points in a small box are fine).
IMPLAUSIBLE_MIN_AREA = 1e8


def _check_bounds(path: Path, mins, maxs, count: int) -> None:
    """Refuse header bounds that are not numbers, inverted, or absurd for the point count.

    A grid is planned from headers before any point is read, so one absurd box (a
    truncated file's header, a coordinate typo) would make the whole survey's grid.
    """
    values = [float(v) for v in (*mins[:3], *maxs[:3])]
    if not all(math.isfinite(v) for v in values):
        raise InputDataError(path, f"header bounds are not finite numbers (min {list(mins)}, max {list(maxs)})")
    if any(lo > hi for lo, hi in zip(mins[:3], maxs[:3])):
        raise InputDataError(path, f"header bounds are inverted (min {list(mins)} above max {list(maxs)})")
    area = (float(maxs[0]) - float(mins[0])) * (float(maxs[1]) - float(mins[1]))
    if area > IMPLAUSIBLE_MIN_AREA and area / max(count, 1) > IMPLAUSIBLE_AREA_PER_POINT:
        raise InputDataError(
            path,
            f"header bounds span {area:.3g} square units for {count:,} points (one point per "
            f"{area / max(count, 1):.3g}): the bounds are implausible",
        )


def point_chunk(
    records: np.ndarray,
    scales: tuple[float, float, float],
    offsets: tuple[float, float, float],
    *,
    pulses: bool = False,
) -> PointChunk:
    """A :class:`PointChunk` over decoded point records (views, no copy of the coordinates)."""
    classification, withheld = _class_and_withheld(records)
    return PointChunk(
        X=records["X"], Y=records["Y"], Z=records["Z"], scales=scales, offsets=offsets,
        classification=classification, withheld=withheld, point_source_id=records["point_source_id"],
        pulses=pulse_fields(records) if pulses else None, return_number=_return_numbers(records),
    )  # fmt: skip


def _class_and_withheld(records: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Class and withheld flag from the raw bytes of any point format (LAS 1.4 R15, tables 7-8 and 15-16)."""
    names = records.dtype.names or ()
    if "raw_classification" in names:  # formats 0-5: class in bits 0-4, withheld in bit 7
        raw = records["raw_classification"]
        return raw & np.uint8(0x1F), (raw & np.uint8(0x80)) != 0
    # formats 6-10: a whole byte of class; flags byte bit 2 is withheld
    return np.asarray(records["classification"]), (records["classification_flags"] & np.uint8(0x04)) != 0


def decode_only(path: str | os.PathLike, chunk_points: int) -> int:
    """Decode every point of a file and drop it: the baseline of the benchmark."""
    total = 0
    for chunk in iter_point_chunks(path, chunk_points, selection=laspy.DecompressionSelection.all()):
        total += len(chunk)
    return total


__all__ = [
    "CRSError",
    "PointChunk",
    "PulseFields",
    "TileHeader",
    "decode_only",
    "header_bounds",
    "iter_point_chunks",
    "iter_xy",
    "pulse_fields",
    "read_header",
]
