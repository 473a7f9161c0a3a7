"""Writing repaired point clouds: a tile copied point for point, fill points appended.

The output is LAZ with the input's LAS version, point format (extra bytes
included), scales, offsets, VLRs and EVLRs (the CRS among them); only the COPC
records are dropped (the copy is not a COPC file). Original points are copied
chunk by chunk as decoded, every dimension untouched; the header's counts,
per-return counts and bounds are recomputed by laspy while writing. The file is
written under a temporary name and renamed when complete.
"""

from __future__ import annotations

import copy
import os
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np
from laspy.vlrs.vlrlist import VLRList

from ..errors import InputDataError, OutputError
from .intermediate import internal_name

#: User id of the COPC records, which describe the layout of a COPC file only.
COPC_USER_ID = "copc"


@dataclass(frozen=True)
class AddedPoints:
    """Points to append to a tile, in the tile's CRS and z units."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    classification: int  # LAS class of every added point

    def __len__(self) -> int:
        return len(self.x)


@dataclass(frozen=True)
class CopyCounts:
    """What a repaired tile holds: the original points copied and the points added."""

    copied: int
    added: int


def write_repaired_tile(
    source: str | os.PathLike, target: str | os.PathLike, added: AddedPoints, *, chunk_points: int
) -> CopyCounts:
    """Copy every point of ``source`` into the LAZ ``target`` and append ``added`` as synthetic points.

    Added points: the synthetic flag set, return 1 of 1, intensity 0, point source 0,
    the GPS time of the tile's latest point (so a time-ordered file stays ordered),
    every other dimension 0.

    Raises
    ------
    InputDataError
        ``source`` cannot be decoded.
    OutputError
        ``target`` cannot be written.
    """
    source, target = Path(source), Path(target)
    partial = target.with_name(f".{internal_name(target.name)}.partial")
    copied, latest = 0, 0.0
    try:
        with laspy.open(source, decompression_selection=laspy.DecompressionSelection.all()) as reader:
            header = reader.header
            out_header = _output_header(header)
            with laspy.open(partial, mode="w", header=out_header, do_compress=True) as writer:
                for chunk in reader.chunk_iterator(chunk_points):
                    if len(chunk) == 0:
                        break
                    writer.write_points(chunk)
                    copied += len(chunk)
                    if "gps_time" in chunk.point_format.dimension_names:
                        latest = max(latest, float(np.max(chunk["gps_time"])))
                if len(added):
                    writer.write_points(_synthetic_record(header, added, latest))
                if out_header.evlrs:
                    writer.write_evlrs(out_header.evlrs)
    except OSError as e:
        partial.unlink(missing_ok=True)
        raise OutputError(f"{target}: cannot write the repaired point cloud: {e.strerror or e}") from None
    except Exception as e:  # laspy raises several unrelated types for corrupt data
        partial.unlink(missing_ok=True)
        raise InputDataError(source, f"point data cannot be copied after {copied:,} points: {e}") from None
    if copied < header.point_count:
        partial.unlink(missing_ok=True)
        raise InputDataError(source, f"header point count is {header.point_count:,} but only {copied:,} were decoded")
    os.replace(partial, target)
    return CopyCounts(copied, len(added))


def _output_header(header: laspy.LasHeader) -> laspy.LasHeader:
    """The input's header for the copy: same version, format, scales, offsets, (E)VLRs; no COPC records."""
    out = copy.deepcopy(header)
    out.vlrs = VLRList([v for v in header.vlrs if getattr(v, "user_id", "") != COPC_USER_ID])
    evlrs = [v for v in (header.evlrs or []) if getattr(v, "user_id", "") != COPC_USER_ID]
    out.evlrs = VLRList(evlrs) if evlrs else None
    return out


def _synthetic_record(header: laspy.LasHeader, added: AddedPoints, gps_time: float) -> laspy.ScaleAwarePointRecord:
    """The added points as a record of the tile's point format, scales and offsets."""
    record = laspy.ScaleAwarePointRecord.zeros(
        len(added), point_format=header.point_format, scales=header.scales, offsets=header.offsets
    )
    record.x, record.y, record.z = added.x, added.y, added.z
    record.classification = np.full(len(added), added.classification, np.uint8)
    record.synthetic = np.ones(len(added), np.uint8)
    record.return_number = np.ones(len(added), np.uint8)
    record.number_of_returns = np.ones(len(added), np.uint8)
    if "gps_time" in record.point_format.dimension_names:
        record.gps_time = np.full(len(added), gps_time)
    return record


__all__ = ["AddedPoints", "CopyCounts", "write_repaired_tile"]
