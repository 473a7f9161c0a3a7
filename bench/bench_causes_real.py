"""Hole causes on the real surveys, scored per cause against evidence the rules do not see.

Runs holefill with default settings (plus the CRS a file lacks,
``compare_outputs.MISSING_CRS``) on each file of ../shared/data and labels every
listed hole with an independent truth (``pipeline.evaluate.causes``: the
producer's water-class points beside the hole, reference lake polygons, building
points standing above the ring). Each file with water-class points is run a
second time with that evidence withheld: a copy of the file with class 9
relabelled 1 (unclassified), so the DSM is the same and the rules lose the
water-class evidence; the rim rules (``level_rim``, ``flat_low_rim``) are then
scored against a truth they never saw. The holes may differ a little (a warning
says so): the water returns also set the first surface that bounds a swath at a
lake's edge (``sensor.sight.surface_tops``), and a hole whose cause changes may
join a missed strip or stop joining it (``holes.strip_joins``). The copies live
in the output folder (a temporary one by default), never in the repository.

Printed: per file and pooled over the water files and over the others, for both
runs: holes, right/total per truth cause, water precision and recall, and every
hole that is wrong or unverified with its evidence. ``--json FILE`` writes it all.

Usage::

    python bench/bench_causes_real.py [--only NAME ...] [--out DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare_outputs import MISSING_CRS, SHARED_DATA

#: The files whose PROVENANCE.md names water, and where the truth of their water comes from:
#: "points" (their water-class points), "polygons" (REFERENCE_WATER) or None (no evidence:
#: autzen_trim has no class 9; the IGN hydro-flattened DSM of the bridge tiles is not flattened
#: and has nodata at the holes, docs/performance.md). Every other file has no water.
WATER_FILES: dict[str, str | None] = {
    "lidr_topography.laz": "points",
    "lidr_megaplot.laz": "polygons",
    "wires_quebec.laz": "points",
    "ahn3_delft_1.laz": "points",
    "autzen_trim.laz": None,
    "ign_crop2_water.laz": "points",
    "ign_corse_water.laz": "points",
    "ign_pont_bridge.laz": "points",
    "ign_bridge_0299_6802.laz": None,
    "ign_bridge_0300_6802.laz": None,
}
REFERENCE_WATER = {"lidr_megaplot.laz": SHARED_DATA / "reference" / "lidr_megaplot_lake_polygons_UTM17.shp"}
RUNS = ("default", "withheld")


def relabel_water(source: Path, target: Path) -> int:
    """Copy a LAS/LAZ file with its water-class points relabelled unclassified; how many were."""
    import laspy
    import numpy as np

    las = laspy.read(source)
    water = np.asarray(las.classification) == 9
    if not water.any():
        return 0
    classes = np.asarray(las.classification).copy()
    classes[water] = 1
    las.classification = classes
    target.parent.mkdir(parents=True, exist_ok=True)
    las.write(target)
    return int(water.sum())


def label_run(name: str, run_dir: Path) -> list:
    """The labelled holes of one finished run of the file ``name``."""
    from pyproj import CRS

    from pipeline.evaluate.causes import label_holes
    from pipeline.io.raster import read_raster
    from pipeline.io.vector import read_survey_area

    polygons = None
    if name in REFERENCE_WATER:
        _, _, wkt = read_raster(run_dir / "dsm.vrt")
        polygons = read_survey_area(REFERENCE_WATER[name], CRS.from_wkt(wkt), what="water")
    known = name not in WATER_FILES or WATER_FILES[name] is not None
    return label_holes(run_dir, SHARED_DATA / name, water_polygons=polygons, water_known=known)


def score_line(label: str, holes: list) -> str:
    from pipeline.evaluate.causes import TRUTH_CAUSES, score_holes

    score = score_holes(holes)
    per_cause = ", ".join(f"{c} {score.right[c]}/{score.total[c]}" for c in TRUTH_CAUSES if score.total[c])
    unverified = sum(h.truth == "unverified" for h in holes)
    return (
        f"{label}: {len(holes)} holes; right per truth cause: {per_cause or '-'}; "
        f"water precision {score.water_precision:.2f} recall {score.water_recall:.2f} "
        f"(tp {score.water_tp}, fp {score.water_fp}, fn {score.water_fn}); unverified {unverified}"
    )


def hole_line(hole) -> str:
    from pipeline.evaluate.causes import is_right

    verdict = "unverified" if hole.truth == "unverified" else ("right" if is_right(hole) else "WRONG")
    return (
        f"    hole {hole.hole_id}: {hole.area_m2:.0f} m2 at ({hole.centroid[0]:.1f}, {hole.centroid[1]:.1f}) "
        f"reported {hole.cause}/{hole.rule}, truth {hole.truth} ({verdict}; edge near class 9 "
        f"{hole.water_edge_share:.2f}, lake {hole.lake_share:.2f}, buildings {hole.building_share:.2f})"
    )


def run_all(paths: list[Path], out_root: Path) -> dict[str, dict[str, list]]:
    """Both runs of every file (the withheld run only where the file has water-class points)."""
    from distributed import Client, LocalCluster

    from pipeline.config import load_config
    from pipeline.run import run_survey

    labelled: dict[str, dict[str, list]] = {}
    with (
        LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=":0", silence_logs=50) as cluster,
        Client(cluster) as client,
    ):
        for path in paths:
            overrides = [f'survey.crs="{MISSING_CRS[path.name]}"'] if path.name in MISSING_CRS else []
            config = load_config(overrides=overrides)
            started = time.perf_counter()
            labelled[path.name] = {}
            try:
                run_survey([str(path)], out_root / "default" / path.name, config, client=client)
                labelled[path.name]["default"] = label_run(path.name, out_root / "default" / path.name)
                copy = out_root / "relabelled" / path.name
                if relabel_water(path, copy):
                    run_survey([str(copy)], out_root / "withheld" / path.name, config, client=client)
                    labelled[path.name]["withheld"] = label_run(path.name, out_root / "withheld" / path.name)
                    _check_same_holes(path.name, labelled[path.name])
                else:  # nothing withheld: the same input, the same run
                    labelled[path.name]["withheld"] = labelled[path.name]["default"]
            except Exception as e:
                print(f"{path.name}: error: {type(e).__name__}: {e}", flush=True)
                continue
            print(f"{path.name}: {time.perf_counter() - started:.1f} s", flush=True)
    return labelled


def _check_same_holes(name: str, runs: dict[str, list]) -> None:
    """Relabelling a class changes no height: both runs must list the same holes."""
    shapes = [sorted((h.hole_id, round(h.area_m2, 3)) for h in runs[run]) for run in RUNS]
    if shapes[0] != shapes[1]:
        print(f"{name}: WARNING: the runs list different holes ({len(shapes[0])} and {len(shapes[1])})", flush=True)


def report(labelled: dict[str, dict[str, list]]) -> dict:
    """Print the per-file and pooled scores; return them for --json."""
    from pipeline.evaluate.causes import is_right

    result: dict = {"files": {}, "pooled": {}}
    for run in RUNS:
        print(f"\n## run: {run}" + (" (class 9 relabelled 1)" if run == "withheld" else ""))
        pooled: dict[str, list] = {"water files": [], "other files": []}
        for name, runs in labelled.items():
            holes = runs.get(run, [])
            group = "water files" if name in WATER_FILES else "other files"
            pooled[group] += holes
            print(score_line(name, holes))
            for hole in holes:
                if hole.truth == "unverified" or not is_right(hole):
                    print(hole_line(hole))
            result["files"].setdefault(name, {})[run] = [dataclasses.asdict(h) for h in holes]
        for group, holes in pooled.items():
            print(score_line(f"pooled, {group}", holes))
            result["pooled"].setdefault(group, {})[run] = _score_dict(holes)
    return result


def _score_dict(holes: list) -> dict:
    from pipeline.evaluate.causes import score_holes

    score = score_holes(holes)
    return {
        "holes": len(holes),
        "right": score.right,
        "total": score.total,
        "unverified": sum(h.truth == "unverified" for h in holes),
        "water_precision": score.water_precision,
        "water_recall": score.water_recall,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--only", nargs="*", default=[])
    parser.add_argument("--out", type=Path, default=None, help="keep the runs here (default: a temporary folder)")
    parser.add_argument("--json", type=Path, default=None, help="write the labelled holes and scores here")
    args = parser.parse_args()
    paths = [p for p in sorted(SHARED_DATA.glob("*.la[sz]")) if not args.only or p.name in args.only]
    with tempfile.TemporaryDirectory() as scratch:
        labelled = run_all(paths, args.out or Path(scratch))
    result = report(labelled)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
