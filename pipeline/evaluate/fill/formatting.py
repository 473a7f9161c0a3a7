"""The benchmark's outputs: ``fill_eval.json`` (strict JSON) and a plain-text table."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from .results import FillBenchmark, summarize


def write_json(path: str | os.PathLike, data: dict[str, Any]) -> Path:
    """Write a report as strict JSON (no NaN: missing values are null)."""
    import json

    path = Path(path)
    path.write_text(json.dumps(_no_nan(data), indent=1, allow_nan=False) + "\n")
    return path


def _no_nan(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _no_nan(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_no_nan(v) for v in value]
    if isinstance(value, np.generic):
        return _no_nan(value.item())
    return value


def format_table(benchmark: FillBenchmark) -> str:
    """A plain-text table: one row per survey, model and method (pipeline runs, then alternatives)."""
    lines = [
        f"{'model':5} {'survey':34} {'px':>4} {'holes':>5} {'method':16} {'RMSE':>8} {'MAE':>8} "
        f"{'max':>8} {'bias':>8} {'n px':>7} {'unfilled':>8}"
    ]

    def number(value: float) -> str:
        return f"{value:8.3f}" if math.isfinite(value) else f"{'-':>8}"

    for survey in benchmark.surveys:
        head = f"{survey.model:5} {survey.survey[:34]:34} {_fmt_res(survey.resolution_m):>4} {len(survey.holes):5d}"
        if survey.skipped:
            lines.append(f"{head} skipped: {survey.skipped}")
            continue
        for name, result in {**survey.methods, **survey.alternatives}.items():
            if result.skipped or result.errors is None:
                lines.append(f"{head} {name:16} skipped: {result.skipped}")
                continue
            e = result.errors
            lines.append(
                f"{head} {name:16} {number(e.rmse)} {number(e.mae)} {number(e.max_abs)} {number(e.bias)} "
                f"{e.n_px:7d} {e.n_unfilled:8d}"
            )
    summary = summarize(benchmark)
    for model, s in summary.items():
        lines.append("")
        lines.append(f"{model}: {s['surveys']} surveys, {s['holes']} holes, {s['cut_px']} px (pooled over surveys)")
        for name, stats in s["pooled"].items():
            lines.append(
                f"  {name:16} RMSE {stats['rmse']}  MAE {stats['mae']}  max {stats['max_abs']}  "
                f"bias {stats['bias']}  n {stats['n_px']}  unfilled {stats['n_unfilled']}"
            )
        t = s["target_default_vs_best_alternative"]
        lines.append(f"  default RMSE <= 0.85 x best alternative's: {t['met']} of {t['of']} surveys")
        t = s["target_mls_vs_idw"]
        lines.append(f"  MLS RMSE <= 0.5 x IDW's: {t['met']} of {t['of']} surveys")
        t = s["target_mls_vs_idw_nocause"]
        lines.append(f"  the same, both by_cause = false: {t['met']} of {t['of']} surveys")
        d = s["default_run_seconds"]
        lines.append(
            f"  default run: rasterize {d['rasterize']} s, fill {d['fill']} s (ratio {d['fill_over_rasterize']})"
        )
    return "\n".join(lines)


def _fmt_res(resolution: float) -> str:
    return f"{resolution:g}" if math.isfinite(resolution) else "-"
