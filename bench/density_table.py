"""Every real survey with default settings: density, chosen pixel size, holes by cause, seconds.

Runs holefill with the default configuration (plus the CRS a file lacks,
``compare_outputs.MISSING_CRS``) on each file of ../shared/data, one at a time on
one local cluster, and prints a Markdown table (the one in docs/performance.md,
"Real surveys with default settings"). The density is the one the run sized its
pixels with: first returns per m² on the data footprint (the pre-pass of
``pipeline.survey.footprint_density``) where the headers' per-return counts add up, else
all points (marked *). A failed run is a row with its error.

Usage::

    python bench/density_table.py [--only NAME ...] [--out DIR] [--set section.key=value ...]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare_outputs import MISSING_CRS, SHARED_DATA

HEADER = (
    "| file | density (pts/m², footprint) | pixel (m) | cell (m) | holes | by cause | "
    "small voids + sampling gaps | min area (m²) | seconds |\n"
    "|---|---|---|---|---|---|---|---|---|"
)


def row(name: str, manifest: dict, seconds: float) -> str:
    sizing = manifest["grid"]["sizing"]
    density = sizing["density"]
    first = density["first_returns_per_m2"]
    shown = f"{first:.3g}" if first is not None else f"{density['points_per_m2']:.3g}*"
    holes = manifest["holes"]
    causes = ", ".join(f"{n} {cause}" for cause, n in holes["by_cause"].items() if n) or "–"
    return (
        f"| `{name}` | {shown} | {sizing['resolution_m']:g} | {sizing['cell_size_m']:g} | {holes['listed']} | "
        f"{causes} | {holes['small_voids']} ({holes['sampling_gaps']} thin) | {holes['min_area_m2']:.3g} | "
        f"{seconds:.1f} |"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--only", nargs="*", default=[])
    parser.add_argument("--out", type=Path, default=None, help="keep the outputs here (default: a temporary folder)")
    parser.add_argument("--set", dest="settings", action="append", default=[], help="section.key=value (repeatable)")
    args = parser.parse_args()

    from distributed import Client, LocalCluster

    from pipeline.config import load_config
    from pipeline.run import run_survey

    paths = [p for p in sorted(SHARED_DATA.glob("*.la[sz]")) if not args.only or p.name in args.only]
    with (
        tempfile.TemporaryDirectory() as scratch,
        LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=":0", silence_logs=50) as cluster,
        Client(cluster) as client,
    ):
        out_root = args.out or Path(scratch)
        print(HEADER, flush=True)
        for path in paths:
            overrides = [f'survey.crs="{MISSING_CRS[path.name]}"'] if path.name in MISSING_CRS else []
            config = load_config(overrides=[*overrides, *args.settings])
            started = time.perf_counter()
            try:
                run_survey([str(path)], out_root / path.name, config, client=client)
            except Exception as e:
                print(f"| `{path.name}` | error: {type(e).__name__}: {e} |||||||||", flush=True)
                continue
            manifest = json.loads((out_root / path.name / "manifest.json").read_text())
            print(row(path.name, manifest, time.perf_counter() - started), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
