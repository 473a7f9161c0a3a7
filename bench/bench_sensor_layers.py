"""What the sensor's geometry costs in stage 1 at the least: its LAZ layers and its sums, against a full decode.

    .venv/bin/python bench/bench_sensor_layers.py FILE_OR_FOLDER... [--repeat 7]

Issue 15 asks the causes from the sensor's geometry to cost at most 0.2 x decoding the
same files (``bench_command.py``'s baseline decodes every layer). In point formats 6-10
every field is compressed in a layer of its own, and stage 1 decodes only the layers it
needs (``pipeline.io.las.NEEDED_LAYERS``); the sensor's geometry adds the GPS-time and
scan-angle layers (``SENSOR_LAYERS``) and the trajectory sums
(``pipeline.sensor.sums.trajectory_sums``). This prints, in one process, the best of
``--repeat`` passes over the files (ns a point) of: decoding the DSM's layers, with GPS
time, with the scan angle, with both, and every layer (the baseline); then the sums over
the decoded chunks; and the sensor's share of the baseline, ``(both - DSM's + sums) / every
layer``: the floor under the stage's cost before any line of sight is cast. Formats 0-5
compress whole points (every selection decodes everything): their layers cost nothing extra.
No assertions.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import laspy
import numpy as np

from pipeline.io.las import NEEDED_LAYERS, SENSOR_LAYERS, iter_point_chunks
from pipeline.sensor.sums import trajectory_sums

CHUNK_POINTS = 1_000_000


def _files(paths: list[str]) -> list[Path]:
    out: list[Path] = []
    for p in map(Path, paths):
        out += sorted(p.glob("*.la[sz]")) if p.is_dir() else [p]
    return out


def decode_seconds(files: list[Path], selection: laspy.DecompressionSelection) -> float:
    """Seconds to decode every file with ``selection``, chunk by chunk, as stage 1 reads them."""
    start = time.perf_counter()
    for path in files:
        with laspy.open(path, laz_backend=laspy.LazBackend.Lazrs, decompression_selection=selection) as reader:
            for _ in reader.chunk_iterator(CHUNK_POINTS):
                pass
    return time.perf_counter() - start


def sums_seconds(files: list[Path]) -> float:
    """Seconds of the trajectory sums alone over every file's decoded chunks (the decoding not counted)."""
    total = 0.0
    for path in files:
        for chunk in iter_point_chunks(path, CHUNK_POINTS, pulses=True):
            pulses = chunk.pulses
            keep = np.ones(len(chunk), bool)
            start = time.perf_counter()
            trajectory_sums(
                chunk.X, chunk.Y, chunk.Z, chunk.point_source_id, pulses.gps_time, pulses.return_number,
                pulses.number_of_returns, pulses.scan_angle_deg, keep,
                origin=(chunk.offsets[0], chunk.offsets[1], chunk.offsets[2]), scales=chunk.scales, offsets=chunk.offsets,
            )  # fmt: skip
            total += time.perf_counter() - start
    return total


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="+")
    parser.add_argument("--repeat", type=int, default=7)
    args = parser.parse_args(argv)
    files = _files(args.paths)
    points = sum(laspy.open(f).header.point_count for f in files)
    formats = sorted({laspy.open(f).header.point_format.id for f in files})
    selections = {
        "DSM's layers": NEEDED_LAYERS,
        "+ GPS time": NEEDED_LAYERS | laspy.DecompressionSelection.GPS_TIME,
        "+ scan angle": NEEDED_LAYERS | laspy.DecompressionSelection.SCAN_ANGLE,
        "+ both (sensor)": SENSOR_LAYERS,
        "every layer (baseline)": laspy.DecompressionSelection.all(),
    }
    sums_seconds(files[:1])  # compile the kernels outside the timing
    best = dict.fromkeys([*selections, "sums"], float("inf"))
    for _ in range(args.repeat):  # interleaved passes: each sees the same machine state
        for name, selection in selections.items():
            best[name] = min(best[name], decode_seconds(files, selection))
        best["sums"] = min(best["sums"], sums_seconds(files))
    ns = {name: seconds * 1e9 / points for name, seconds in best.items()}
    print(f"{len(files)} files, {points:,} points, point formats {formats}, best of {args.repeat}")
    for name, value in ns.items():
        print(f"  {name:24s} {value:6.1f} ns a point")
    layers = ns["+ both (sensor)"] - ns["DSM's layers"]
    baseline = ns["every layer (baseline)"]
    print(f"  sensor layers {layers:.1f} ns = {layers / baseline:.3f} x the baseline; with the sums "
          f"{layers + ns['sums']:.1f} ns = {(layers + ns['sums']) / baseline:.3f} x")  # fmt: skip


if __name__ == "__main__":
    sys.exit(main())
