"""One entry point, :func:`fill_region`, and the registry of fill methods."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import scipy.ndimage as ndi

from ._problem import Problem, build_problem, fit_plane, rim_pairs, rims_by_label
from .baselines import fill_flat, fill_idw, fill_nearest
from .laplace import fill_tin
from .mls import fill_mls
from .natural import fill_natural
from .scattered import fill_linear, fill_spline
from .settings import METHOD_CODES, NOT_FILLED, ComponentFill, FillOutcome, FillSettings

__all__ = ["FILL_METHODS", "choose_methods", "contest", "fill_region", "pick"]

Kernel = Callable[[Problem, np.ndarray, np.ndarray], list[ComponentFill]]

FILL_METHODS: dict[str, Kernel] = {
    "nearest": fill_nearest,
    "idw": fill_idw,
    "mls": fill_mls,
    "tin": fill_tin,
    "flat": fill_flat,
    "spline": fill_spline,
    "linear": fill_linear,
    "natural": fill_natural,
}
"""Every kernel has the signature ``kernel(problem, labels, out) -> list[ComponentFill]``:
it fills the components ``labels`` of ``problem`` into the float64 raster ``out``."""


def fill_region(
    heights: np.ndarray,
    region: np.ndarray,
    *,
    method: str = "auto",
    pixel_size: float = 1.0,
    settings: FillSettings | None = None,
    support: np.ndarray | None = None,
    barriers: np.ndarray | None = None,
    labels: np.ndarray | None = None,
) -> FillOutcome:
    """Fill every connected component of ``region`` from the measured pixels around it.

    Parameters
    ----------
    heights : ndarray of shape (M, N)
        Heights (any real dtype); NaN = unknown. Row 0 is north. Not modified.
    region : ndarray of bool, shape (M, N)
        Pixels to fill (True). Their input heights are ignored, even finite ones.
    method : {"auto", "tin", "spline", "mls", "linear", "natural", "idw", "nearest", "flat"}
        Fill method; ``auto`` chooses per component: by cross-validation on its own rim
        among ``settings.auto_candidates`` (:func:`contest`) for components of at least
        ``auto_contest_min_px`` pixels, :func:`choose_methods` for the others.
    pixel_size : float
        Pixel size in survey units (the MLS fit uses metric coordinates).
    settings : FillSettings, optional
        Method parameters; ``FillSettings()`` by default.
    support : ndarray of bool, optional
        Measured pixels allowed to serve as rim / support points (default: every
        finite pixel outside the region). Pass :func:`lower_side_support` to fill an
        occlusion hole from the ground only.
    barriers : ndarray of bool, optional
        Break lines (walls): never support, and the neighbourhood graph is cut there
        (components are split by them; ``tin`` has no edge across them; MLS/IDW
        neighbours are searched through support pixels only). Region pixels on a
        barrier are filled last with the highest adjacent height (code ``barrier``).
    labels : ndarray of int, optional
        Caller's component labels (> 0 on every region pixel). Default: 4-connected
        components of ``region`` minus ``barriers``.

    Returns
    -------
    FillOutcome
        Filled heights, per-pixel method codes, labels and one record per component.

    Raises
    ------
    ValueError
        Unknown method, arrays of different shapes, bad labels or pixel size.
    """
    settings = FillSettings() if settings is None else settings
    if method != "auto" and method not in FILL_METHODS:
        raise ValueError(f"unknown fill method {method!r}, must be one of {['auto', *FILL_METHODS]}")
    problem = build_problem(
        heights, region, pixel_size=pixel_size, settings=settings, support=support, barriers=barriers, labels=labels
    )
    chosen, scores = _choose(problem, method, settings)
    out = problem.heights.copy()
    records = _run(problem, chosen, out)
    records = {k: _with_scores(r, scores.get(k)) for k, r in records.items()}
    lut = np.zeros(problem.n_labels + 1, np.uint8)
    for rec in records.values():
        lut[rec.label] = METHOD_CODES[rec.method] if rec.filled else NOT_FILLED
    code = lut[problem.labels]
    if settings.estimate_error and records:
        records = _with_holdout_errors(problem, chosen, records, scores)
    region_b = np.asarray(region, bool)
    if barriers is not None:
        _fill_barrier_pixels(out, code, region_b & np.asarray(barriers, bool))
    bad = region_b & ~np.isfinite(out)
    out[bad] = np.nan
    code[bad] = NOT_FILLED
    dtype = heights.dtype if np.issubdtype(np.asarray(heights).dtype, np.floating) else np.float64
    return FillOutcome(
        heights=out.astype(dtype, copy=False),
        method_code=code,
        labels=problem.labels,
        components=tuple(records[k] for k in sorted(records)),
    )


def _choose(
    problem: Problem, method: str, settings: FillSettings
) -> tuple[dict[int, str], dict[int, dict[str, tuple[float, int]]]]:
    """A method per component label, and the rim cross-validation RMSE of each candidate where ``auto`` held a contest."""
    sizes = problem.sizes()
    present = np.nonzero(sizes[1:])[0] + 1
    if method != "auto":
        return {int(k): method for k in present}, {}
    chosen = choose_methods(problem.labels, present, settings)
    scores: dict[int, dict[str, tuple[float, int]]] = {}
    entrants = present[sizes[present] >= settings.auto_contest_min_px] if settings.auto_candidates else present[:0]
    rough = (
        set(rough_rims(problem, entrants, settings.auto_rough_rim).tolist())
        if "tin" in settings.auto_candidates
        else set()
    )
    tin_first = ("tin", *(m for m in settings.auto_candidates if m != "tin"))
    for k, by_method in _contest_errors(problem, entrants, settings.auto_candidates).items():
        if by_method:
            order = tin_first if k in rough else settings.auto_candidates
            chosen[k] = pick(by_method, order, settings.auto_z)
            scores[k] = {m: (v[0], len(v[1])) for m, v in by_method.items()}
    return chosen, scores


def rough_rims(problem: Problem, labels: np.ndarray, limit: float) -> np.ndarray:
    """The components among ``labels`` whose rim heights scatter about their least-squares plane
    by more than ``limit`` (RMS, z units): several surfaces side by side (``FillSettings.auto_rough_rim``)."""
    if len(labels) == 0 or not math.isfinite(limit):
        return np.zeros(0, np.int64)
    w = problem.labels.shape[1]
    rough = []
    for k, rim in rims_by_label(problem, np.asarray(labels, np.int64)).items():
        if len(rim) < 4:
            continue
        rows, cols = np.divmod(rim, w)
        z = problem.heights.ravel()[rim]
        a, b, c = fit_plane(rows, cols, z)
        if np.sqrt(np.mean((z - (a + b * cols + c * rows)) ** 2)) > limit:
            rough.append(k)
    return np.array(rough, np.int64)


def _with_holdout_errors(
    problem: Problem,
    chosen: dict[int, str],
    records: dict[int, ComponentFill],
    scores: dict[int, dict[str, tuple[float, int]]],
) -> dict[int, ComponentFill]:
    """Each record with its error estimate: the contest's winner keeps its cross-validation RMSE,
    the others get the leave-boundary-out RMSE (:func:`_holdout_errors`)."""
    others = {k: m for k, m in chosen.items() if not scores.get(k)}
    holdout = _holdout_errors(problem, others, records) if others else {}
    return {k: r if scores.get(k) else replace(r, error_estimate=holdout.get(k, math.nan)) for k, r in records.items()}


def _run(problem: Problem, chosen: dict[int, str], out: np.ndarray) -> dict[int, ComponentFill]:
    records: dict[int, ComponentFill] = {}
    for name, kernel in FILL_METHODS.items():
        labs = np.array(sorted(k for k, m in chosen.items() if m == name), np.int64)
        if len(labs):
            for rec in kernel(problem, labs, out):
                records[rec.label] = rec
    return records


def choose_methods(labels: np.ndarray, present: np.ndarray, settings: FillSettings) -> dict[int, str]:
    """The ``auto`` rule: a method per component label.

    ``tin`` (biharmonic fairing: exact for planes and quadratics, and the most accurate
    method on the benchmark for every hole size), except components of at least
    ``auto_mls_min_px`` pixels that are round (``auto_mls_min_roundness``), which use
    ``mls`` when that option is switched on (``auto_mls_min_px > 0``). Elongated holes
    (flight-line gaps, strips along walls) always use ``tin``: a moving quadratic fit
    across a strip is driven by one side at a time.
    """
    chosen = {int(k): "tin" for k in present}
    if settings.auto_mls_min_px <= 0:
        return chosen
    sizes = np.bincount(labels.ravel(), minlength=int(present.max(initial=0)) + 1)
    boxes = ndi.find_objects(labels)
    for k in present:
        k = int(k)
        if sizes[k] < settings.auto_mls_min_px:
            continue
        sl = boxes[k - 1]
        longest = max(sl[0].stop - sl[0].start, sl[1].stop - sl[1].start)
        if sizes[k] / (np.pi / 4 * longest**2) >= settings.auto_mls_min_roundness:
            chosen[k] = "mls"
    return chosen


def _fill_barrier_pixels(out: np.ndarray, code: np.ndarray, todo: np.ndarray) -> None:
    """Region pixels on a barrier take the highest adjacent finite height, repeatedly
    (a wall pixel of a DSM holds the top of the wall)."""
    todo = todo.copy()
    fp = np.ones((3, 3), bool)
    while todo.any():
        filled = np.where(np.isfinite(out), out, -np.inf)
        grown = ndi.maximum_filter(filled, footprint=fp, mode="constant", cval=-np.inf)
        take = todo & np.isfinite(grown)
        if not take.any():
            break
        out[take] = grown[take]
        code[take] = METHOD_CODES["barrier"]
        todo &= ~take


def _withhold(problem: Problem, offset: int = 0) -> tuple[Problem, np.ndarray, np.ndarray]:
    """The problem with part of every component's rim withheld (made part of the component).

    The rim is cut into ``holdout_sectors`` angular sectors around each component's
    centroid and every ``holdout_every``-th one is withheld, starting at sector ``offset``;
    a rim pixel shared by two components never is. Returns the new problem and the (label, flat index) pairs of
    the withheld pixels.
    """
    st = problem.settings
    rim_l, rim_i = rim_pairs(problem)
    w = problem.labels.shape[1]
    uniq, counts = np.unique(rim_i, return_counts=True)
    shared = np.isin(rim_i, uniq[counts > 1])
    rr, rc = np.divmod(rim_i, w)
    cen = problem.centroids()
    ang = np.arctan2(rr - cen[rim_l - 1, 0], rc - cen[rim_l - 1, 1])
    sector = np.floor((ang + np.pi) / (2 * np.pi) * st.holdout_sectors).astype(np.int64) % st.holdout_sectors
    held = (sector % st.holdout_every == offset % st.holdout_every) & ~shared
    labels2 = problem.labels.copy()
    labels2.ravel()[rim_i[held]] = rim_l[held]
    support2 = problem.support.copy()
    support2.ravel()[rim_i[held]] = False
    heights2 = problem.heights.copy()
    heights2.ravel()[rim_i[held]] = np.nan
    return replace(problem, heights=heights2, labels=labels2, support=support2), rim_l[held], rim_i[held]


def contest(problem: Problem, entrants: np.ndarray, candidates: tuple[str, ...]) -> dict[int, dict[str, float]]:
    """Cross-validation RMSE of every candidate method on every entrant component's rim.

    In each of ``auto_folds`` folds, part of every component's rim is withheld
    (:func:`_withhold`: the error estimate's split, fold ``f`` starting at sector
    ``f * holdout_every // auto_folds``, so two folds withhold two perpendicular pairs of
    arcs) and each candidate refills the components; its heights at the withheld pixels,
    kept within the range of the rim left in (as ``fill.clamp_to_rim`` keeps a fill), are
    compared with the measured ones. Returns ``{label: {method: RMSE over every fold}}``
    (the winner is :func:`pick`'s). A method that could not fill all of a component's
    withheld pixels is left out, and a component none could (no rim pixel withheld)
    maps to ``{}``.
    """
    return {k: {m: v[0] for m, v in by.items()} for k, by in _contest_errors(problem, entrants, candidates).items()}


def _contest_errors(
    problem: Problem, entrants: np.ndarray, candidates: tuple[str, ...]
) -> dict[int, dict[str, tuple[float, np.ndarray]]]:
    """``{label: {method: (RMSE, squared errors at the withheld pixels)}}`` (see :func:`contest`)."""
    if len(entrants) == 0 or not candidates:
        return {}
    st = problem.settings
    n = problem.n_labels + 1
    labs = np.asarray(entrants, np.int64)
    errors: dict[str, list[np.ndarray]] = {name: [] for name in candidates}
    held_labels = []
    for fold in range(st.auto_folds):
        p2, held_l, held_i = _withhold(problem, fold * st.holdout_every // st.auto_folds)
        keep = np.isin(held_l, labs)
        held_l, held_i = held_l[keep], held_i[keep]
        held_labels.append(held_l)
        truth = problem.heights.ravel()[held_i]
        # the rim left in: its range per component, the clamp a fill gets
        rim_l, rim_i = rim_pairs(p2)
        lo, hi = np.full(n, np.inf), np.full(n, -np.inf)
        np.minimum.at(lo, rim_l, problem.heights.ravel()[rim_i])
        np.maximum.at(hi, rim_l, problem.heights.ravel()[rim_i])
        todo = labs[np.bincount(held_l, minlength=n)[labs] > 0]
        for name in candidates:
            out2 = p2.heights.copy()
            if len(todo):
                FILL_METHODS[name](p2, todo, out2)
            errors[name].append((np.clip(out2.ravel()[held_i], lo[held_l], hi[held_l]) - truth) ** 2)
    all_l = np.concatenate(held_labels)
    order = np.argsort(all_l, kind="stable")
    bounds = np.searchsorted(all_l[order], np.arange(n + 1))
    result: dict[int, dict[str, tuple[float, np.ndarray]]] = {int(k): {} for k in labs}
    for name in candidates:
        d2 = np.concatenate(errors[name])[order]
        for k in labs:
            mine = d2[bounds[k] : bounds[k + 1]]
            if len(mine) and np.isfinite(mine).all():
                result[int(k)][name] = (float(np.sqrt(mine.mean())), mine)
    return result


def pick(by_method: dict[str, tuple[float, np.ndarray]], candidates: tuple[str, ...], z: float) -> str:
    """The contest's winner: the first candidate (the reference), unless others predict the
    withheld rim significantly better, then the best of those.

    Better means a lower mean squared error by more than ``z`` standard errors of the
    paired difference (the same withheld pixels): on a rough rim (tree crowns, roofs)
    every method misses by metres and the ranking is noise, so the reference stays.
    """
    ref = next((m for m in candidates if m in by_method), None)
    if ref is None:
        return ""
    _, ref_d2 = by_method[ref]
    best, best_rmse = ref, by_method[ref][0]
    for name, (rmse, d2) in by_method.items():
        if name == ref or rmse >= best_rmse:
            continue
        diff = ref_d2 - d2
        se = diff.std(ddof=1) / np.sqrt(len(diff)) if len(diff) > 1 else math.inf
        if diff.mean() > z * se:
            best, best_rmse = name, rmse
    return best


def _with_scores(record: ComponentFill, by_method: dict[str, tuple[float, int]] | None) -> ComponentFill:
    """A contest winner's record: its cross-validation RMSE as the error estimate, every score and
    how many withheld rim pixels they rest on in ``detail`` (one pixel scores 0 for a method that
    happens to hit it: the count says how little that means)."""
    if not by_method or not record.filled or record.method not in by_method:
        return record
    scores = ", ".join(f"{m} {e:.3g}" for m, (e, _) in sorted(by_method.items(), key=lambda item: item[1][0]))
    withheld = by_method[record.method][1]
    pixels = "pixel" if withheld == 1 else "pixels"
    detail = f"auto: {record.method} by rim cross-validation on {withheld} withheld rim {pixels} (RMSE {scores})"
    return replace(
        record,
        error_estimate=by_method[record.method][0],
        detail=f"{record.detail}; {detail}" if record.detail else detail,
    )


def _holdout_errors(problem: Problem, chosen: dict[int, str], records: dict[int, ComponentFill]) -> dict[int, float]:
    """Leave-boundary-out RMSE per component: withhold every ``holdout_every``-th of
    ``holdout_sectors`` angular sectors of the rim (:func:`_withhold`), refill with the
    same method and compare the refilled rim heights with the measured ones."""
    p2, held_l, held_i = _withhold(problem)
    out2 = p2.heights.copy()
    _run(p2, {k: m for k, m in chosen.items() if records[k].filled}, out2)
    errs = {}
    truth = problem.heights.ravel()[held_i]
    got = out2.ravel()[held_i]
    for k in np.unique(held_l):
        sel = held_l == k
        d = got[sel] - truth[sel]
        if np.all(np.isfinite(d)):
            errs[int(k)] = float(np.sqrt(np.mean(d * d)))
    return errs
