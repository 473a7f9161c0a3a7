"""The fill benchmark on every real survey of ../shared/data, DSM and DTM.

    .venv/bin/python bench/bench_fill_eval.py OUT [--holes 20] [--seed 0] [--model both] [--only NAME ...] [--methods default,mls,...]

Same as ``holefill evaluate --fill FILE... --out OUT --model both`` with the CRS
that some files lack (``MISSING_CRS`` of compare_outputs.py) and one local Dask
cluster of two workers. Prints the table and writes OUT/fill_eval.json and
OUT/fill_eval.txt; the figures go to docs/performance.md. No assertions.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from compare_outputs import MISSING_CRS, SHARED_DATA


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path)
    parser.add_argument("--holes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--model", choices=["dsm", "dtm", "both"], default="both")
    parser.add_argument("--only", nargs="*", default=[])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--methods", default="", help="pipeline runs, comma-separated (default: all)")
    args = parser.parse_args()

    from pipeline.config import load_config
    from pipeline.evaluate_fill import evaluate_fill, format_table

    files = [p for p in sorted(SHARED_DATA.glob("*.la[sz]")) if not args.only or p.name in args.only]
    if not files:
        sys.exit(f"no survey found in {SHARED_DATA}")
    config = load_config(overrides=[f"dask.workers={args.workers}"])

    def progress(result) -> None:
        state = f"skipped: {result.skipped}" if result.skipped else f"{len(result.holes)} holes, {result.cut_px} px"
        print(f"{result.model} {result.survey} ({result.resolution_m:g} m): {state}", file=sys.stderr, flush=True)

    benchmark = evaluate_fill(
        [[str(p)] for p in files],
        args.out,
        config,
        n_holes=args.holes,
        seed=args.seed,
        models=("dsm", "dtm") if args.model == "both" else (args.model,),
        crs=dict(MISSING_CRS),
        **({"methods": tuple(args.methods.split(","))} if args.methods else {}),
        on_survey=progress,
    )
    table = format_table(benchmark)
    (args.out / "fill_eval.txt").write_text(table + "\n")
    print(table)
    print(f"{benchmark.seconds:.0f} s", file=sys.stderr)


if __name__ == "__main__":
    main()
