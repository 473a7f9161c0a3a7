"""COPC files: decoding a chosen set of octree nodes, and writing COPC.

A COPC file (https://copc.io) is a LAZ 1.4 file whose points are grouped into
the nodes of an octree, one variable-size LAZ chunk per node, with a hierarchy
(EVLR) listing each node's key, byte offset, byte size and point count. A
large file can therefore be read by several tasks, each decompressing its own
nodes' byte ranges and nothing else (:mod:`pipeline.reads` assigns the nodes). The
hierarchy (:class:`CopcOctree`) is read with the header, by :mod:`.copc_octree`, which
needs nothing of this module (so :mod:`.las` and this module do not import each other).

Reading uses laspy's COPC hierarchy parser and lazrs's chunk-table decoder (what
``laspy.CopcReader.query`` does inside), without its bounds filter: every point
of a node is returned, so every point is decoded exactly once in a run.
Writing (:func:`write_copc`) lays the points of a LAS/LAZ file into an octree
with lazrs; it serves the tests and the benchmark (no COPC is written by a run).
"""

from __future__ import annotations

import dataclasses
import io
import os
import struct
from collections.abc import Iterator, Sequence
from pathlib import Path

import laspy
import numpy as np
from laspy.point.record import PackedPointRecord

from ..errors import InputDataError
from .copc_octree import NODE_DTYPE, CopcOctree, read_copc_octree
from .las import NEEDED_LAYERS, SENSOR_LAYERS, PointChunk, PulseFields, point_chunk
from .plain_data import write_npz_atomically

__all__ = ["CopcOctree", "iter_copc_nodes", "load_point_chunk", "read_copc_octree", "save_point_chunk", "write_copc"]


def iter_copc_nodes(
    path: str | os.PathLike,
    nodes: Sequence[tuple[int, int, int]],
    chunk_points: int,
    *,
    selection: laspy.DecompressionSelection = NEEDED_LAYERS,
    pulses: bool = False,
) -> Iterator[PointChunk]:
    """Decode the given nodes of a COPC file, about ``chunk_points`` points at a time.

    ``nodes`` are ``(byte offset, byte size, point count)`` of the node chunks
    (from :class:`CopcOctree`); each is read and decompressed once, whole. Memory
    is bounded by ``chunk_points`` or one node, whichever is larger.

    Raises
    ------
    InputDataError
        A chunk cannot be read or decompressed (file truncated or corrupt).
    """
    path = Path(path)
    if pulses:
        selection = selection | SENSOR_LAYERS
    decoded = 0
    expected = sum(int(n[2]) for n in nodes)
    try:
        with path.open("rb") as fh:
            header = laspy.LasHeader.read_from(fh)
            laszip = header.vlrs.get("LasZipVlr")[0].record_data
            scales = tuple(float(v) for v in header.scales)
            offsets = tuple(float(v) for v in header.offsets)
            for batch in _batches(sorted(nodes), chunk_points):
                records = _decompress(fh, batch, header.point_format, laszip, selection)
                decoded += len(records)
                yield point_chunk(records, scales, offsets, pulses=pulses)  # type: ignore[arg-type]
    except InputDataError:
        raise
    except Exception as e:
        raise InputDataError(
            path, f"COPC chunks cannot be decoded after {decoded:,} of {expected:,} points: {e} (file corrupt)"
        ) from None


def _batches(nodes: list[tuple[int, int, int]], chunk_points: int) -> Iterator[list[tuple[int, int, int]]]:
    """Consecutive nodes grouped up to ``chunk_points`` points (a larger node forms a batch alone)."""
    batch: list[tuple[int, int, int]] = []
    count = 0
    for node in nodes:
        if batch and count + node[2] > chunk_points:
            yield batch
            batch, count = [], 0
        batch.append(node)
        count += node[2]
    if batch:
        yield batch


def _decompress(fh, batch, point_format, laszip: bytes, selection: laspy.DecompressionSelection) -> np.ndarray:
    """The records of a batch of node chunks, decompressed by lazrs from their byte ranges."""
    import lazrs

    compressed = bytearray(sum(int(size) for _, size, _ in batch))
    view = memoryview(compressed)
    start = 0
    for offset, size, _ in batch:
        fh.seek(int(offset))
        if fh.readinto(view[start : start + int(size)]) != size:
            raise InputDataError(Path(fh.name), f"COPC chunk at byte {offset} ends early (file truncated)")
        start += int(size)
    count = sum(int(points) for _, _, points in batch)
    out = np.zeros(count * point_format.size, dtype=np.uint8)
    table = [(int(points), int(size)) for _, size, points in batch]
    lazrs.decompress_points_with_chunk_table(compressed, laszip, out, table, selection.to_lazrs())
    return PackedPointRecord.from_buffer(out, point_format).array


# -- writing (tests and benchmarks) ---------------------------------------------------

#: Points a node keeps before its remaining points go down to its children.
DEFAULT_NODE_POINTS = 20_000
#: The sampling grid of a node (per axis): a node keeps one point per grid voxel.
NODE_GRID = 64
MAX_LEVEL = 12


def write_copc(
    source: str | os.PathLike | Sequence[str | os.PathLike],
    path: str | os.PathLike,
    *,
    max_node_points: int = DEFAULT_NODE_POINTS,
) -> int:
    """Write the points of one or more LAS/LAZ files (one CRS, one point format) into one COPC file.

    The octree is built the usual way: a node keeps one point per voxel of a
    ``NODE_GRID``-cube lattice over itself and passes the others to its eight
    children, until a node holds at most ``max_node_points``. Points are
    converted to point format 6 (7/8 when the source has colour), as COPC
    requires, and written one LAZ chunk per node; returns the number of nodes.
    """
    sources = [source] if isinstance(source, (str, os.PathLike)) else list(source)
    las = _read_all(sources)
    center, halfsize = _root_cube(las.header.mins, las.header.maxs)
    order, entries = _build_octree(np.column_stack([las.x, las.y, las.z]), center, halfsize, max_node_points)
    points = las.points.array[order]
    _write_file(path, las.header, points, entries, center, halfsize)
    return len(entries)


def _read_all(sources: list) -> laspy.LasData:
    """The files' points as one LasData in a COPC point format (6, 7 or 8)."""
    parts = [laspy.read(p) for p in sources]
    first = parts[0]
    target = {6: 6, 7: 7, 8: 8}.get(first.header.point_format.id, 7 if first.header.point_format.id in (2, 3, 5) else 6)
    header = laspy.LasHeader(point_format=target, version="1.4")
    header.scales, header.offsets = first.header.scales, first.header.offsets
    crs = first.header.parse_crs()
    if crs is not None:
        header.add_crs(crs)
    merged = laspy.LasData(header)
    arrays = []
    for part in parts:
        converted = laspy.convert(part, point_format_id=target, file_version="1.4")
        record = laspy.ScaleAwarePointRecord.zeros(len(converted.points), header=header)
        for name in record.array.dtype.names:
            if name in ("X", "Y", "Z"):
                continue
            if name in converted.points.array.dtype.names:
                record.array[name] = converted.points.array[name]
        record.x, record.y, record.z = converted.x, converted.y, converted.z  # rescaled to the first file
        arrays.append(record.array)
    merged.points = laspy.ScaleAwarePointRecord(
        np.concatenate(arrays), header.point_format, header.scales, header.offsets
    )
    merged.update_header()
    return merged


def _root_cube(mins, maxs) -> tuple[np.ndarray, float]:
    center = (np.asarray(mins[:3], np.float64) + np.asarray(maxs[:3], np.float64)) / 2
    halfsize = float(np.max(np.asarray(maxs[:3]) - np.asarray(mins[:3]))) / 2 * 1.0001 + 1e-6
    return center, halfsize


def _build_octree(
    xyz: np.ndarray, center: np.ndarray, halfsize: float, max_node_points: int
) -> tuple[np.ndarray, list[tuple[int, int, int, int, int]]]:
    """Point order (node by node) and ``(level, x, y, z, point count)`` of each node, root first."""
    base = center - halfsize
    order_parts, entries = [], []
    stack = [(0, 0, 0, 0, np.arange(len(xyz)))]
    while stack:
        level, kx, ky, kz, index = stack.pop(0)
        side = 2 * halfsize / 2**level
        lower = base + np.array([kx, ky, kz]) * side
        local = np.clip((xyz[index] - lower) / side, 0, np.nextafter(1, 0))
        if len(index) <= max_node_points or level >= MAX_LEVEL:
            keep = np.ones(len(index), bool)
        else:
            voxel = np.floor(local * NODE_GRID).astype(np.int64)
            flat = (voxel[:, 0] * NODE_GRID + voxel[:, 1]) * NODE_GRID + voxel[:, 2]
            keep = np.zeros(len(index), bool)
            keep[np.unique(flat, return_index=True)[1]] = True
        order_parts.append(index[keep])
        entries.append((level, kx, ky, kz, int(keep.sum())))
        rest, octant = index[~keep], (local[~keep] >= 0.5).astype(np.int64)
        for child in range(8):
            dx, dy, dz = child & 1, (child >> 1) & 1, (child >> 2) & 1
            chosen = rest[(octant[:, 0] == dx) & (octant[:, 1] == dy) & (octant[:, 2] == dz)]
            if len(chosen):
                stack.append((level + 1, 2 * kx + dx, 2 * ky + dy, 2 * kz + dz, chosen))
    return np.concatenate(order_parts), entries


def _write_file(path, header: laspy.LasHeader, points: np.ndarray, entries, center, halfsize: float) -> None:
    """Header and VLRs (COPC info first), one LAZ chunk per node, the chunk table, the hierarchy EVLR."""
    import lazrs

    laz_vlr = lazrs.LazVlr.new_for_compression(header.point_format.id, header.point_format.num_extra_bytes, True)
    info = laspy.VLR("copc", 1, "copc info", bytes(160))
    header.vlrs.insert(0, info)
    header.vlrs.append(laspy.VLR("laszip encoded", 22204, "lazrs", laz_vlr.record_data()))
    header.are_points_compressed = True
    with open(path, "w+b") as fh:
        header.write_to(fh)
        compressor = lazrs.LasZipCompressor(fh, laz_vlr)
        start = 0
        for *_, count in entries:
            compressor.compress_many(np.frombuffer(points[start : start + count].tobytes(), np.uint8))
            compressor.finish_current_chunk()
            start += count
        compressor.done()
        fh.seek(header.offset_to_point_data)
        table = lazrs.read_chunk_table(fh, laz_vlr)  # the chunks' byte sizes, as lazrs wrote them
        sizes = np.array([size for _, size in table], np.int64)
        offsets = header.offset_to_point_data + 8 + np.concatenate([[0], np.cumsum(sizes)[:-1]])
        rows = [(*entry[:4], offset, size, entry[4]) for entry, offset, size in zip(entries, offsets, sizes)]
        fh.seek(0, io.SEEK_END)
        evlr_start = fh.tell()
        hierarchy = np.array(rows, dtype=NODE_DTYPE).tobytes()
        fh.write(struct.pack("<H16sHQ32s", 0, b"copc", 1000, len(hierarchy), b"EPT hierarchy"))
        fh.write(hierarchy)
        spacing = 2 * halfsize / NODE_GRID
        info.record_data = struct.pack(
            "<5d2Q2d11Q", *center, halfsize, spacing, evlr_start + 60, len(hierarchy), 0.0, 0.0, *([0] * 11)
        )
        header.start_of_first_evlr, header.number_of_evlrs = evlr_start, 1
        fh.seek(0)
        header.write_to(fh, ensure_same_size=True)


# -- points handed from a COPC file's top task to its cell tasks ------------------------


def save_point_chunk(path: str | os.PathLike, chunk: PointChunk, keep: np.ndarray) -> None:
    """Keep the points ``keep`` of a decoded chunk for another task (``.npz``, the raw fields)."""
    pulses = {} if chunk.pulses is None else {f"pulse_{k}": v[keep] for k, v in vars(chunk.pulses).items()}
    write_npz_atomically(path, dict(
        X=chunk.X[keep], Y=chunk.Y[keep], Z=chunk.Z[keep],
        classification=chunk.classification[keep], withheld=chunk.withheld[keep],
        point_source_id=chunk.point_source_id[keep],
        scales=np.array(chunk.scales), offsets=np.array(chunk.offsets), **pulses,
    ))  # fmt: skip


def load_point_chunk(path: str | os.PathLike) -> PointChunk:
    """Points kept by :func:`save_point_chunk`."""
    with np.load(path) as data:
        fields = [f.name for f in dataclasses.fields(PulseFields)]
        pulses = PulseFields(*(data[f"pulse_{f}"] for f in fields)) if f"pulse_{fields[0]}" in data else None
        return PointChunk(
            X=data["X"], Y=data["Y"], Z=data["Z"],
            scales=tuple(float(v) for v in data["scales"]),  # type: ignore[arg-type]
            offsets=tuple(float(v) for v in data["offsets"]),  # type: ignore[arg-type]
            classification=data["classification"], withheld=data["withheld"],
            point_source_id=data["point_source_id"], pulses=pulses,
        )  # fmt: skip
