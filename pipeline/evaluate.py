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
import os
from dataclasses import dataclass, field

import numpy as np

from .io.raster import geometry_mask, read_raster
from .io.vector import read_layer

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

    truth, transform, _ = read_raster(truth_causes)
    truth = np.nan_to_num(truth, nan=0).astype(np.uint8)
    labels, n = ndi.label(truth > 0)
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    big = sizes >= min_area_px
    big[0] = False
    true_mask = big[labels]
    holes = read_layer(holes_gpkg, "holes")
    detected = np.zeros(truth.shape, bool)
    confusion: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    correct = 0
    scored = 0
    causes = holes["cause"] if "cause" in holes.columns else []  # a layer with no hole may have no fields
    for geometry, cause in zip(holes.geometry, causes):
        mask = geometry_mask(geometry, transform, truth.shape)
        if not mask.any():
            continue
        detected |= mask
        codes = truth[mask]
        codes = codes[codes > 0]
        true_cause = CAUSE_NAMES[int(np.bincount(codes).argmax())] if len(codes) else "none"
        confusion[true_cause][cause] += 1
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
    )
