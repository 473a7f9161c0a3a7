"""What the benchmark found: per method, per survey and overall (:func:`summarize`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from .metrics import ErrorStats, _finite
from .placement import CutHole


@dataclass
class MethodResult:
    """One method on one survey: errors, or why it did not run."""

    errors: ErrorStats | None = None
    skipped: str = ""
    seconds: float = math.nan
    stage_seconds: dict[str, float] = field(default_factory=dict)
    per_hole_rmse: dict[int, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = self.errors.as_dict() if self.errors else {}
        if self.skipped:
            out["skipped"] = self.skipped
        out["seconds"] = _finite(self.seconds)
        if self.stage_seconds:
            out["stage_seconds"] = {k: _finite(v) for k, v in self.stage_seconds.items()}
        return out


@dataclass
class SurveyResult:
    """One survey, one surface model."""

    survey: str
    model: str
    inputs: list[str]
    resolution_m: float = math.nan
    z_unit_m: float = 1.0  # metres per z unit: errors are in z units (feet on a survey in feet)
    skipped: str = ""
    holes: list[CutHole] = field(default_factory=list)
    points_removed: int = 0
    cut_check: dict[str, int] = field(default_factory=dict)
    common_px: int = 0  # removed pixels every method filled: the pixels scored
    methods: dict[str, MethodResult] = field(default_factory=dict)
    alternatives: dict[str, MethodResult] = field(default_factory=dict)

    @property
    def cut_px(self) -> int:
        return sum(h.n_px for h in self.holes)

    def best_alternative(self) -> tuple[str, float] | None:
        scored = [
            (name, r.errors.rmse)
            for name, r in self.alternatives.items()
            if r.errors and r.errors.n_px and not r.skipped
        ]
        return min(scored, key=lambda item: item[1]) if scored else None

    def rmse(self, name: str) -> float:
        result = self.methods.get(name) or self.alternatives.get(name)
        return result.errors.rmse if result and result.errors else math.nan

    def as_dict(self) -> dict[str, Any]:
        best = self.best_alternative()
        per_hole = []
        for hole in self.holes:
            record = hole.as_dict(self.resolution_m)
            record["rmse"] = {
                name: _finite(r.per_hole_rmse.get(hole.hole_id, math.nan))
                for name, r in {**self.methods, **self.alternatives}.items()
                if r.errors
            }
            per_hole.append(record)
        return {
            "survey": self.survey,
            "model": self.model,
            "inputs": self.inputs,
            "resolution_m": _finite(self.resolution_m),
            "z_unit_m": self.z_unit_m,
            "skipped": self.skipped or None,
            "n_holes": len(self.holes),
            "cut_px": self.cut_px,
            "scored_px": self.common_px,
            "points_removed": self.points_removed,
            "cut_check": self.cut_check,
            "methods": {k: v.as_dict() for k, v in self.methods.items()},
            "alternatives": {k: v.as_dict() for k, v in self.alternatives.items()},
            "best_alternative": best[0] if best else None,
            "default_vs_best_alternative": _finite(self.rmse("default") / best[1]) if best and best[1] else None,
            "mls_vs_idw": _finite(self.rmse("mls") / self.rmse("idw")) if self.rmse("idw") else None,
            "mls_vs_idw_nocause": _finite(self.rmse("mls-nocause") / self.rmse("idw-nocause"))
            if self.rmse("idw-nocause")
            else None,
            "holes": per_hole,
        }


@dataclass
class FillBenchmark:
    """Every survey and model of one benchmark, with the settings it ran with."""

    settings: dict[str, Any]
    surveys: list[SurveyResult] = field(default_factory=list)
    seconds: float = math.nan

    def as_dict(self) -> dict[str, Any]:
        return {
            "settings": self.settings,
            "seconds": _finite(self.seconds),
            "summary": summarize(self),
            "surveys": [s.as_dict() for s in self.surveys],
        }


def summarize(benchmark: FillBenchmark) -> dict[str, Any]:
    """Pooled errors per model and method, the targets, and the default run's stage times."""
    out: dict[str, Any] = {}
    for model in dict.fromkeys(s.model for s in benchmark.surveys):
        done = [s for s in benchmark.surveys if s.model == model and not s.skipped]
        pooled: dict[str, ErrorStats] = {}
        for survey in done:
            for name, result in {**survey.methods, **survey.alternatives}.items():
                if result.errors:
                    pooled[name] = pooled.get(name, ErrorStats()) + result.errors
        ratios = {s.survey: s.rmse("default") / best[1] for s in done if (best := s.best_alternative()) and best[1] > 0}
        mls_idw = {s.survey: s.rmse("mls") / s.rmse("idw") for s in done if s.rmse("idw") > 0}
        mls_idw_nocause = {
            s.survey: s.rmse("mls-nocause") / s.rmse("idw-nocause") for s in done if s.rmse("idw-nocause") > 0
        }
        rasterize = sum(
            s.methods["default"].stage_seconds.get("rasterize", 0.0) for s in done if "default" in s.methods
        )
        fill = sum(s.methods["default"].stage_seconds.get("fill", 0.0) for s in done if "default" in s.methods)
        out[model] = {
            "surveys": len(done),
            "skipped_surveys": {s.survey: s.skipped for s in benchmark.surveys if s.model == model and s.skipped},
            "holes": sum(len(s.holes) for s in done),
            "cut_px": sum(s.cut_px for s in done),
            "pooled": {name: stats.as_dict() for name, stats in pooled.items()},
            "target_default_vs_best_alternative": {
                "limit": 0.85,
                "met": sum(r <= 0.85 for r in ratios.values() if math.isfinite(r)),
                "of": sum(math.isfinite(r) for r in ratios.values()),
                "ratios": {k: _finite(v) for k, v in ratios.items()},
            },
            "target_mls_vs_idw": {
                "limit": 0.5,
                "met": sum(r <= 0.5 for r in mls_idw.values() if math.isfinite(r)),
                "of": sum(math.isfinite(r) for r in mls_idw.values()),
                "ratios": {k: _finite(v) for k, v in mls_idw.items()},
            },
            "target_mls_vs_idw_nocause": {
                "limit": 0.5,
                "met": sum(r <= 0.5 for r in mls_idw_nocause.values() if math.isfinite(r)),
                "of": sum(math.isfinite(r) for r in mls_idw_nocause.values()),
                "ratios": {k: _finite(v) for k, v in mls_idw_nocause.items()},
            },
            "default_run_seconds": {
                "rasterize": _finite(rasterize),
                "fill": _finite(fill),
                "fill_over_rasterize": _finite(fill / rasterize) if rasterize else None,
            },
        }
    return out
