"""Scoring a run against known truth: hole masks (IoU) and hole causes.

Truth comes as a raster of cause codes on the same pixel lattice as the run
(``pipeline.synth.HoleCause``: 0 no hole, 1 occlusion, 2 water, 3 missed
coverage, 4 no return, 5 covered), as the synthetic surveys and the scan
simulator (``pipeline.simulate``) write it. Detected holes are the polygons
of the ``holes`` layer, rasterized by pixel centre (exact: they follow pixel
edges). A detected hole's true cause is the most common truth cause of its
pixels.
"""

from __future__ import annotations

import collections
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputDataError
from ..io.raster import geometry_mask, raster_lattice, read_raster
from ..io.vector import read_layer

#: Truth codes -> cause names of the ``holes`` layer.
CAUSE_NAMES = {1: "occlusion", 2: "water", 3: "missed_coverage", 4: "no_return", 5: "covered"}


@dataclass
class HoleScore:
    """How well the holes of a run match the truth."""

    iou: float  # detected hole area vs true hole area (pixels above the minimum area)
    true_hole_px: int
    detected_px: int
    holes: int  # detected holes scored
    cause_correct: int
    confusion: dict[str, dict[str, int]] = field(default_factory=dict)  # true -> detected -> count
    missed_true_holes: int = 0  # true hole components (>= min area) with no detected pixel
    confusion_px: dict[str, dict[str, int]] = field(default_factory=dict)  # the same, weighed by hole pixels

    @property
    def cause_accuracy(self) -> float:
        return self.cause_correct / self.holes if self.holes else float("nan")

    def as_dict(self) -> dict:
        return {
            "iou": round(self.iou, 4),
            "true_hole_px": self.true_hole_px,
            "detected_px": self.detected_px,
            "holes": self.holes,
            "cause_accuracy": round(self.cause_accuracy, 4) if self.holes else None,  # JSON has no NaN
            "confusion": self.confusion,
            "missed_true_holes": self.missed_true_holes,
            "confusion_px": self.confusion_px,
        }


def score_holes(holes_gpkg: str | os.PathLike, truth_causes: str | os.PathLike, *, min_area_px: int = 1) -> HoleScore:
    """Compare the ``holes`` layer of a run with a truth raster of cause codes.

    Parameters
    ----------
    holes_gpkg : path-like
        The run's ``holes.gpkg``.
    truth_causes : path-like
        A raster of ``HoleCause`` codes on the run's pixel lattice.
    min_area_px : int
        True hole components smaller than this are not counted as holes (the run
        lists only holes of at least ``holes.min_area_m2``).
    """
    import scipy.ndimage as ndi

    try:
        truth, transform, _ = read_raster(truth_causes)
    except Exception as e:  # not a raster GDAL reads, or a truncated one
        raise InputDataError(truth_causes, f"truth is not a readable raster ({_first_line(e)})") from None
    truth = np.nan_to_num(truth, nan=0).astype(np.uint8)
    labels, n = ndi.label(truth > 0)
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    big = sizes >= min_area_px
    big[0] = False
    true_mask = big[labels]
    holes = read_layer(holes_gpkg, "holes")
    detected = np.zeros(truth.shape, bool)
    confusion: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    confusion_px: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    correct = 0
    scored = 0
    causes = holes["cause"] if "cause" in holes.columns else [None] * len(holes)  # an empty layer of an older run
    for geometry, cause in zip(holes.geometry, causes):
        mask = geometry_mask(geometry, transform, truth.shape)
        if not mask.any():
            continue
        detected |= mask
        codes = truth[mask]
        codes = codes[codes > 0]
        true_cause = CAUSE_NAMES[int(np.bincount(codes).argmax())] if len(codes) else "none"
        confusion[true_cause][cause] += 1
        confusion_px[true_cause][cause] += int(mask.sum())
        scored += 1
        correct += true_cause == cause
    union = (detected | true_mask).sum()
    hit = np.unique(labels[detected & true_mask])
    missed = int(big.sum() - len(hit[hit > 0]))
    return HoleScore(
        iou=float((detected & true_mask).sum() / union) if union else 1.0,
        true_hole_px=int(true_mask.sum()),
        detected_px=int(detected.sum()),
        holes=scored,
        cause_correct=int(correct),
        confusion={k: dict(v) for k, v in confusion.items()},
        missed_true_holes=missed,
        confusion_px={k: dict(v) for k, v in confusion_px.items()},
    )


def check_truth_lattice(truth_path: str | os.PathLike, run_lattice: tuple[float, float, float, str]) -> float:
    """Refuse a truth raster that is not on the run's pixel lattice; returns its pixel size.

    Holes are scored pixel by pixel: a truth raster of another pixel size, origin off
    the run's lattice, or another CRS would give a score that means nothing.

    Parameters
    ----------
    truth_path : path-like
        The truth raster.
    run_lattice : tuple
        The run's ``(resolution, min x, max y, crs_wkt)`` (:func:`pipeline.io.raster.raster_lattice`).
    """
    try:
        resolution, x0, y0, crs_wkt = raster_lattice(truth_path)
    except Exception as e:
        raise InputDataError(truth_path, f"truth is not a readable raster ({_first_line(e)})") from None
    run_resolution, run_x0, run_y0, run_crs = run_lattice
    advice = (
        f"resample it onto the run's grid (e.g. gdalwarp -r mode -tr {run_resolution:g} {run_resolution:g} "
        f"-tap -t_srs <the run's CRS>)"
    )
    if resolution is None:
        raise InputDataError(truth_path, f"truth raster is rotated or sheared; {advice}")
    if not math.isclose(resolution, run_resolution, rel_tol=1e-6):
        raise InputDataError(
            truth_path, f"truth pixel size {resolution:g} differs from the run's {run_resolution:g}; {advice}"
        )
    off = [(a - b) / run_resolution for a, b in ((x0, run_x0), (y0, run_y0))]
    if any(abs(v - round(v)) > 1e-3 for v in off):
        raise InputDataError(
            truth_path,
            f"truth pixels are shifted off the run's lattice by ({off[0] % 1:.3g}, {off[1] % 1:.3g}) pixels; {advice}",
        )
    if crs_wkt and run_crs:
        from pyproj import CRS

        if not CRS.from_wkt(crs_wkt).equals(CRS.from_wkt(run_crs), ignore_axis_order=True):
            raise InputDataError(truth_path, f"truth CRS '{CRS.from_wkt(crs_wkt).name}' is not the run's; {advice}")
    return resolution


def score_run(out_dir: str | os.PathLike, truth_causes: str | os.PathLike, *, min_area_m2: float | str) -> HoleScore:
    """Score the holes of the finished run in ``out_dir`` against a truth raster of cause codes.

    Parameters
    ----------
    out_dir : path-like
        The run's output folder (its ``holes.gpkg``, and ``manifest.json`` or ``dsm.vrt``).
    truth_causes : path-like
        A raster of true cause codes on the run's pixel lattice (:func:`check_truth_lattice`).
    min_area_m2 : float or "auto"
        ``holes.min_area_m2``; "auto": the value the run settled (from its manifest).

    Raises
    ------
    InputDataError
        ``out_dir`` holds no finished run, its minimum area or pixel grid cannot be told,
        or the truth is not on its lattice.
    """
    out = Path(out_dir)
    if not (out / "holes.gpkg").exists():
        raise InputDataError(out, "holds no finished holefill run (no holes.gpkg)")
    manifest = json.loads((out / "manifest.json").read_text()) if (out / "manifest.json").exists() else None
    if min_area_m2 == "auto":  # as the run resolved it
        if manifest is None:
            raise InputDataError(out, "has no manifest.json to tell holes.min_area_m2: give --set holes.min_area_m2=")
        min_area_m2 = manifest["holes"]["min_area_m2"]
    resolution = check_truth_lattice(truth_causes, run_lattice(out, manifest))
    return score_holes(out / "holes.gpkg", truth_causes, min_area_px=min_area_px(float(min_area_m2), resolution))


def run_lattice(out: Path, manifest: dict | None) -> tuple[float, float, float, str]:
    """The pixel lattice ``(resolution, left, top, crs_wkt)`` of the run in ``out``: from its manifest, else its DSM."""
    if manifest is not None and "grid" in manifest:
        grid = manifest["grid"]
        return float(grid["resolution"]), grid["bounds"][0], grid["bounds"][3], manifest.get("crs", {}).get("wkt", "")
    if not (out / "dsm.vrt").exists():
        raise InputDataError(out, "has neither manifest.json nor dsm.vrt to tell the run's pixel grid")
    resolution, left, top, crs_wkt = raster_lattice(out / "dsm.vrt")
    return float(resolution or 0.0), left, top, crs_wkt


def min_area_px(min_area_m2: float, resolution: float) -> int:
    """The smallest hole scored, in pixels of side ``resolution``: at least one."""
    return max(1, math.ceil(min_area_m2 / resolution**2))


def _first_line(e: BaseException) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__
