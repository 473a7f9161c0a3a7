"""Scoring hole causes on real surveys against a truth the cause rules do not see.

A real survey has no truth raster of causes (``pipeline.evaluate.truth`` scores the
synthetic ones). What it has is evidence from outside the rules, read here
straight from the points and from reference files:

- the producer's classification: water-class points (ASPRS 9) around a void
  say water; building-class points (ASPRS 6) standing well above the rest of
  the surroundings say the void is a building's shadow;
- reference polygons of known water (e.g. lidR's lake polygons of Megaplot).

Each listed hole of a run gets one truth label (``TRUTH_CAUSES``, or
``unverified``): **water** when at least ``water_min_share`` of its edge pixels
lie within ``reach_m`` (at least 2 pixels) of a pixel holding water-class
points (a water body's few returns lie on its surface, beside the void), or
when at least ``lake_min_share`` of it lies inside reference water polygons;
else **occlusion** when at least ``building_min_share`` of its *truth ring*
(the pixels holding points within ``reach_m`` of it, outside every hole) holds
building-class points ``step_m`` above the ring's low level; else
**not_water**, for a survey whose water is known (it has class-9 points or
polygons, or its provenance names no water), or **unverified**. The evidence
rasters are made on the run's own pixel lattice, so a hole polygon (pixel
edges) maps to its pixels exactly.

The water truth from class-9 points is the same evidence the ``water_points``
rule uses (on a wider ring, at a higher share), so it scores the rules that do
not see class 9 (``level_rim``, ``flat_low_rim``) honestly only in a run
where class 9 was withheld from the pipeline (``bench/bench_causes_real.py``
relabels it to class 1 in a copy of the file: same DSM, same holes).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import shapely
from affine import Affine
from scipy import ndimage

from ..io.las import iter_point_chunks
from ..io.raster import geometry_mask, read_raster
from ..io.vector import read_layer
from ..rasterize import WATER_CLASS

#: ASPRS class of buildings.
BUILDING_CLASS = 6
#: Truth labels scored: water, a building's shadow, or neither. A hole of a survey with
#: water but no water evidence without a building beside it is "unverified" (not scored).
TRUTH_CAUSES = ("water", "occlusion", "not_water")


@dataclass(frozen=True)
class TruthRules:
    """How the truth of a hole is read from the evidence around it.

    reach_m : how far (m, at least 2 pixels) water evidence may lie from the hole's
        edge, and the width of the truth ring.
    water_min_share : share of the hole's edge pixels within ``reach_m`` of water-class points.
    lake_min_share : share of the hole inside reference water polygons.
    building_min_share : share of the ring's pixels holding building-class points
        that stand ``step_m`` above the ring's low level (its 5 % quantile of lowest points).
    """

    reach_m: float = 5.0
    water_min_share: float = 0.3
    lake_min_share: float = 0.5
    building_min_share: float = 0.25
    step_m: float = 2.5


@dataclass(frozen=True)
class PointEvidence:
    """Per-pixel evidence from a file's points on a run's lattice (row 0 at the top)."""

    count: np.ndarray  # points (all classes but the dropped ones)
    water: np.ndarray  # water-class points
    building_zmax: np.ndarray  # highest building-class point, NaN where none
    zmin: np.ndarray  # lowest point, NaN where none


@dataclass(frozen=True)
class HoleTruth:
    """The truth of one listed hole and the evidence it rests on."""

    hole_id: int
    area_m2: float
    cause: str  # reported by the run
    rule: str
    truth: str  # one of TRUTH_CAUSES
    ring_px: int
    water_edge_share: float  # edge pixels within reach_m of water-class points
    building_share: float  # ring pixels with building-class points above the low level by step_m
    lake_share: float  # hole pixels inside the reference water polygons (NaN: none given)
    centroid: tuple[float, float]


def point_evidence(
    path: str | os.PathLike,
    transform: Affine,
    shape: tuple[int, int],
    *,
    drop_classes: tuple[int, ...] = (7, 18),
    chunk_points: int = 1_000_000,
) -> PointEvidence:
    """Bin one file's points on the lattice of ``transform`` (north up) and ``shape``.

    The run's own filter by default: noise classes and withheld points are left out.
    """
    rows, cols = shape
    n = rows * cols
    count = np.zeros(n, np.int64)
    water = np.zeros(n, np.int64)
    building_zmax = np.full(n, -np.inf)
    zmin = np.full(n, np.inf)
    for chunk in iter_point_chunks(path, chunk_points):
        x, y, z = chunk.coordinates()
        col = np.floor((x - transform.c) / transform.a).astype(np.int64)
        row = np.floor((y - transform.f) / transform.e).astype(np.int64)
        inside = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
        keep = inside & ~np.isin(chunk.classification, drop_classes) & ~chunk.withheld
        pixel = row[keep] * cols + col[keep]
        cls, zk = chunk.classification[keep], z[keep]
        count += np.bincount(pixel, minlength=n)
        water += np.bincount(pixel[cls == WATER_CLASS], minlength=n)
        np.maximum.at(building_zmax, pixel[cls == BUILDING_CLASS], zk[cls == BUILDING_CLASS])
        np.minimum.at(zmin, pixel, zk)
    return PointEvidence(
        count=count.reshape(shape),
        water=water.reshape(shape),
        building_zmax=np.where(np.isfinite(building_zmax), building_zmax, np.nan).reshape(shape),
        zmin=np.where(np.isfinite(zmin), zmin, np.nan).reshape(shape),
    )


def ring_mask(hole: np.ndarray, all_holes: np.ndarray, has_points: np.ndarray, radius_px: int) -> np.ndarray:
    """Pixels with points within ``radius_px`` (a disc) of ``hole``, outside every hole."""
    return ndimage.binary_dilation(hole, structure=_disc(radius_px)) & ~all_holes & has_points


def _disc(radius_px: int) -> np.ndarray:
    yy, xx = np.mgrid[-radius_px : radius_px + 1, -radius_px : radius_px + 1]
    return xx**2 + yy**2 <= radius_px**2


def edge_near(hole: np.ndarray, distance: np.ndarray, within: float) -> float:
    """Share of the hole's edge pixels (hole pixels with a 4-neighbour outside it) within ``within`` of something.

    ``distance``: per pixel, the distance to the nearest pixel holding that something.
    """
    edge = hole & ~ndimage.binary_erosion(hole, border_value=0)
    return float((distance[edge] <= within).mean()) if edge.any() else 0.0


def building_share(ring: np.ndarray, evidence: PointEvidence, step: float) -> float:
    """Share of the ring's pixels whose building-class points stand ``step`` above the ring's low level."""
    if not ring.any():
        return 0.0
    low = float(np.nanquantile(evidence.zmin[ring], 0.05))
    return float(np.mean(np.nan_to_num(evidence.building_zmax[ring], nan=-np.inf) >= low + step))


def truth_of_hole(
    water_edge: float, lake_share: float, buildings: float, rules: TruthRules, *, water_known: bool
) -> str:
    """The truth label of one hole (one of ``TRUTH_CAUSES``, or ``unverified``).

    Water first (the hole's edge beside water-class points, or the hole inside
    reference water polygons), then a building's shadow, else ``not_water``, which
    only a survey whose water is known can say (``water_known``: it has water
    evidence, or its provenance says it has no water).
    """
    if water_edge >= rules.water_min_share or lake_share >= rules.lake_min_share:
        return "water"
    if buildings >= rules.building_min_share:
        return "occlusion"
    return "not_water" if water_known else "unverified"


def label_holes(
    run_dir: str | os.PathLike,
    las_path: str | os.PathLike,
    *,
    water_polygons: shapely.Geometry | None = None,
    water_known: bool = True,
    rules: TruthRules | None = None,
) -> list[HoleTruth]:
    """Every listed hole of a finished run with its reported cause and its truth.

    ``water_polygons``: a shapely geometry of known water in the run's CRS, or None.
    ``water_known``: False for a survey with water but neither water-class points nor
    polygons (its holes without building evidence are ``unverified``).
    """
    import json
    from pathlib import Path

    rules = rules or TruthRules()
    run_dir = Path(run_dir)
    holes = read_layer(run_dir / "holes.gpkg", "holes")
    dsm, transform, _ = read_raster(run_dir / "dsm.vrt")
    unit_m = float(json.loads((run_dir / "manifest.json").read_text())["grid"]["resolution_unit_m"])
    pixel_m = abs(transform.a) * unit_m
    evidence = point_evidence(las_path, transform, dsm.shape)
    water_distance = ndimage.distance_transform_edt(evidence.water == 0) * pixel_m
    masks = [geometry_mask(g, transform, dsm.shape) for g in holes.geometry]
    all_holes = np.logical_or.reduce(masks) if masks else np.zeros(dsm.shape, bool)
    lakes = geometry_mask(water_polygons, transform, dsm.shape) if water_polygons is not None else None
    within_m = max(rules.reach_m, 2 * pixel_m)
    found = []
    for row, mask in zip(holes.itertuples(), masks):
        ring = ring_mask(mask, all_holes, evidence.count > 0, max(2, int(np.ceil(within_m / pixel_m))))
        water_edge = edge_near(mask, water_distance, within_m)
        lake_share = float(lakes[mask].mean()) if lakes is not None and mask.any() else float("nan")
        buildings = building_share(ring, evidence, rules.step_m / unit_m)
        truth = truth_of_hole(water_edge, np.nan_to_num(lake_share), buildings, rules, water_known=water_known)
        centroid = row.geometry.centroid
        found.append(
            HoleTruth(
                hole_id=int(row.hole_id), area_m2=float(row.area_m2), cause=str(row.cause),
                rule=str(row.cause_rule), truth=truth, ring_px=int(ring.sum()), water_edge_share=water_edge,
                building_share=buildings, lake_share=lake_share, centroid=(centroid.x, centroid.y),
            )
        )  # fmt: skip
    return found


@dataclass
class CauseScore:
    """Per truth cause: holes reported right / holes; water precision and recall."""

    right: dict[str, int]
    total: dict[str, int]
    water_tp: int
    water_fp: int
    water_fn: int

    @property
    def water_precision(self) -> float:
        reported = self.water_tp + self.water_fp
        return self.water_tp / reported if reported else float("nan")

    @property
    def water_recall(self) -> float:
        true = self.water_tp + self.water_fn
        return self.water_tp / true if true else float("nan")


def is_right(hole: HoleTruth) -> bool:
    """A hole is reported right: water as water, a building's shadow as occlusion, else anything but water."""
    if hole.truth == "not_water":
        return hole.cause != "water"
    return hole.cause == hole.truth


def score_holes(holes: list[HoleTruth]) -> CauseScore:
    """Count right answers per truth cause, and the water confusion, over some labelled holes."""
    right = dict.fromkeys(TRUTH_CAUSES, 0)
    total = dict.fromkeys(TRUTH_CAUSES, 0)
    holes = [h for h in holes if h.truth in TRUTH_CAUSES]
    for hole in holes:
        total[hole.truth] += 1
        right[hole.truth] += is_right(hole)
    said_water = np.array([h.cause == "water" for h in holes], bool)
    is_water = np.array([h.truth == "water" for h in holes], bool)
    return CauseScore(
        right=right,
        total=total,
        water_tp=int((said_water & is_water).sum()),
        water_fp=int((said_water & ~is_water).sum()),
        water_fn=int((~said_water & is_water).sum()),
    )
