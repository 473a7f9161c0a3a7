"""Throughput of per-cell hole detection + cause classification.

Run: ``python bench/bench_holes.py [--size 1000] [--repeat 5]``. Prints pixels per
second on one core for a few synthetic 1000 x 1000 cells (the core; the halo is
extra): a typical mixed scene, a scene full of 1-pixel voids (sparse data) and a
mostly empty cell; the speckle scene again with small closed voids settled in
the cell (``min_area_px``), as the pipeline runs it.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import scipy.ndimage as ndi

from pipeline.grid import Cell, PixelWindow
from pipeline.holes import DetectParams, classify_causes, detect_cell_holes
from pipeline.parameters import default_cause_rules


def scene(kind: str, size: int, halo: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    n = size + 2 * halo
    ground = ndi.gaussian_filter(rng.standard_normal((n, n)), 40) * 200.0
    z = ground + rng.normal(0, 0.05, (n, n))
    count = rng.integers(1, 20, (n, n)).astype(np.uint32)
    if kind == "mixed":
        # buildings with a shadow band on their east side
        for _ in range(300):
            r, c = rng.integers(0, n - 40, 2)
            hh, ww = rng.integers(8, 30, 2)
            z[r : r + hh, c : c + ww] += rng.uniform(4, 25)
            count[r : r + hh, c + ww : c + ww + rng.integers(2, 8)] = 0
        # lakes
        blobs = ndi.gaussian_filter(rng.standard_normal((n, n)), 25) > 0.012
        count[blobs] = 0
        # scattered dropouts
        count[rng.random((n, n)) < 0.01] = 0
    elif kind == "speckle":
        count[rng.random((n, n)) < 0.3] = 0
    elif kind == "empty":
        count[ndi.gaussian_filter(rng.standard_normal((n, n)), 30) > -0.01] = 0
    zmax = np.where(count > 0, z, np.nan).astype(np.float32)
    zmin = np.where(count > 0, z - rng.uniform(0, 0.3, (n, n)), np.nan).astype(np.float32)
    return count, zmax, zmin


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--size", type=int, default=1000)
    parser.add_argument("--halo", type=int, default=8)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    size, halo = args.size, args.halo
    core = PixelWindow(halo, halo, size, size)
    cell = Cell("bench", 0, 0, core, core.expand(halo))
    grid_window = core.expand(halo)
    # compile the numba kernels outside the timings
    count, zmax, zmin = scene("mixed", 64, halo)
    small = PixelWindow(halo, halo, 64, 64)
    detect_cell_holes(
        count,
        zmax,
        zmin,
        cell=Cell("warm", 0, 0, small, small.expand(halo)),
        grid_window=small.expand(halo),
        params=DetectParams(jump_threshold=2.0),
    )
    for kind, min_area in (("mixed", 0), ("speckle", 0), ("speckle", 4), ("empty", 0)):
        count, zmax, zmin = scene(kind, size, halo)
        aoi = np.ones(count.shape, bool)
        best = np.inf
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            res = detect_cell_holes(
                count,
                zmax,
                zmin,
                aoi,
                cell=cell,
                grid_window=grid_window,
                params=DetectParams(jump_threshold=2.0, min_area_px=min_area),
            )
            classify_causes(res.stats, default_cause_rules(pixel_size=1.0, jump_threshold=2.0))
            best = min(best, time.perf_counter() - t0)
        label = f"{kind} (min_area_px={min_area})" if min_area else kind
        print(
            f"{label:26s} {size}x{size} core: {res.n_parts:7d} parts, {best * 1e3:7.1f} ms, "
            f"{size * size / best / 1e6:6.1f} Mpx/s"
        )


if __name__ == "__main__":
    main()
