"""The fill benchmark on every real survey of ../shared/data, DSM and DTM.

    .venv/bin/python bench/bench_fill_eval.py OUT [--holes 20] [--seed 0] [--model both] [--only NAME ...] [--methods default,mls,...]
    .venv/bin/python bench/bench_fill_eval.py --markdown OUT/fill_eval.json [MORE.json ...]

Same as ``holefill evaluate --fill FILE... --out OUT --model both`` with the CRS
that some files lack (``MISSING_CRS`` of compare_outputs.py) and one local Dask
cluster of two workers. Prints the table and writes OUT/fill_eval.json and
OUT/fill_eval.txt; ``--markdown`` turns reports into the tables of
docs/performance.md (RMSE per survey and method, pooled errors, targets). No assertions.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from compare_outputs import MISSING_CRS, SHARED_DATA

ALTERNATIVE_COLUMNS = ("gdal_fillnodata", "tin_linear", "nni", "laplace")


def markdown(paths: list[Path]) -> str:
    """RMSE tables per model from fill_eval.json reports (surveys of several reports together)."""
    import json

    surveys, summaries = [], {}
    for path in paths:
        report = json.loads(path.read_text())
        surveys += report["surveys"]
        summaries.update(report["summary"])
    lines = []
    for model in dict.fromkeys(s["model"] for s in surveys):
        rows = [s for s in surveys if s["model"] == model]
        methods = list(dict.fromkeys(m for s in rows for m in s["methods"]))
        columns = methods + [a for a in ALTERNATIVE_COLUMNS if any(a in s["alternatives"] for s in rows)]
        lines += [f"### {model.upper()}: RMSE per survey (z units), scored pixels", ""]
        lines.append(
            "| survey | px (m) | holes | scored px | " + " | ".join(columns) + " | default / best alt. | MLS / IDW |"
        )
        lines.append("|---" * (len(columns) + 6) + "|")
        for s in rows:
            if s["skipped"]:
                lines.append(
                    f"| {s['survey']} | {s['resolution_m'] or '-'} | {s['n_holes']} | skipped: {s['skipped']} |"
                )
                continue
            values = []
            best = min(
                (
                    s["alternatives"][a]["rmse"]
                    for a in columns
                    if a in s["alternatives"] and s["alternatives"][a].get("rmse") is not None
                ),
                default=None,
            )
            for c in columns:
                r = (s["methods"].get(c) or s["alternatives"].get(c) or {}).get("rmse")
                text = "-" if r is None else f"{r:.3f}"
                values.append(f"**{text}**" if r is not None and r == best else text)
            ratio = s["default_vs_best_alternative"]
            mls = s["mls_vs_idw"]
            lines.append(
                f"| {s['survey']} | {s['resolution_m']:g} | {s['n_holes']} | {s['scored_px']} | "
                + " | ".join(values)
                + f" | {'-' if ratio is None else f'{ratio:.2f}'} | {'-' if mls is None else f'{mls:.2f}'} |"
            )
        summary = summaries[model]
        lines += ["", f"### {model.upper()}: pooled over {summary['surveys']} surveys ({summary['holes']} holes)", ""]
        lines.append("| method | RMSE | MAE | max | bias | scored px | unfilled px |")
        lines.append("|---|---|---|---|---|---|---|")
        for name, e in summary["pooled"].items():
            lines.append(
                f"| {name} | {e['rmse']} | {e['mae']} | {e['max_abs']} | {e['bias']} | {e['n_px']} | {e['n_unfilled']} |"
            )
        t, m, d = (
            summary["target_default_vs_best_alternative"],
            summary["target_mls_vs_idw"],
            summary["default_run_seconds"],
        )
        lines += [
            "",
            f"default RMSE <= 0.85 x best alternative's: {t['met']} of {t['of']} surveys; "
            f"MLS RMSE <= 0.5 x IDW's: {m['met']} of {m['of']}; default runs: rasterize {d['rasterize']} s, "
            f"fill {d['fill']} s in all (fill / rasterize {d['fill_over_rasterize']})",
            "",
        ]
    return "\n".join(lines)


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--markdown":
        print(markdown([Path(p) for p in sys.argv[2:]]))
        return
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
