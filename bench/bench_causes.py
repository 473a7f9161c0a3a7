"""Hole causes per true cause on synthetic scenes: lakes, sloped rivers, a canal, missed strips.

Run: ``python bench/bench_causes.py [--scenes lakes,canal] [--seeds 0,1,2] [--json out.json]``.
Each scene of ``pipeline.synth.scenes.CAUSE_SCENES`` is generated per seed, its truth
written (``write_truth``), and the pipeline run on its tiles with the DEFAULT
configuration -- no AOI, no water polygons: the survey area comes from the tile grid,
the pixel size and the minimum hole area are "auto" -- exactly what ``holefill run
TILES --out OUT`` does, on one local cluster shared by the runs. The holes are scored
with ``pipeline.evaluate.truth.score_holes`` (a detected hole's true cause is the most common
truth cause of its pixels). Prints, per scene and pooled: holes, right/total and accuracy
per true cause, the confusion (true -> reported), the IoU of hole pixels, and every hole
whose cause is wrong with the rule that decided and its ring heights.
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
from dataclasses import dataclass, field

import numpy as np

from pipeline.config import load_config
from pipeline.evaluate.truth import CAUSE_NAMES, score_holes
from pipeline.io.raster import geometry_mask, read_raster
from pipeline.io.vector import read_layer
from pipeline.run import run_survey
from pipeline.synth import generate_survey, write_truth
from pipeline.synth.scenes import CAUSE_SCENES, cause_scene

#: Columns of the ``holes`` layer printed for a hole with a wrong cause.
EVIDENCE = (
    "area_m2",
    "cause_rule",
    "boundary_z_min",
    "boundary_z_max",
    "boundary_z_std",
    "boundary_jump_px",
    "boundary_px",
)


@dataclass
class Tally:
    """Scores of some runs, pooled."""

    runs: int = 0
    holes: int = 0
    intersection_px: float = 0.0
    union_px: float = 0.0
    confusion: dict[str, collections.Counter] = field(
        default_factory=lambda: collections.defaultdict(collections.Counter)
    )
    confusion_px: dict[str, collections.Counter] = field(
        default_factory=lambda: collections.defaultdict(collections.Counter)
    )

    def add(self, score) -> None:
        self.runs += 1
        self.holes += score.holes
        # IoU = I / (T + D - I), so I = IoU (T + D) / (1 + IoU)
        inter = score.iou * (score.true_hole_px + score.detected_px) / (1.0 + score.iou)
        self.intersection_px += inter
        self.union_px += score.true_hole_px + score.detected_px - inter
        for true, reported in score.confusion.items():
            self.confusion[true].update(reported)
        for true, reported in getattr(score, "confusion_px", {}).items():
            self.confusion_px[true].update(reported)

    def per_cause_px(self) -> dict[str, float]:
        """True cause -> the share of its detected hole pixels in holes given that cause (area-weighted)."""
        return {
            true: counts.get(true, 0) / total
            for true, counts in sorted(self.confusion_px.items())
            if (total := sum(counts.values()))
        }

    def per_cause(self) -> dict[str, tuple[int, int]]:
        """True cause -> (right, total) over the detected holes."""
        return {true: (counts.get(true, 0), sum(counts.values())) for true, counts in sorted(self.confusion.items())}

    def as_dict(self) -> dict:
        return {
            "runs": self.runs,
            "holes": self.holes,
            "iou": round(self.intersection_px / self.union_px, 4) if self.union_px else None,
            "per_cause": {
                true: {"right": right, "total": total, "accuracy": round(right / total, 4)}
                for true, (right, total) in self.per_cause().items()
            },
            "confusion": {true: dict(counts) for true, counts in sorted(self.confusion.items())},
            "per_cause_area": {true: round(share, 4) for true, share in self.per_cause_px().items()},
        }


def run_scene(name: str, seed: int, folder: pathlib.Path, client) -> dict:
    """Generate one scene, run the default pipeline on it and score its holes."""
    spec = cause_scene(name, seed)
    started = time.perf_counter()
    survey = generate_survey(folder / "tiles", spec)
    truth = write_truth(survey, folder)
    generated = time.perf_counter() - started
    out = folder / "out"
    run_survey([str(folder / "tiles")], out, load_config(), client=client)
    seconds = time.perf_counter() - started - generated
    manifest = json.loads((out / "manifest.json").read_text())
    min_area_m2 = manifest["holes"]["min_area_m2"]
    score = score_holes(
        out / "holes.gpkg", truth["hole_cause"], min_area_px=max(1, math.ceil(min_area_m2 / spec.resolution**2))
    )
    area = read_layer(out / "holes.gpkg", "survey_area")
    return {
        "scene": name,
        "seed": seed,
        "points": survey.n_points,
        "tiles": len(survey.tiles),
        "survey_area": str(area["source"].iloc[0]) if "source" in area.columns else None,
        "min_area_m2": round(min_area_m2, 2),
        "generate_s": round(generated, 2),
        "run_s": round(seconds, 2),
        "score": score,
        "wrong": wrong_holes(out / "holes.gpkg", truth["hole_cause"]),
    }


def wrong_holes(holes_gpkg: pathlib.Path, truth_path: pathlib.Path) -> list[dict]:
    """The holes whose reported cause is not their true cause, with the evidence the rules saw."""
    truth, transform, _ = read_raster(truth_path)
    truth = np.nan_to_num(truth, nan=0).astype(np.uint8)
    holes = read_layer(holes_gpkg, "holes")
    wrong = []
    for index in range(len(holes)):
        mask = geometry_mask(holes.geometry.iloc[index], transform, truth.shape)
        codes = truth[mask]
        codes = codes[codes > 0]
        true_cause = CAUSE_NAMES[int(np.bincount(codes).argmax())] if len(codes) else "none"
        if mask.any() and true_cause != holes["cause"].iloc[index]:
            record = {
                "hole_id": int(holes["hole_id"].iloc[index]),
                "true": true_cause,
                "cause": holes["cause"].iloc[index],
            }
            for column in EVIDENCE:
                if column in holes.columns:
                    value = holes[column].iloc[index]
                    record[column] = value if isinstance(value, str) else round(float(value), 2)
            wrong.append(record)
    return wrong


def format_tally(label: str, tally: Tally) -> str:
    causes = tally.per_cause()
    by_area = tally.per_cause_px()
    cells = [
        f"{true} {right}/{total} ({right / total:.0%}"
        + (f"; {by_area[true]:.1%} of its area)" if true in by_area else ")")
        for true, (right, total) in causes.items()
    ]
    iou = tally.intersection_px / tally.union_px if tally.union_px else float("nan")
    return f"{label:24s} {tally.runs:4d} {tally.holes:6d} {iou:6.3f}   " + ", ".join(cells)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", default=",".join(CAUSE_SCENES), help="comma-separated scene names")
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated seeds")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--work", type=pathlib.Path, help="keep the scenes and runs here (default: a temporary folder)")
    parser.add_argument("--json", type=pathlib.Path, help="write the results as JSON here")
    args = parser.parse_args(argv)
    scenes = [name.strip() for name in args.scenes.split(",") if name.strip()]
    unknown = sorted(set(scenes) - set(CAUSE_SCENES))
    if unknown:
        parser.error(f"unknown scene(s) {unknown}; choose from {sorted(CAUSE_SCENES)}")
    seeds = [int(seed) for seed in args.seeds.split(",")]

    from distributed import Client, LocalCluster

    results = []
    with (
        tempfile.TemporaryDirectory(prefix="bench_causes_") as scratch,
        LocalCluster(n_workers=args.workers, threads_per_worker=1, dashboard_address=":0", silence_logs=50) as cluster,
        Client(cluster) as client,
    ):
        work = args.work or pathlib.Path(scratch)
        for name in scenes:
            for seed in seeds:
                result = run_scene(name, seed, work / f"{name}-{seed}", client)
                score = result["score"]
                print(
                    f"{name:24s} seed {seed}: {score.holes:3d} holes, IoU {score.iou:.3f}, "
                    f"{result['points']:,} points, run {result['run_s']:.1f} s, area: {result['survey_area']}",
                    flush=True,
                )
                for hole in result["wrong"]:
                    print(f"    wrong: {hole}", flush=True)
                results.append(result)

    by_scene: dict[str, Tally] = collections.defaultdict(Tally)
    pooled = Tally()
    for result in results:
        by_scene[result["scene"]].add(result["score"])
        pooled.add(result["score"])
    print(f"\n{'scene':24s} {'runs':>4s} {'holes':>6s} {'IoU':>6s}   right/total per true cause (and by area)")
    for name in scenes:
        print(format_tally(name, by_scene[name]))
    print(format_tally("pooled", pooled))
    print("\nconfusion (true -> reported), pooled:")
    for true, counts in sorted(pooled.confusion.items()):
        print(f"  {true:16s} -> {dict(counts)}")

    if args.json:
        payload = {
            "seeds": seeds,
            "runs": [{**r, "score": r["score"].as_dict()} for r in results],
            "scenes": {name: by_scene[name].as_dict() for name in scenes},
            "pooled": pooled.as_dict(),
        }
        args.json.write_text(json.dumps(payload, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
