"""Benchmark: `holefill run` (stage 1 + DSM output) against decoding the same LAZ with laspy alone.

Hole detection is off unless --with-holes (the DSM is what this compares). Both sides run on a fresh Dask LocalCluster with the same number of single-threaded worker
processes, one task per tile, started inside the timed region; runs are interleaved
(baseline, holefill, baseline, holefill, ...) so both see the same machine state. Prints
both times, their ratio, points per second and the peak resident memory of each worker.

    .venv/bin/python bench/bench_rasterize.py                   # ~25 M points, 2 workers
    .venv/bin/python bench/bench_rasterize.py --size-m 3000 --workers 16

The synthetic survey is generated once into bench-out/ and reused.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import resource
import shutil
import sys
import time
from pathlib import Path

import laspy

from pipeline.config import load_config
from pipeline.run import run_survey
from pipeline.synth import generate_survey, preset


def decode_tile(path: str, chunk_points: int) -> int:
    """The baseline task: laspy + lazrs decoding every point of one file, in chunks."""
    total = 0
    with laspy.open(path, laz_backend=laspy.LazBackend.Lazrs) as reader:
        for chunk in reader.chunk_iterator(chunk_points):
            total += len(chunk)
    return total


def decode_tile_with_coordinates(path: str, chunk_points: int) -> int:
    """A second baseline: decoding plus scaling x, y, z to float64 (what any DSM needs)."""
    total = 0
    with laspy.open(path, laz_backend=laspy.LazBackend.Lazrs) as reader:
        for chunk in reader.chunk_iterator(chunk_points):
            _ = (chunk.x[:], chunk.y[:], chunk.z[:])  # scaled float64 coordinates
            total += len(chunk)
    return total


def peak_rss_bytes() -> int:
    """Peak resident memory of the calling process (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def local_cluster(workers: int, memory_limit: str = "auto"):
    from distributed import Client, LocalCluster

    cluster = LocalCluster(
        n_workers=workers, threads_per_worker=1, processes=True, memory_limit=memory_limit,
        dashboard_address=":0", silence_logs=logging.CRITICAL,
    )  # fmt: skip
    return cluster, Client(cluster)


def time_baseline(tiles: list[str], workers: int, chunk_points: int, task) -> tuple[float, int, list[int]]:
    started = time.perf_counter()
    cluster, client = local_cluster(workers)
    try:
        futures = [client.submit(task, t, chunk_points, pure=False) for t in tiles]
        points = sum(f.result() for f in futures)
        peaks = list(client.run(peak_rss_bytes).values())
    finally:
        client.close()
        cluster.close()
    return time.perf_counter() - started, points, peaks


def time_holefill(tiles_dir: Path, out: Path, workers: int, overrides: list[str]) -> tuple[float, int, list[int], dict]:
    config = load_config(overrides=[f"dask.workers={workers}", *overrides])
    started = time.perf_counter()
    cluster, client = local_cluster(workers)
    try:
        summary = run_survey([str(tiles_dir)], out, config, client=client)
        peaks = list(client.run(peak_rss_bytes).values())
    finally:
        client.close()
        cluster.close()
    return time.perf_counter() - started, summary.points_read, peaks, summary.stage_seconds


def _arguments() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size-m", type=float, default=1500.0, help="side of the square survey (m); ~11 points/m2")
    parser.add_argument("--tile-m", type=float, default=250.0, help="LAZ tile side (m)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--resolution", type=float, default=0.5, help="DSM pixel size (m)")
    parser.add_argument(
        "--las-version", choices=["1.2", "1.4"], default="1.4",
        help="1.4: point format 6 (layered LAZ: only needed layers are decoded); 1.2: point format 1",
    )  # fmt: skip
    parser.add_argument("--bench-dir", type=Path, default=Path("bench-out"))
    parser.add_argument("--json", type=Path, help="also write the figures to this file")
    parser.add_argument(
        "--with-holes", action="store_true",
        help="time the whole run, hole detection included (default: stage 1 + DSM output, holes.enabled=false)",
    )  # fmt: skip
    return parser.parse_args()


def _survey(args: argparse.Namespace) -> tuple[Path, Path]:
    """The benchmark survey's folder and its completion marker, generated once."""

    spec = preset(
        "bench", width_m=args.size_m, height_m=args.size_m, tile_size_m=args.tile_m, las_version=args.las_version
    )
    suffix = "" if args.las_version == "1.4" else "_las12"
    survey_dir = args.bench_dir / f"survey_{int(args.size_m)}m_{int(args.tile_m)}m{suffix}"
    marker = survey_dir / "complete.json"
    if not marker.exists():
        shutil.rmtree(survey_dir, ignore_errors=True)
        t0 = time.perf_counter()
        synthetic = generate_survey(survey_dir, spec, keep_truth=False)
        marker.write_text(json.dumps({"points": synthetic.n_points, "tiles": len(synthetic.tiles)}))
        print(
            f"generated {synthetic.n_points:,} points in {len(synthetic.tiles)} tiles in {time.perf_counter() - t0:.1f} s"
        )
    return survey_dir, marker


def main() -> None:
    args = _arguments()
    survey_dir, marker = _survey(args)
    info = json.loads(marker.read_text())
    tiles = sorted(str(p) for p in survey_dir.glob("*.laz"))
    size_mb = sum(Path(t).stat().st_size for t in tiles) / 1e6
    chunk = load_config().rasterize.chunk_points
    overrides = [f"grid.resolution_m={args.resolution}", f"holes.enabled={'true' if args.with_holes else 'false'}"]
    print(
        f"survey: {info['points']:,} points, {len(tiles)} LAZ {args.las_version} tiles, {size_mb:.0f} MB; "
        f"workers: {args.workers}; DSM {args.resolution} m; hole stage {'on' if args.with_holes else 'off'}; machine: {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} cores, Python {sys.version.split()[0]}"
    )
    rows = {"decode": [], "decode_xyz": [], "holefill": []}
    peaks = {"decode": 0, "decode_xyz": 0, "holefill": 0}
    stages = []
    for i in range(args.repeat):
        seconds, points, worker_peaks = time_baseline(tiles, args.workers, chunk, decode_tile)
        rows["decode"].append(seconds)
        peaks["decode"] = max(peaks["decode"], *worker_peaks)
        seconds, points_xyz, worker_peaks = time_baseline(tiles, args.workers, chunk, decode_tile_with_coordinates)
        rows["decode_xyz"].append(seconds)
        peaks["decode_xyz"] = max(peaks["decode_xyz"], *worker_peaks)
        out = args.bench_dir / "run-out"
        seconds, read, worker_peaks, stage_seconds = time_holefill(survey_dir, out, args.workers, overrides)
        assert read == points == points_xyz == info["points"], (read, points, info["points"])
        rows["holefill"].append(seconds)
        peaks["holefill"] = max(peaks["holefill"], *worker_peaks)
        stages.append(stage_seconds)
        print(
            f"run {i + 1}: decode {rows['decode'][-1]:.2f} s, decode+xyz {rows['decode_xyz'][-1]:.2f} s, "
            f"holefill {seconds:.2f} s (stages: " + ", ".join(f"{k} {v:.2f}" for k, v in stage_seconds.items()) + ")"
        )
    best = {k: min(v) for k, v in rows.items()}
    figures = {
        "las_version": args.las_version,
        "with_holes": args.with_holes,
        "points": info["points"],
        "tiles": len(tiles),
        "workers": args.workers,
        "decode_s": round(best["decode"], 2),
        "decode_xyz_s": round(best["decode_xyz"], 2),
        "holefill_s": round(best["holefill"], 2),
        "ratio_vs_decode": round(best["holefill"] / best["decode"], 3),
        "ratio_vs_decode_xyz": round(best["holefill"] / best["decode_xyz"], 3),
        "holefill_points_per_s": round(info["points"] / best["holefill"]),
        "decode_points_per_s": round(info["points"] / best["decode"]),
        "peak_worker_rss_mb": {k: round(v / 2**20) for k, v in peaks.items()},
    }
    print(
        f"best of {args.repeat}: decode-only {best['decode']:.2f} s ({figures['decode_points_per_s'] / 1e6:.2f} M pts/s), "
        f"holefill {best['holefill']:.2f} s ({figures['holefill_points_per_s'] / 1e6:.2f} M pts/s); "
        f"ratio {figures['ratio_vs_decode']:.3f} (vs decode+xyz {figures['ratio_vs_decode_xyz']:.3f}); "
        f"peak memory per worker: holefill {figures['peak_worker_rss_mb']['holefill']} MB, "
        f"decode-only {figures['peak_worker_rss_mb']['decode']} MB"
    )
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2))


if __name__ == "__main__":
    main()
