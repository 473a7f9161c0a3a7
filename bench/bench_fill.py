"""Speed and accuracy of the fill kernels on a synthetic 1000 x 1000 DSM.

    .venv/bin/python bench/bench_fill.py [--size 1000] [--seed 0] [--methods tin,mls,...]

The surface is known everywhere (rolling terrain plus metre-scale relief), holes are
cut into it (many small blobs of 5-500 px, a few large ones of 10k-100k px including
a flight-line strip), every method fills them in one process, and the script prints
filled pixels per second and the RMSE against the known surface, for small and large
holes separately. No assertions: the figures go to docs/filling.md.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import scipy.ndimage as ndi

from pipeline.fill import METHOD_CODES, FillSettings, fill_region


def synthetic_surface(size: int, rng: np.random.Generator) -> np.ndarray:
    """Rolling terrain (100 m scale), hills (20 m) and metre-scale relief, 1 m pixels."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    z = 50 + 0.02 * xx - 0.01 * yy
    z += 10 * np.sin(xx / 80) * np.cos(yy / 120)
    z += 2 * np.sin(xx / 15 + yy / 23) + 0.8 * np.cos(xx / 7 - yy / 11)
    z += ndi.gaussian_filter(rng.normal(size=(size, size)), 3) * 3
    return z


def hole_mix(size: int, rng: np.random.Generator, n_small: int = 1500) -> np.ndarray:
    """Many small blobs (5-500 px, log-uniform) and four large holes (about 12k, 30k,
    60k as a flight-line strip, 90k px)."""
    region = np.zeros((size, size), bool)
    yy, xx = np.mgrid[0:size, 0:size]
    for cy, cx, ry, rx in ((200, 200, 55, 70), (700, 250, 90, 105), (300, 700, 160, 180)):
        region |= ((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 <= 1
    region[:, 880:940] = True  # a missed flight line, 60 px wide
    areas = np.exp(rng.uniform(np.log(5), np.log(500), n_small))
    for a in areas:
        ry = np.sqrt(a / np.pi) * rng.uniform(0.6, 1.6)
        rx = a / np.pi / ry
        cy, cx = rng.integers(5, size - 5, 2)
        r0, r1 = int(max(cy - ry - 1, 0)), int(min(cy + ry + 2, size))
        c0, c1 = int(max(cx - rx - 1, 0)), int(min(cx + rx + 2, size))
        sub = ((yy[r0:r1, c0:c1] - cy) / ry) ** 2 + ((xx[r0:r1, c0:c1] - cx) / rx) ** 2 <= 1
        region[r0:r1, c0:c1] |= sub
    region[:1, :] = region[-1:, :] = False  # keep a measured frame so every hole has a rim
    region[:, :1] = region[:, -1:] = False
    return region


def run(method: str, z: np.ndarray, region: np.ndarray, settings: FillSettings) -> dict:
    h = z.copy()
    h[region] = np.nan
    t = time.perf_counter()
    out = fill_region(h, region, method=method, pixel_size=1.0, settings=settings)
    dt = time.perf_counter() - t
    lab, _ = ndi.label(region)
    sizes = np.bincount(lab.ravel())
    large = region & (sizes[lab] >= 10_000)
    small = region & ~large
    err = out.heights - z
    filled = np.count_nonzero(region & np.isfinite(out.heights))
    used = {
        m: int(np.count_nonzero(out.method_code == c)) for m, c in METHOD_CODES.items() if np.any(out.method_code == c)
    }
    return dict(
        method=method,
        seconds=dt,
        rate=filled / dt,
        rmse=float(np.sqrt(np.nanmean(err[region] ** 2))),
        rmse_small=float(np.sqrt(np.nanmean(err[small] ** 2))),
        rmse_large=float(np.sqrt(np.nanmean(err[large] ** 2))),
        n_comp=len(out.components),
        used=used,
        degraded=sum(c.degraded for c in out.components),
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--methods", default="nearest,idw,tin,tin1,mls,auto")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    z = synthetic_surface(args.size, rng)
    region = hole_mix(args.size, rng)
    lab, n = ndi.label(region)
    sizes = np.bincount(lab.ravel())[1:]
    print(
        f"raster {args.size}x{args.size}, {n} holes, {region.sum()} px to fill "
        f"({np.count_nonzero(sizes < 10_000)} holes < 10k px holding {sizes[sizes < 10_000].sum()} px; "
        f"largest {sizes.max()} px); cores visible {os.cpu_count()}, run single-process"
    )
    # compile the numba kernels outside the timing
    small = np.zeros((30, 30), bool)
    small[10:20, 10:20] = True
    fill_region(np.ones((30, 30)), small, method="mls")
    print(f"{'method':8s} {'seconds':>8s} {'Mpx/s':>7s} {'RMSE':>7s} {'small':>7s} {'large':>7s}  methods used")
    for name in args.methods.split(","):
        method, settings = name, FillSettings()
        if name == "tin1":
            method, settings = "tin", FillSettings(tin_order=1)
        r = run(method, z, region, settings)
        print(
            f"{name:8s} {r['seconds']:8.2f} {r['rate'] / 1e6:7.2f} {r['rmse']:7.3f} {r['rmse_small']:7.3f} "
            f"{r['rmse_large']:7.3f}  {r['used']} degraded={r['degraded']}"
        )


if __name__ == "__main__":
    main()
