"""The benchmark driver: the tool that runs the pipeline on surveys and their cut copies.

:func:`evaluate_fill` reads and writes files and runs the pipeline (through
:func:`pipeline.run.run_survey`); per survey and model, :func:`_evaluate_survey` goes
through named steps: scan, reference run, cut, pipeline runs per fill method,
alternatives, scoring.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ...cluster import dask_client
from ...config import AUTO, Config
from ...errors import ConfigError, HolefillError
from .alternatives import ALTERNATIVES, AlternativeUnavailable, _hole_windows
from .cutting import _write_cut_holes, align, cut_points
from .formatting import write_json
from .metrics import fill_errors
from .placement import choose_resolution, place_holes
from .results import FillBenchmark, MethodResult, SurveyResult

logger = logging.getLogger("pipeline.evaluate_fill")  # the name it logged under as one module

#: Pipeline runs on the cut survey: name -> ``[fill]`` overrides. ``default`` is the
#: default configuration (``auto``, filled by cause); the others change one thing.
PIPELINE_RUNS: dict[str, dict[str, Any]] = {
    "default": {},
    "auto-nocause": {"by_cause": False},
    "tin": {"method": "tin"},
    "mls": {"method": "mls"},
    "idw": {"method": "idw"},
    "nearest": {"method": "nearest"},
    # auto's contest among the methods bounded by their rim only (no MLS, no spline: they extrapolate)
    "auto-bounded": {"auto_candidates": ["tin", "linear"]},
    # the interpolators alone, every hole filled as ground would be (no flat water, no lower side)
    "mls-nocause": {"method": "mls", "by_cause": False},
    "idw-nocause": {"method": "idw", "by_cause": False},
}

#: Surface models: name -> ``[filter]`` overrides.
MODELS: dict[str, dict[str, Any]] = {"dsm": {}, "dtm": {"keep_classes": [2]}}


def placement_rng(seed: int, survey: str, model: str) -> np.random.Generator:
    """The generator of one survey's holes in one model: from the seed, the survey's name and the
    model's place in :data:`MODELS` (not in the run's list), so a survey gets the same holes in any
    company (before 2026-11-27 a DTM run alone drew the DSM's holes: the list's index was 0)."""
    return np.random.default_rng([seed, zlib.crc32(survey.encode()), list(MODELS).index(model)])


@dataclass(frozen=True)
class BenchmarkPlan:
    """What every survey of one benchmark runs with (the options of :func:`evaluate_fill`).

    Attributes
    ----------
    n_holes, seed : int
        Holes per survey and model, and the seed they are drawn from (with the
        survey's name and the model, so a survey gets the same holes in any company).
    models : tuple of {"dsm", "dtm"}
    methods : tuple of str
        Keys of :data:`PIPELINE_RUNS`; ``default`` is always run (first).
    alternatives : tuple of str
        Keys of :data:`ALTERNATIVES`.
    resolution_m : float, optional
        Pixel size for every survey; default: :func:`choose_resolution` per survey.
    margin_px : int
        Measured pixels a hole keeps around it (:func:`place_holes`).
    size_range_m : (float, float)
        The holes' smallest and largest size across, in metres.
    """

    n_holes: int = 20
    seed: int = 0
    models: tuple[str, ...] = ("dsm",)
    methods: tuple[str, ...] = tuple(PIPELINE_RUNS)
    alternatives: tuple[str, ...] = tuple(ALTERNATIVES)
    resolution_m: float | None = None
    margin_px: int = 4
    size_range_m: tuple[float, float] = (2.0, 50.0)

    def settings(self) -> dict[str, Any]:
        """The ``settings`` of ``fill_eval.json``."""
        return {
            "n_holes": self.n_holes,
            "seed": self.seed,
            "models": list(self.models),
            "methods": list(self.methods),
            "alternatives": list(self.alternatives),
            "resolution_m": self.resolution_m,
            "margin_px": self.margin_px,
            "size_range_m": list(self.size_range_m),
            "grass": shutil.which("grass") or None,
        }


def evaluate_fill(
    surveys: list[list[str]],
    out_dir: str | os.PathLike,
    config: Config,
    *,
    plan: BenchmarkPlan = BenchmarkPlan(),
    names: list[str] | None = None,
    crs: dict[str, str] | None = None,
    client: Any = None,
    scheduler: str | None = None,
    on_survey: Callable[[SurveyResult], None] | None = None,
) -> FillBenchmark:
    """Run the fill benchmark on surveys and write ``fill_eval.json`` into ``out_dir``.

    Parameters
    ----------
    surveys : list of list of str
        Each survey's inputs (files, folders or globs, as for ``holefill run``).
    out_dir : path-like
        Where the cut copies, the runs and ``fill_eval.json`` go; inputs are never modified.
    config : Config
        The base configuration; the benchmark overrides ``grid.resolution_m`` (when
        ``resolution_m`` is given or a survey is sparse), ``filter.keep_classes`` (DTM),
        ``fill.*`` per method, ``output.keep_unfilled`` and ``flightplan.enabled`` (off).
    plan : BenchmarkPlan
        The holes, models, methods and alternatives every survey runs with.
    names : list of str, optional
        A name per survey (default: the file or folder name).
    crs : dict, optional
        ``survey.crs`` per survey name (``"*"``: every survey) for files without one.
    client, scheduler
        A Dask client, or a scheduler address; default: one local cluster for all runs.
    on_survey : callable, optional
        Called with each :class:`SurveyResult` when it is done (progress).
    """
    _check_choices(plan.methods, plan.alternatives, plan.models, config)
    plan = replace(plan, methods=("default", *(m for m in plan.methods if m != "default")))
    names = names or [survey_name(inputs) for inputs in surveys]
    if len(set(names)) != len(names):
        raise ConfigError(f"survey names must be unique, got {names}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    benchmark = FillBenchmark(settings=plan.settings())
    base = config.replace("flightplan", source="fill benchmark", enabled=False)
    with dask_client(client, scheduler, base) as connect:
        runs_client = connect()
        for model in plan.models:
            for name, inputs in zip(names, surveys):
                rng = placement_rng(plan.seed, name, model)
                survey_config = _survey_config(base, model, (crs or {}).get(name) or (crs or {}).get("*"))
                result = _evaluate_survey(
                    name, inputs, out / model / name, survey_config, model=model, rng=rng, plan=plan, client=runs_client
                )
                benchmark.surveys.append(result)
                benchmark.seconds = time.perf_counter() - started
                # so far: a long benchmark can be read while it runs
                write_json(out / "fill_eval.json", benchmark.as_dict())
                if on_survey is not None:
                    on_survey(result)
    benchmark.seconds = time.perf_counter() - started
    write_json(out / "fill_eval.json", benchmark.as_dict())
    return benchmark


def _check_choices(
    methods: tuple[str, ...], alternatives: tuple[str, ...], models: tuple[str, ...], config: Config
) -> None:
    """Reject unknown methods, alternatives or models, and a target CRS (points are cut in their own)."""
    unknown = [m for m in methods if m not in PIPELINE_RUNS] + [a for a in alternatives if a not in ALTERNATIVES]
    unknown += [m for m in models if m not in MODELS]
    if unknown:
        raise ConfigError(
            f"unknown benchmark method or model {unknown}; methods: {list(PIPELINE_RUNS)}, "
            f"alternatives: {list(ALTERNATIVES)}, models: {list(MODELS)}"
        )
    if config.survey.target_crs:
        raise ConfigError("the fill benchmark cuts points in their own CRS: survey.target_crs must be empty")


def _survey_config(base: Config, model: str, survey_crs: str | None) -> Config:
    """The configuration of one survey and surface model: its ``--crs``, the model's ``[filter]``."""
    survey_config = base
    if survey_crs:
        survey_config = survey_config.replace("survey", source="--crs", crs=survey_crs)
    if MODELS[model]:
        survey_config = survey_config.replace("filter", source=f"model {model}", **MODELS[model])
    return survey_config


def survey_name(inputs: list[str]) -> str:
    """A survey's name: its file or folder name (the first one's, + the number of others)."""
    first = Path(inputs[0].rstrip("/"))
    return first.name if len(inputs) == 1 else f"{first.stem}+{len(inputs) - 1}"


def _evaluate_survey(
    name: str,
    inputs: list[str],
    folder: Path,
    config: Config,
    *,
    model: str,
    rng: np.random.Generator,
    plan: BenchmarkPlan,
    client: Any,
) -> SurveyResult:
    """One survey and model: each step records what it found in the result, or why the survey was skipped."""
    result = SurveyResult(survey=name, model=model, inputs=list(inputs))
    scanned = _scan(result, inputs, config, plan.resolution_m)
    if scanned is None:
        return result
    survey, config = scanned
    reference = _run_reference(result, inputs, folder, config, client)
    if reference is None:
        return result
    heights, transform, crs_wkt = reference
    cut = _cut_survey(result, survey, folder, config, heights, transform, crs_wkt, rng=rng, plan=plan)
    if cut is None:
        return result
    labels, cut_inputs = cut
    fills, unfilled = _run_methods(
        result, cut_inputs, folder, config, heights, transform, labels, methods=plan.methods, client=client
    )
    if unfilled is not None:
        _run_alternatives(result, fills, unfilled, labels, plan.alternatives)
    _score_all(result, fills, heights, labels)
    return result


def _scan(
    result: SurveyResult, inputs: list[str], config: Config, resolution_m: float | None
) -> tuple[Any, Config] | None:
    """The survey's tiles and the configuration on its pixel size (:func:`choose_resolution` unless given).

    None when the survey cannot be read.
    """
    from ...survey.scan import scan_survey

    try:
        survey = scan_survey(inputs, crs=config.survey.crs, on_error=config.survey.on_error)
    except HolefillError as e:
        result.skipped = f"cannot be read: {e}"
        return None
    result.z_unit_m = survey.vertical_unit_m
    if resolution_m is None:
        area = sum((t.bounds[2] - t.bounds[0]) * (t.bounds[3] - t.bounds[1]) for t in survey.tiles)
        area_m2 = area * survey.horizontal_unit_m**2
        resolution_m = choose_resolution(sum(t.header.point_count for t in survey.tiles), area_m2)
    result.resolution_m = resolution_m
    if resolution_m != config.grid.resolution_m:
        if config.grid.cell_size_m == AUTO:  # cells of so many pixels at any pixel size
            config = config.replace("grid", source="fill benchmark", resolution_m=resolution_m)
        else:  # the cell stays about as large, on the new lattice
            cell_px = max(16, round(float(config.grid.cell_size_m) / resolution_m))
            config = config.replace(
                "grid", source="fill benchmark", resolution_m=resolution_m, cell_size_m=cell_px * resolution_m
            )
    return survey, config


def _run_reference(
    result: SurveyResult, inputs: list[str], folder: Path, config: Config, client: Any
) -> tuple[np.ndarray, Any, str] | None:
    """Run the pipeline on the full survey without holes or fills; its raster, or None when it failed."""
    from ...io.raster import read_raster
    from ...run import run_survey

    reference_config = config.replace("holes", source="fill benchmark", enabled=False)
    try:
        run_survey(inputs, folder / "reference", reference_config, client=client)
    except HolefillError as e:
        result.skipped = f"reference run failed: {e}"
        return None
    if not (folder / "reference" / "dsm.vrt").exists():
        result.skipped = "the reference run wrote no raster (no point of the kept classes)"
        return None
    return read_raster(folder / "reference" / "dsm.vrt")


def _cut_survey(
    result: SurveyResult,
    survey: Any,
    folder: Path,
    config: Config,
    reference: np.ndarray,
    transform: Any,
    crs_wkt: str,
    *,
    rng: np.random.Generator,
    plan: BenchmarkPlan,
) -> tuple[np.ndarray, list[str]] | None:
    """Place the holes and write the cut copies of the inputs: the labels and the copies, or None if none fits."""
    resolution_m = result.resolution_m
    labels, holes = place_holes(
        reference,
        n_holes=plan.n_holes,
        rng=rng,
        pixel_size_m=resolution_m,
        min_size_m=plan.size_range_m[0],
        max_size_m=plan.size_range_m[1],
        margin_px=plan.margin_px,
        edge_px=math.ceil(2 * config.holes.footprint_block_m / resolution_m),
    )
    result.holes = holes
    if not holes:
        result.skipped = "no place is measured over a 2 m hole and its margin"
        return None
    _write_cut_holes(folder / "cut_holes.gpkg", labels, transform, crs_wkt, holes, resolution_m)
    cut_inputs = []
    for tile in survey.tiles:
        target = folder / "cut" / f"{tile.index:04d}_{tile.name}"
        result.points_removed += cut_points(tile.path, target, labels, transform)
        cut_inputs.append(str(target))
    return labels, cut_inputs


def _run_methods(
    result: SurveyResult,
    cut_inputs: list[str],
    folder: Path,
    config: Config,
    reference: np.ndarray,
    transform: Any,
    labels: np.ndarray,
    *,
    methods: tuple[str, ...],
    client: Any,
) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
    """Run the pipeline on the cut survey once per method: the filled rasters, and the default run's unfilled one."""
    from ...io.raster import read_raster
    from ...run import run_survey

    resolution_m = result.resolution_m
    deepest_m = max(h.max_distance_px for h in result.holes) * resolution_m
    fill_limits = {
        "max_distance_m": max(config.fill.max_distance_m, deepest_m + 2 * resolution_m),
        "max_area_m2": max(config.fill.max_area_m2, (max(h.n_px for h in result.holes) + 1) * resolution_m**2),
    }
    unfilled = None
    fills: dict[str, np.ndarray] = {}
    for method in methods:
        run_config = config.replace("fill", source=f"method {method}", **{**fill_limits, **PIPELINE_RUNS[method]})
        if method == "default":
            run_config = run_config.replace("output", source="fill benchmark", keep_unfilled=True)
        t0 = time.perf_counter()
        try:
            summary = run_survey(cut_inputs, folder / "runs" / method, run_config, client=client)
        except HolefillError as e:
            result.methods[method] = MethodResult(skipped=f"run failed: {e}")
            continue
        result.methods[method] = MethodResult(seconds=time.perf_counter() - t0, stage_seconds=summary.stage_seconds)
        filled, filled_transform, _ = read_raster(folder / "runs" / method / "dsm.vrt")
        fills[method] = align(filled, filled_transform, transform, reference.shape)
        if method == "default":
            unfilled = _check_cut(result, folder / "runs" / method, reference, transform, labels > 0)
    return fills, unfilled


def _check_cut(result: SurveyResult, run: Path, reference: np.ndarray, transform: Any, cut: np.ndarray) -> np.ndarray:
    """The default run's unfilled raster; records (and warns) where it differs from the reference but for the cut."""
    from ...io.raster import read_raster

    raw, raw_transform, _ = read_raster(run / "dsm_unfilled.vrt")
    unfilled = align(raw, raw_transform, transform, reference.shape)
    result.cut_check = {
        "cut_px_with_data": int(np.isfinite(unfilled[cut]).sum()),
        "other_px_changed": int(
            (~cut & (np.isfinite(reference) != np.isfinite(unfilled))).sum()
            + (~cut & np.isfinite(reference) & np.isfinite(unfilled) & (reference != unfilled)).sum()
        ),
    }
    if any(result.cut_check.values()):
        logger.warning(
            "%s (%s): the cut run differs from the reference: %s", result.survey, result.model, result.cut_check
        )
    return unfilled


def _run_alternatives(
    result: SurveyResult,
    fills: dict[str, np.ndarray],
    unfilled: np.ndarray,
    labels: np.ndarray,
    alternatives: tuple[str, ...],
) -> None:
    """Fill the holes of the unfilled raster with each alternative (into ``fills``); a missing one is skipped."""
    cut = labels > 0
    for alternative in alternatives:
        t0 = time.perf_counter()
        try:
            filled = ALTERNATIVES[alternative](unfilled, labels)
        except AlternativeUnavailable as e:
            result.alternatives[alternative] = MethodResult(skipped=str(e))
            continue
        result.alternatives[alternative] = MethodResult(seconds=time.perf_counter() - t0)
        fills[alternative] = np.where(cut, filled, np.nan)


def _score_all(result: SurveyResult, fills: dict[str, np.ndarray], reference: np.ndarray, labels: np.ndarray) -> None:
    """Score every method and alternative on the same pixels."""
    # every method is scored on the same pixels: those every method filled; what one left empty is counted apart
    common = (labels > 0) & np.isfinite(reference)
    for filled in fills.values():
        common &= np.isfinite(filled)
    result.common_px = int(common.sum())
    for name_, filled in fills.items():
        record = result.methods.get(name_) or result.alternatives[name_]
        _score(record, filled, reference, labels, common)


def _score(record: MethodResult, filled: np.ndarray, reference: np.ndarray, labels: np.ndarray, common: np.ndarray):
    """Errors of one method on the common pixels; its own empty removed pixels counted apart."""
    record.errors = fill_errors(filled, reference, common)
    record.errors.n_unfilled = int((labels > 0)[np.isfinite(reference) & ~np.isfinite(filled)].sum())
    for hole_id, box, _ in _hole_windows(labels):
        record.per_hole_rmse[hole_id] = fill_errors(
            filled[box], reference[box], common[box] & (labels[box] == hole_id)
        ).rmse
