"""Hole causes on lidar scans simulated over real terrain (``pipeline.simulate``).

Run: ``python bench/bench_sim_causes.py [--scans 30] [--terrains delft,bcts,topography]
[--seeds 0,1,2,...] [--json out.json] [--work folder] [--set KEY=VALUE ...] [--aoi]``.

Scan ``k`` flies over terrain ``k mod len(terrains)`` with the parameters drawn from seed
``seeds[k]`` (default ``k``): heading, lines with ids in arbitrary order, a dropped line
(usually), a crossing line (sometimes), single or multiple returns, scan angles or none,
density, field of view, height, dark patches (``random_scan_params``). The tiles (CRS
embedded) go through the DEFAULT pipeline, exactly as ``holefill run TILES --out OUT``
runs it -- no AOI, no water polygons, pixel size and minimum hole area "auto" -- on one
local cluster shared by the runs (with ``--aoi``, the scene's rectangle is given as the
planned area, ``holefill run --aoi``). The truth is then made at the run's pixel size
(``write_truth``), and the holes scored with ``pipeline.evaluate.truth.score_holes``. Prints,
per terrain and pooled: holes, right/total per true cause, the confusion (true ->
reported), the IoU of hole pixels, and every hole whose cause is wrong with the rule that
decided.
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import pathlib
import sys
import tempfile
import time

import pyproj
import shapely
from bench_causes import Tally, format_tally, wrong_holes

from pipeline.config import load_config
from pipeline.evaluate.truth import score_holes
from pipeline.io.vector import write_layer
from pipeline.run import run_survey
from pipeline.simulate import TERRAINS, Terrain, load_terrain, random_scan_params, simulate_scan, write_truth

DEFAULT_DATA = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "data"


def run_scan(
    terrain: Terrain, seed: int, folder: pathlib.Path, client, overrides: tuple[str, ...] = (), *, aoi: bool = False
) -> dict:
    """Simulate one scan, run the default pipeline on its tiles (``aoi``: the scene's rectangle as
    the planned area) and score its holes."""
    params = random_scan_params(seed, terrain)
    started = time.perf_counter()
    scan = simulate_scan(terrain, params, folder / "scan")
    simulated = time.perf_counter() - started
    out = folder / "out"
    planned = planned_area(terrain, folder / "planned_area.gpkg") if aoi else None
    run_survey([str(folder / "scan" / "tiles")], out, load_config(overrides=overrides), client=client, aoi=planned)
    seconds = time.perf_counter() - started - simulated
    manifest = json.loads((out / "manifest.json").read_text())
    resolution = float(manifest["grid"]["resolution"])
    min_area_m2 = float(manifest["holes"]["min_area_m2"])
    truth = write_truth(scan, resolution, folder / "truth_hole_cause.tif")
    score = score_holes(out / "holes.gpkg", truth, min_area_px=max(1, math.ceil(min_area_m2 / resolution**2)))
    return {
        "terrain": terrain.name,
        "seed": seed,
        "params": params.summary(),
        "points": scan.n_points,
        "tiles": len(scan.tiles),
        "resolution": resolution,
        "min_area_m2": round(min_area_m2, 2),
        "simulate_s": round(simulated, 2),
        "run_s": round(seconds, 2),
        "score": score,
        "wrong": wrong_holes(out / "holes.gpkg", truth),
    }


def planned_area(terrain: Terrain, path: pathlib.Path) -> pathlib.Path:
    """The scene's rectangle as a GeoPackage: the area the survey was planned to cover."""
    rows, cols = terrain.surface.shape
    box = shapely.box(
        terrain.x_min, terrain.y_min, terrain.x_min + cols * terrain.cell_m, terrain.y_min + rows * terrain.cell_m
    )
    return write_layer(path, "planned_area", [{"name": terrain.name}], [box], crs_wkt=pyproj.CRS(terrain.crs).to_wkt())


def print_summary(results: list[dict], terrains: list[str]) -> tuple[dict[str, Tally], Tally]:
    """The per-terrain and pooled tallies, printed."""
    by_terrain: dict[str, Tally] = collections.defaultdict(Tally)
    pooled = Tally()
    for result in results:
        by_terrain[result["terrain"]].add(result["score"])
        pooled.add(result["score"])
    print(f"\n{'terrain':24s} {'runs':>4s} {'holes':>6s} {'IoU':>6s}   right/total per true cause (and by area)")
    for name in terrains:
        print(format_tally(name, by_terrain[name]))
    print(format_tally("pooled", pooled))
    for label, tally in [*((name, by_terrain[name]) for name in terrains), ("pooled", pooled)]:
        print(f"\nconfusion (true -> reported), {label}:")
        for true, counts in sorted(tally.confusion.items()):
            print(f"  {true:16s} -> {dict(counts)}")
    rules: collections.Counter = collections.Counter()
    for result in results:
        rules.update((hole["true"], hole["cause"], hole.get("cause_rule", "?")) for hole in result["wrong"])
    print("\nwrong holes by (true, reported, rule), pooled:")
    for (true, cause, rule), count in rules.most_common():
        print(f"  {count:4d}  {true} -> {cause} by {rule}")
    return by_terrain, pooled


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scans", type=int, default=30, help="number of scans (terrains taken in turn)")
    parser.add_argument("--terrains", default="delft,bcts,topography", help=f"comma-separated, of {sorted(TERRAINS)}")
    parser.add_argument("--seeds", help="comma-separated seeds, one per scan (default 0, 1, ...)")
    parser.add_argument("--data", type=pathlib.Path, default=DEFAULT_DATA, help="the real files (../shared/data)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--work", type=pathlib.Path, help="keep the scans and runs here (default: a temporary folder)")
    parser.add_argument("--json", type=pathlib.Path, help="write the results as JSON here")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a setting for every run (as holefill run --set)",
    )
    parser.add_argument("--aoi", action="store_true", help="give the scene's rectangle as the planned area")
    args = parser.parse_args(argv)
    terrains = [name.strip() for name in args.terrains.split(",") if name.strip()]
    unknown = sorted(set(terrains) - set(TERRAINS))
    if unknown:
        parser.error(f"unknown terrain(s) {unknown}; choose from {sorted(TERRAINS)}")
    if not args.data.is_dir():
        parser.error(f"the real files are not at {args.data} (--data)")
    seeds = [int(s) for s in args.seeds.split(",")] if args.seeds else list(range(args.scans))
    if len(seeds) < args.scans:
        parser.error(f"{args.scans} scans need {args.scans} seeds, got {len(seeds)}")

    from distributed import Client, LocalCluster

    loaded = {name: load_terrain(name, args.data) for name in terrains}
    results = []
    with (
        tempfile.TemporaryDirectory(prefix="bench_sim_causes_") as scratch,
        LocalCluster(n_workers=args.workers, threads_per_worker=1, dashboard_address=":0", silence_logs=50) as cluster,
        Client(cluster) as client,
    ):
        work = args.work or pathlib.Path(scratch)
        for k in range(args.scans):
            name, seed = terrains[k % len(terrains)], seeds[k]
            result = run_scan(loaded[name], seed, work / f"{name}-{seed}", client, tuple(args.set), aoi=args.aoi)
            score = result["score"]
            print(
                f"{name:12s} {result['params']}\n{'':12s} -> {result['points']:,} points, {result['resolution']} m "
                f"pixels, {score.holes} holes, IoU {score.iou:.3f}, missed true holes {score.missed_true_holes}, "
                f"simulate {result['simulate_s']:.1f} s, run {result['run_s']:.1f} s",
                flush=True,
            )
            for hole in result["wrong"]:
                print(f"    wrong: {hole}", flush=True)
            results.append(result)
    by_terrain, pooled = print_summary(results, terrains)
    if args.json:
        payload = {
            "seeds": seeds[: args.scans],
            "runs": [{**r, "score": r["score"].as_dict()} for r in results],
            "terrains": {name: by_terrain[name].as_dict() for name in terrains},
            "pooled": pooled.as_dict(),
        }
        args.json.write_text(json.dumps(payload, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
