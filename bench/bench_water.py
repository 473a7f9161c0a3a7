"""Water levels of the fill on synthetic lakes and rivers with known water surfaces.

    PYTHONPATH=. .venv/bin/python bench/bench_water.py [--scenes lakes,river_fall_10] [--lake-m 300,500]

Each scene of :data:`pipeline.synth.scenes.CAUSE_SCENES` is generated, run through
``holefill run`` with the default configuration (in-process, one worker), and the DSM
on the water pixels that were voids is compared with the scene's true water surface:
the largest and RMS error, the steepest fall between neighbouring filled water pixels
(against ``causes.water_max_slope``), and the share of survey-area pixels that hold a
height. ``--lake-m`` adds a scene with one lake of that size (metres across). No
assertions: the figures go to docs/filling.md.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from pipeline.config import load_config
from pipeline.io.raster import read_raster
from pipeline.run import run_survey
from pipeline.synth import HoleCause, build_scene, generate_survey, write_truth
from pipeline.synth import draw as synth_draw
from pipeline.synth.scenes import cause_scene


def measure(spec, folder: Path) -> dict:
    survey = generate_survey(folder / "tiles", spec)
    truth = write_truth(survey, folder)
    config = load_config()
    run_survey([str(folder / "tiles")], folder / "out", config, aoi=truth["survey_area"])
    dsm, _, _ = read_raster(folder / "out" / "dsm.vrt")
    rows, cols = np.indices(dsm.shape)
    u, v = (cols + 0.5) * spec.resolution, spec.height_m - (rows + 0.5) * spec.resolution
    is_water, level = build_scene(spec).water_level(u, v)
    voids = (survey.hole_cause == HoleCause.WATER) & is_water
    filled = voids & np.isfinite(dsm)
    error = dsm[filled] - level[filled]
    steepest = 0.0
    for axis in (0, 1):
        both = np.diff(filled.astype(int), axis=axis) == 0
        both &= np.take(filled, range(filled.shape[axis] - 1), axis=axis)
        step = np.abs(np.diff(dsm, axis=axis))[both]
        steepest = max(steepest, float(step.max(initial=0.0)) / spec.resolution)
    return {
        "water_void_px": int(voids.sum()),
        "filled": float(filled.sum() / max(voids.sum(), 1)),
        "max_abs_m": float(np.abs(error).max(initial=0.0)),
        "rmse_m": float(np.sqrt(np.mean(error**2))) if len(error) else float("nan"),
        "steepest": steepest,
        "area_filled": float(np.isfinite(dsm).mean()),
        "max_slope": config.causes.water_max_slope,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="lakes,river_flat,river_fall_2,river_fall_5,river_fall_10")
    parser.add_argument("--lake-m", default="", help="sizes (m across) of single-lake scenes to add")
    args = parser.parse_args()
    specs = [(name, cause_scene(name)) for name in args.scenes.split(",") if name]
    for size in [float(s) for s in args.lake_m.split(",") if s]:
        side = size + 120.0
        specs.append((f"lake_{size:g}m", cause_scene("lakes").__class__(**{
            **cause_scene("lakes").__dict__, "width_m": side, "height_m": side, "lakes": 1,
            "building_density": 0.0, "tree_density": 5.0, "missed_line": None}), size))  # fmt: skip
    for item in specs:
        name, spec = item[0], item[1]
        if len(item) == 3:
            synth_draw.LAKE_SIZE_M = (item[2], item[2])
        with tempfile.TemporaryDirectory() as tmp:
            result = measure(spec, Path(tmp))
        print(name, " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in result.items()))


if __name__ == "__main__":
    main()
