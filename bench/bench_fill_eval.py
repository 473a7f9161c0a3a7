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

ALTERNATIVE_COLUMNS = ("gdal_fillnodata", "nearest_alt", "tin_linear", "nni", "laplace", "grass_fillnulls")
#: The standard methods issue 16's target compares with (natural neighbours are not one of them).
STANDARD_METHODS = ("gdal_fillnodata", "nearest_alt", "tin_linear", "laplace", "grass_fillnulls")


def _median(values: list[float]) -> str:
    return f"{sorted(values)[len(values) // 2]:.2f}" if values else "-"


def markdown(paths: list[Path]) -> str:
    """RMSE tables per model from fill_eval.json reports, pooled again over the surveys of all of them."""
    surveys = _load_surveys(paths)
    lines = []
    for model in dict.fromkeys(s["model"] for s in surveys):
        rows = [s for s in surveys if s["model"] == model]
        done = [s for s in rows if not s["skipped"]]
        methods = list(dict.fromkeys(m for s in rows for m in s["methods"]))
        columns = methods + [a for a in ALTERNATIVE_COLUMNS if any(a in s["alternatives"] for s in rows)]
        lines += _survey_table(model, rows, columns)
        lines += [
            "",
            f"### {model.upper()}: pooled over {len(done)} surveys ({sum(s['n_holes'] for s in done)} holes)",
            "",
        ]
        lines += _pooled_table(done, columns) + _relief_table(done, columns) + _targets(done) + _hindsight(done)
    return "\n".join(lines)


def _load_surveys(paths: list[Path]) -> list[dict]:
    """The surveys of the reports, with their errors also in metres (``m``, ``rmse_m``)."""
    import json

    from pipeline.survey.scan import scan_survey

    surveys = []
    for path in paths:
        surveys += json.loads(path.read_text())["surveys"]
    for s in surveys:  # reports written before z_unit_m was recorded: read it from the headers
        if "z_unit_m" not in s:
            s["z_unit_m"] = scan_survey(s["inputs"], crs=MISSING_CRS.get(s["survey"], "")).vertical_unit_m
        factor = s["z_unit_m"]  # pooled errors are in metres
        for r in [*s["methods"].values(), *s["alternatives"].values()]:
            r["m"] = {k: r[k] * factor for k in ("rmse", "mae", "bias", "max_abs") if r.get(k) is not None}
        for h in s["holes"]:
            h["rmse_m"] = {k: v * factor for k, v in h["rmse"].items() if v is not None}
    return surveys


def _survey_table(model: str, rows: list[dict], columns: list[str]) -> list[str]:
    """RMSE per survey and method, the best alternative in bold, and the target ratios."""
    lines = [f"### {model.upper()}: RMSE per survey (z units), scored pixels", ""]
    lines.append(
        "| survey | px (m) | holes | scored px | "
        + " | ".join(columns)
        + " | default / best alt. | MLS / IDW | MLS / IDW, no cause |"
    )
    lines.append("|---" * (len(columns) + 7) + "|")
    for s in rows:
        if s["skipped"]:
            lines.append(f"| {s['survey']} | {s['resolution_m'] or '-'} | {s['n_holes']} | skipped: {s['skipped']} |")
            continue
        alternatives = [s["alternatives"][a]["rmse"] for a in columns if s["alternatives"].get(a, {}).get("rmse")]
        best = min(alternatives, default=None)
        values = []
        for c in columns:
            r = (s["methods"].get(c) or s["alternatives"].get(c) or {}).get("rmse")
            text = "-" if r is None else f"{r:.3f}"
            values.append(f"**{text}**" if r is not None and r == best else text)
        ratios = [s["default_vs_best_alternative"], s["mls_vs_idw"], s.get("mls_vs_idw_nocause")]
        lines.append(
            f"| {s['survey']} | {s['resolution_m']:g} | {s['n_holes']} | {s['scored_px']} | "
            + " | ".join(values + ["-" if r is None else f"{r:.2f}" for r in ratios])
            + " |"
        )
    return lines


def _pooled_table(done: list[dict], columns: list[str]) -> list[str]:
    """Errors per method pooled over the scored pixels of every survey, in metres."""
    import math

    lines = [
        "| method | RMSE (m) | MAE (m) | max (m) | bias (m) | scored px | unfilled px |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in columns:
        scores = [r for s in done if (r := s["methods"].get(name) or s["alternatives"].get(name)) and r.get("n_px")]
        n = sum(r["n_px"] for r in scores)
        if not n:
            continue
        rmse = math.sqrt(sum(r["m"]["rmse"] ** 2 * r["n_px"] for r in scores) / n)
        mae = sum(r["m"]["mae"] * r["n_px"] for r in scores) / n
        bias = sum(r["m"]["bias"] * r["n_px"] for r in scores) / n
        top = max(r["m"]["max_abs"] for r in scores)
        unfilled = sum(r["n_unfilled"] for r in scores)
        lines.append(f"| {name} | {rmse:.3f} | {mae:.3f} | {top:.2f} | {bias:+.3f} | {n} | {unfilled} |")
    return lines


def _relief_table(done: list[dict], columns: list[str]) -> list[str]:
    """RMSE pooled over holes by the relief of the reference under them."""
    import math

    lines = ["", "RMSE (m) pooled over holes by the relief (m) of the reference under them (max - min):", ""]
    lines.append("| relief | holes | px | " + " | ".join(columns) + " |")
    lines.append("|---" * (len(columns) + 3) + "|")
    for label, test in (("< 2.5", lambda r: r < 2.5), (">= 2.5", lambda r: r >= 2.5)):
        holes = [h for s in done for h in s["holes"] if h["relief"] is not None and test(h["relief"] * s["z_unit_m"])]
        cells = []
        for c in columns:
            scored = [(h["rmse_m"][c], h["n_px"]) for h in holes if c in h["rmse_m"]]
            n = sum(w for _, w in scored)
            cells.append(f"{math.sqrt(sum(r * r * w for r, w in scored) / n):.3f}" if n else "-")
        lines.append(f"| {label} | {len(holes)} | {sum(h['n_px'] for h in holes)} | " + " | ".join(cells) + " |")
    return lines


def hindsight_ratios(survey: dict) -> tuple[float, float, float] | None:
    """What choosing each hole's interpolator could reach at best, against the best standard method.

    Per hole, the method with the smallest error *on the truth* (hindsight, which no fill
    has): once among the standard methods, once among them, the default and natural
    neighbours. Returns ``(default, hindsight standard, hindsight all)`` as ratios of
    the survey's RMSE to that of its best single standard method, over the holes every
    method filled; None where no such hole is left or the best is exact.
    """
    import math

    rmse_of = {}
    best_standard = best_all = 0.0
    n = 0
    for hole in survey["holes"]:
        errors = hole["rmse"]
        standard = [m for m in STANDARD_METHODS if m in errors]
        if errors.get("default") is None or not standard or any(errors[m] is None for m in standard):
            continue
        anyone = [errors[m] for m in (*standard, "default", "nni") if errors.get(m) is not None]
        weight = hole["n_px"]
        for m in (*standard, "default"):
            rmse_of[m] = rmse_of.get(m, 0.0) + errors[m] ** 2 * weight
        best_standard += min(errors[m] for m in standard) ** 2 * weight
        best_all += min(anyone) ** 2 * weight
        n += weight
    if n == 0:
        return None
    best = min(v for m, v in rmse_of.items() if m != "default")
    if best == 0:
        return None
    return tuple(math.sqrt(v / best) for v in (rmse_of["default"], best_standard, best_all))  # type: ignore[return-value]


def _hindsight(done: list[dict]) -> list[str]:
    """How many surveys could reach 0.85 x the best standard method by choosing each hole's method with hindsight."""
    ratios = [r for s in done if (r := hindsight_ratios(s)) is not None]
    if not ratios:
        return []
    counts = [sum(r[k] <= 0.85 for r in ratios) for k in range(3)]
    medians = [_median([r[k] for r in ratios]) for k in range(3)]
    return [
        "Choosing each hole's method with hindsight (the smallest error on the truth), against the survey's "
        f"best single standard method ({len(ratios)} surveys): at or under 0.85 x with the default {counts[0]} "
        f"(median {medians[0]}), with the best standard method per hole {counts[1]} (median {medians[1]}), with "
        f"the best of those, the default and natural neighbours per hole {counts[2]} (median {medians[2]}).",
        "",
    ]


def _targets(done: list[dict]) -> list[str]:
    """The issue's targets counted over the surveys, and the default runs' stage times."""
    import math

    ratios = [s["default_vs_best_alternative"] for s in done if s["default_vs_best_alternative"] is not None]
    mls = [s["mls_vs_idw"] for s in done if s["mls_vs_idw"] is not None]
    nocause = [s["mls_vs_idw_nocause"] for s in done if s.get("mls_vs_idw_nocause") is not None]
    stages = [s["methods"]["default"].get("stage_seconds", {}) for s in done if "default" in s["methods"]]
    rasterize = sum(t.get("rasterize") or 0 for t in stages)
    fill = sum(t.get("fill") or 0 for t in stages)
    return [
        "",
        f"default RMSE <= 0.85 x best alternative's: {sum(r <= 0.85 for r in ratios)} of {len(ratios)} surveys "
        f"(median ratio {_median(ratios)}); MLS RMSE <= 0.5 x IDW's: "
        f"{sum(r <= 0.5 for r in mls)} of {len(mls)} (median {_median(mls)})"
        + (
            f", both by_cause = false: {sum(r <= 0.5 for r in nocause)} of {len(nocause)} (median {_median(nocause)}); "
            if nocause
            else "; "
        )
        + f"default runs: rasterize {rasterize:.1f} s, fill {fill:.1f} s in all (fill / rasterize {fill / rasterize if rasterize else math.nan:.2f})",
        "",
    ]


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
    from pipeline.evaluate.fill import BenchmarkPlan, evaluate_fill, format_table

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
        plan=BenchmarkPlan(
            n_holes=args.holes,
            seed=args.seed,
            models=("dsm", "dtm") if args.model == "both" else (args.model,),
            **({"methods": tuple(args.methods.split(","))} if args.methods else {}),
        ),
        crs=dict(MISSING_CRS),
        on_survey=progress,
    )
    table = format_table(benchmark)
    (args.out / "fill_eval.txt").write_text(table + "\n")
    print(table)
    print(f"{benchmark.seconds:.0f} s", file=sys.stderr)


if __name__ == "__main__":
    main()
