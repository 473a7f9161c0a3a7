"""Benchmark: one COPC file read by split tasks, against the same points in LAZ tiles and decoding alone.

A synthetic survey (a few million points) is generated into a temporary folder as
LAZ tiles, and the same points are written into one COPC file
(:func:`pipeline.io.copc.write_copc`). Timed, interleaved, best of ``--repeat``:

- ``holefill`` (stage 1 + DSM output, holes off) on the LAZ tiles, one task per tile;
- ``holefill`` on the COPC file split into read tasks (``rasterize.copc_split = true``);
- ``holefill`` on the COPC file read whole by one task (``rasterize.copc_split = false``);
- laspy + lazrs decoding alone, every layer, in a process pool of as many workers:
  the LAZ tiles one per process task, and the COPC file's node groups (the split
  read tasks' nodes) one per process task.

The holefill runs include starting their Dask cluster, as a user's run does. Besides the
wall time, each variant's CPU time is reported (this process and its finished children: the
pool's or the cluster's worker processes), which a machine shared with other work disturbs
far less than the wall time.

    .venv/bin/python bench/bench_copc.py                  # ~5 M points, 2 workers
    .venv/bin/python bench/bench_copc.py --size-m 1000 --workers 8
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing
import os
import platform
import resource
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import laspy

from pipeline.config import load_config
from pipeline.io.copc import iter_copc_nodes, write_copc
from pipeline.plan import plan_survey
from pipeline.run import run_survey
from pipeline.survey.scan import scan_survey
from pipeline.synth import generate_survey, preset

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_rasterize import decode_tile as decode_laz  # the baseline: laspy + lazrs, every layer, in chunks


def decode_nodes(path: str, nodes: tuple, chunk_points: int) -> int:
    """Baseline task: lazrs decoding every layer of some COPC nodes (what a split read task decodes)."""
    selection = laspy.DecompressionSelection.all()
    return sum(len(chunk) for chunk in iter_copc_nodes(path, nodes, chunk_points, selection=selection))


def cpu_seconds() -> float:
    """CPU time of this process and of its children that have ended (user + system)."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def time_pool(workers: int, function, jobs: list[tuple]) -> tuple[float, int]:
    started = time.perf_counter()
    # spawned, not forked: the parent holds threads (Dask's, numba's) that a fork would copy mid-lock
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        points = sum(pool.map(function, *zip(*jobs)))
    return time.perf_counter() - started, points


def time_holefill(inputs: list[str], out: Path, workers: int, overrides: list[str]) -> tuple[float, int, int]:
    from distributed import Client, LocalCluster

    config = load_config(overrides=[f"dask.workers={workers}", *overrides])
    started = time.perf_counter()
    with (
        LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
            silence_logs=logging.CRITICAL,
        ) as cluster,
        Client(cluster) as client,
    ):  # fmt: skip
        summary = run_survey(inputs, out, config, client=client, overwrite=True)
    manifest = json.loads((out / "manifest.json").read_text())
    tasks = sum(entry["read_tasks"] for entry in manifest["inputs"])
    return time.perf_counter() - started, summary.points_read, tasks


VARIANTS = ("laz", "copc_split", "copc_whole", "decode_laz", "decode_copc")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size-m", type=float, default=800.0, help="side of the square survey (m); ~11 points/m2")
    parser.add_argument("--tile-m", type=float, default=200.0, help="LAZ tile side (m)")
    parser.add_argument("--cell-m", type=float, default=200.0, help="grid.cell_size_m (m)")
    parser.add_argument("--resolution", type=float, default=1.0, help="DSM pixel size (m)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--json", type=Path, help="also write the figures to this file")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-copc-") as tmp:
        survey = prepare(Path(tmp), args)
        wall: dict[str, list[float]] = {k: [] for k in VARIANTS}
        cpu: dict[str, list[float]] = {k: [] for k in VARIANTS}
        tasks: dict[str, int] = {}
        for i in range(args.repeat):
            for name in VARIANTS:
                cpu_before = cpu_seconds()
                seconds, points, tasks[name] = run_variant(name, survey, args.workers)
                cpu[name].append(cpu_seconds() - cpu_before)
                wall[name].append(seconds)
                assert points == survey["points"], (name, points)
            print(f"run {i + 1}: " + ", ".join(f"{k} {wall[k][-1]:.2f} s ({cpu[k][-1]:.1f} s CPU)" for k in VARIANTS))
        figures = summarize(survey, args, wall, cpu, tasks)
        if args.json:
            args.json.write_text(json.dumps(figures, indent=2))


def prepare(folder: Path, args) -> dict:
    """The synthetic survey as LAZ tiles, the same points as one COPC file, and the split read tasks' nodes."""
    t0 = time.perf_counter()
    spec = preset("bench", width_m=args.size_m, height_m=args.size_m, tile_size_m=args.tile_m)
    synthetic = generate_survey(folder / "tiles", spec, keep_truth=False)
    tiles = sorted(str(p) for p in (folder / "tiles").glob("*.laz"))
    t1 = time.perf_counter()
    copc = str(folder / "survey.copc.laz")
    nodes = write_copc(tiles, copc)
    t2 = time.perf_counter()
    overrides = [
        f"grid.resolution_m={args.resolution}",
        f"grid.cell_size_m={args.cell_m}",
        "holes.enabled=false",
        "flightplan.enabled=false",
    ]
    chunk = load_config().rasterize.chunk_points
    plan = plan_survey(scan_survey([copc]), load_config(overrides=[*overrides, "rasterize.copc_split=true"]))
    size_mb = sum(Path(t).stat().st_size for t in tiles) / 1e6
    print(
        f"survey: {synthetic.n_points:,} points; {len(tiles)} LAZ tiles ({size_mb:.0f} MB, generated in "
        f"{t1 - t0:.1f} s); one COPC file of {nodes} nodes ({Path(copc).stat().st_size / 1e6:.0f} MB, "
        f"written in {t2 - t1:.1f} s); {len(plan.cells)} cells of {args.cell_m:g} m, DSM {args.resolution} m; "
        f"workers: {args.workers}; machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"Python {sys.version.split()[0]}"
    )
    return {
        "folder": folder,
        "tiles": tiles,
        "copc": copc,
        "nodes": nodes,
        "points": synthetic.n_points,
        "overrides": overrides,
        "chunk": chunk,
        "node_jobs": [(copc, read.nodes, chunk) for read in plan.reads],
    }


def run_variant(name: str, survey: dict, workers: int) -> tuple[float, int, int]:
    """Wall seconds, points decoded and tasks of one variant."""
    if name == "decode_laz":
        return (*time_pool(workers, decode_laz, [(t, survey["chunk"]) for t in survey["tiles"]]), len(survey["tiles"]))
    if name == "decode_copc":
        return (*time_pool(workers, decode_nodes, survey["node_jobs"]), len(survey["node_jobs"]))
    inputs = survey["tiles"] if name == "laz" else [survey["copc"]]
    split = "true" if name == "copc_split" else "false"
    overrides = [*survey["overrides"], f"rasterize.copc_split={split}"]
    return time_holefill(inputs, survey["folder"] / f"out-{name}", workers, overrides)


def summarize(survey: dict, args, wall: dict, cpu: dict, tasks: dict) -> dict:
    """Best of the repeats, the ratios, printed and returned."""
    best = {k: min(v) for k, v in wall.items()}
    best_cpu = {k: min(v) for k, v in cpu.items()}

    def ratios(values: dict) -> dict:
        return {
            "copc_split_vs_laz": round(values["copc_split"] / values["laz"], 3),
            "copc_split_vs_copc_whole": round(values["copc_split"] / values["copc_whole"], 3),
            "copc_split_vs_decode_copc": round(values["copc_split"] / values["decode_copc"], 3),
            "laz_vs_decode_laz": round(values["laz"] / values["decode_laz"], 3),
            "decode_copc_vs_decode_laz": round(values["decode_copc"] / values["decode_laz"], 3),
        }

    figures = {
        "points": survey["points"],
        "copc_nodes": survey["nodes"],
        "tasks": tasks,
        "workers": args.workers,
        "wall_s": {k: round(v, 2) for k, v in best.items()},
        "cpu_s": {k: round(v, 2) for k, v in best_cpu.items()},
        "wall_ratios": ratios(best),
        "cpu_ratios": ratios(best_cpu),
    }
    print(f"best of {args.repeat} (tasks: {tasks}):")
    for k in VARIANTS:
        print(f"  {k:<12} {best[k]:6.2f} s wall  {best_cpu[k]:6.2f} s CPU")
    print(f"  wall ratios: {figures['wall_ratios']}")
    print(f"  CPU ratios:  {figures['cpu_ratios']}")
    return figures


if __name__ == "__main__":
    main()
