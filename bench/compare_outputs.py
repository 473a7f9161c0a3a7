"""Snapshot holefill's outputs on the demo and on every real file, and compare two snapshots.

A restructure must not change what users get. ``snapshot`` runs the pipeline with
default settings (plus the CRS a file lacks) on the demo survey and on every file of
../shared/data, one output folder each; ``compare`` then checks, for two snapshots
taken before and after a change:

- every raster tile (``dsm/*.tif``, and the fill's ``fill_mask/*.tif``,
  ``fill_distance/*.tif``, ``dsm_unfilled/*.tif`` where a run writes them) is byte-identical
  (and, if not, by how much the pixel values differ);
- every layer of ``holes.gpkg`` and ``flightplan.gpkg`` has the same features with the same
  values in every column it had before (columns added since are reported by name, not compared).

The comparison is of a restructure, so take both snapshots with the same settings
(``--set fill.enabled=false`` compares the unfilled DSM).

Usage::

    python bench/compare_outputs.py snapshot DIR [--only NAME ...] [--set section.key=value ...]
    python bench/compare_outputs.py compare BEFORE AFTER

Exit status 0 when every output matches, 1 otherwise.
"""

from __future__ import annotations

import argparse
import hashlib
import math
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"

#: CRS for the real files that carry none (from PROVENANCE.md).
MISSING_CRS = {
    "ahn3_delft_1.laz": "EPSG:28992",
    "ahn_amsterdam_2386_9702.laz": "EPSG:28992",
    "ign_stbarth_nocrs.laz": "EPSG:5490",
    "pdal_warsaw_small.las": "EPSG:2180",
    "pdal_sample_c_nocrs.las": "EPSG:32633",
}


def snapshot(out_root: Path, only: list[str], settings: list[str]) -> None:
    from distributed import Client, LocalCluster

    from pipeline.config import load_config
    from pipeline.run import run_survey
    from pipeline.synth import generate_survey, preset, write_truth

    out_root.mkdir(parents=True, exist_ok=True)
    jobs: list[tuple[str, list[str], list[str], dict]] = []
    if not only or "demo" in only:
        survey_dir = out_root / "_demo_survey"
        synthetic = generate_survey(survey_dir / "tiles", preset("demo"))
        truth = write_truth(synthetic, survey_dir)
        jobs.append(("demo", [str(survey_dir / "tiles")], [], {"aoi": truth["survey_area"]}))
    for path in sorted(SHARED_DATA.glob("*.la[sz]")):
        if only and path.name not in only:
            continue
        overrides = [f'survey.crs="{MISSING_CRS[path.name]}"'] if path.name in MISSING_CRS else []
        jobs.append((path.name, [str(path)], overrides, {}))
    with (
        LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=":0", silence_logs=50) as cluster,
        Client(cluster) as client,
    ):
        for name, inputs, overrides, kwargs in jobs:
            started = time.perf_counter()
            config = load_config(overrides=[*overrides, *settings])
            try:
                run_survey(inputs, out_root / name, config, client=client, **kwargs)
                print(f"{name}: {time.perf_counter() - started:.1f} s", flush=True)
            except Exception as e:  # a snapshot records failures too: they must not change either
                (out_root / name).mkdir(parents=True, exist_ok=True)
                (out_root / name / "error.txt").write_text(f"{type(e).__name__}: {e}\n")
                print(f"{name}: {type(e).__name__}: {e}", flush=True)


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


#: The raster products whose tiles are compared (a folder of tiles each, where a run writes it).
RASTER_PRODUCTS = ("dsm", "fill_mask", "fill_distance", "dsm_unfilled")
#: The GeoPackages whose layers are compared.
GEOPACKAGES = ("holes.gpkg", "flightplan.gpkg")


def compare_rasters(before: Path, after: Path) -> list[str]:
    return [problem for product in RASTER_PRODUCTS for problem in _compare_tiles(before, after, product)]


def _compare_tiles(before: Path, after: Path, product: str) -> list[str]:
    import numpy as np
    import rasterio

    problems = []
    names_before = sorted(p.name for p in (before / product).glob("*.tif")) if (before / product).is_dir() else []
    names_after = sorted(p.name for p in (after / product).glob("*.tif")) if (after / product).is_dir() else []
    if names_before != names_after:
        return [f"{product} tiles differ: {len(names_before)} before, {len(names_after)} after"]
    for name in names_before:
        a, b = before / product / name, after / product / name
        if _digest(a) == _digest(b):
            continue
        with rasterio.open(a) as ra, rasterio.open(b) as rb:
            va, vb = ra.read(1, masked=True), rb.read(1, masked=True)
        if va.shape != vb.shape or (va.mask != vb.mask).any():
            problems.append(f"{product}/{name}: shape or nodata differs")
            continue
        diff = np.abs(va.filled(0).astype(np.float64) - vb.filled(0))
        problems.append(f"{product}/{name}: bytes differ (max pixel difference {diff.max():.6g})")
    return problems


def compare_layers(before: Path, after: Path) -> list[str]:
    return [problem for gpkg in GEOPACKAGES for problem in _compare_gpkg(before, after, gpkg)]


def _compare_gpkg(before: Path, after: Path, gpkg: str) -> list[str]:
    import pyogrio

    a, b = before / gpkg, after / gpkg
    if not a.exists() and not b.exists():
        return []
    if a.exists() != b.exists():
        return [f"{gpkg} exists on one side only"]
    layers_a = [name for name, _ in pyogrio.list_layers(a)]
    layers_b = [name for name, _ in pyogrio.list_layers(b)]
    if sorted(layers_a) != sorted(layers_b):
        return [f"{gpkg} layers differ: {layers_a} against {layers_b}"]
    problems = []
    for layer in layers_a:
        fa = pyogrio.read_dataframe(a, layer=layer)
        fb = pyogrio.read_dataframe(b, layer=layer)
        missing = [c for c in fa.columns if c not in fb.columns]
        if missing:
            problems.append(f"{gpkg}/{layer}: columns gone: {missing}")
            continue
        if len(fa) != len(fb):
            problems.append(f"{gpkg}/{layer}: {len(fa)} features before, {len(fb)} after")
            continue
        for column in fa.columns:
            if column == "geometry":
                same = fa.geometry.geom_equals_exact(fb.geometry, tolerance=0) | (
                    fa.geometry.isna() & fb.geometry.isna()
                )
                if not same.all():
                    problems.append(f"{gpkg}/{layer}: {int((~same).sum())} geometries differ")
                continue
            for i, (x, y) in enumerate(zip(fa[column].tolist(), fb[column].tolist())):
                if column == "path":  # inputs generated inside each snapshot: compare their names
                    x, y = Path(x).name, Path(y).name
                if not _same_value(x, y):
                    problems.append(f"{gpkg}/{layer}: row {i} column {column}: {x!r} against {y!r}")
                    break
    return problems


def _same_value(x, y) -> bool:
    if isinstance(x, float) and isinstance(y, float):
        return (math.isnan(x) and math.isnan(y)) or x == y
    return x == y or (x is None and y is None) or (x != x and y != y)


def compare(before_root: Path, after_root: Path) -> int:
    names = sorted({p.name for p in before_root.iterdir() if p.is_dir() and not p.name.startswith("_")})
    failures = 0
    for name in names:
        before, after = before_root / name, after_root / name
        if not after.is_dir():
            print(f"{name}: MISSING after")
            failures += 1
            continue
        error_a = (before / "error.txt").read_text() if (before / "error.txt").exists() else None
        error_b = (after / "error.txt").read_text() if (after / "error.txt").exists() else None
        problems = [] if error_a == error_b else [f"error before {error_a!r}, after {error_b!r}"]
        if error_a is None and error_b is None:
            problems += compare_rasters(before, after) + compare_layers(before, after)
        print(f"{name}: {'same' if not problems else 'DIFFERENT'}")
        for problem in problems[:10]:
            print(f"    {problem}")
        failures += bool(problems)
    print(f"{len(names) - failures} of {len(names)} outputs identical")
    return 1 if failures else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    snap = sub.add_parser("snapshot")
    snap.add_argument("out", type=Path)
    snap.add_argument("--only", nargs="*", default=[])
    snap.add_argument("--set", dest="settings", action="append", default=[], help="section.key=value (repeatable)")
    comp = sub.add_parser("compare")
    comp.add_argument("before", type=Path)
    comp.add_argument("after", type=Path)
    args = parser.parse_args()
    if args.command == "snapshot":
        snapshot(args.out, args.only, args.settings)
        return 0
    return compare(args.before, args.after)


if __name__ == "__main__":
    sys.exit(main())
