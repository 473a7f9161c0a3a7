"""Figure: a sortie's side view, the flight path over the highest surface near it (docs/flightplans.md).

Run: ``python bench/figure_flight_profile.py RUN_FOLDER [--sortie 1] [--dsm DSM] [--out
docs/img/flightplan_profile.png]`` on a finished run (``holefill demo --out demo-out`` makes one)
or a ``holefill plan`` folder (with ``--dsm``). Along the route, every metre: the
highest DSM pixel within ``flightplan.clearance_radius_m`` of the path (grey, filled), that surface
plus ``flightplan.min_clearance_m`` (red: what every leg must stay above), the flight path from the
``waypoints`` layer's heights (blue, from the climb at take-off), the take-off point's ground
(green square) and, pale, where the path crosses no data (the hole being re-flown). Drawn with
numpy and written with holefill's own PNG encoder (no plotting library).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import rasterio

from pipeline.config import load_config
from pipeline.io.vector import read_layer
from pipeline.report.png import encode_png

WIDTH, HEIGHT, MARGIN = 1200, 360, 20
GREY, RED, BLUE, GREEN, WHITE = (170, 170, 170), (210, 40, 40), (30, 90, 200), (20, 150, 60), (255, 255, 255)
PALE = (225, 232, 245)  # no data under the path: the hole being re-flown


def profile(run: Path, sortie: int, dsm_path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float, float]:
    """Distance along the route (m), flight height and highest surface near the path, every metre."""
    manifest = run / "manifest.json"
    if manifest.exists():
        config = json.loads(manifest.read_text())["config"]["flightplan"]
        radius, minimum = float(config["clearance_radius_m"]), float(config["min_clearance_m"])
    else:  # a `holefill plan` folder: the default settings
        defaults = load_config().flightplan
        radius, minimum = defaults.clearance_radius_m, defaults.min_clearance_m
    frame = read_layer(run / "flightplan.gpkg", "waypoints")
    frame = frame[frame["sortie"] == sortie].sort_values("sequence")
    xy = np.array([[g.x, g.y] for g in frame.geometry])
    z = frame["height_dsm_m"].to_numpy(float)
    legs = np.hypot(*np.diff(xy, axis=0).T)
    along = np.concatenate([[0.0], np.cumsum(legs)])
    samples = np.arange(0.0, along[-1], 1.0)
    px, py = (np.interp(samples, along, xy[:, k]) for k in range(2))
    flight = np.interp(samples, along, z)
    with rasterio.open(dsm_path) as src:
        dsm = src.read(1, masked=True).filled(np.nan)
        inverse = ~src.transform
    surface = np.full(len(samples), np.nan)
    reach = int(math.ceil(radius)) + 1
    for i, (x, y) in enumerate(zip(px, py, strict=True)):
        col, row = (int(math.floor(v)) for v in inverse * (x, y))
        window = dsm[max(row - reach, 0) : row + reach + 1, max(col - reach, 0) : col + reach + 1]
        if window.size and np.isfinite(window).any():
            surface[i] = np.nanmax(window)
    ground = float(frame["height_dsm_m"].iloc[0] - frame["altitude_m"].iloc[0])
    return samples, flight, surface, minimum, ground, float(along[-1])


def draw(samples, flight, surface, minimum, ground, length) -> np.ndarray:
    image = np.full((HEIGHT, WIDTH, 3), WHITE, np.uint8)
    top = float(np.nanmax(np.concatenate([flight, surface + minimum]))) + 5.0
    bottom = min(float(np.nanmin(surface)), ground) - 5.0

    def col(d):
        return (MARGIN + np.asarray(d) / length * (WIDTH - 2 * MARGIN)).astype(int)

    def row(h):
        return (MARGIN + (top - np.asarray(h)) / (top - bottom) * (HEIGHT - 2 * MARGIN)).astype(int)

    for d, s in zip(samples, surface, strict=True):
        if np.isfinite(s):
            image[row(s) : HEIGHT - MARGIN, col(d)] = GREY
        elif int(col(d)) % 4 == 0:
            image[MARGIN : HEIGHT - MARGIN, col(d)] = PALE
    climb = int(col(0.0))  # the climb from the take-off point's ground to the first waypoint
    image[int(row(flight[0])) : int(row(ground)) + 1, max(climb - 1, 0) : climb + 2] = BLUE
    for values, colour, dashed in ((surface + minimum, RED, True), (flight, BLUE, False)):
        for i, (d, h) in enumerate(zip(samples, values, strict=True)):
            if np.isfinite(h) and not (dashed and (i // 6) % 2):
                r, c = int(row(h)), int(col(d))
                image[max(r - 1, 0) : r + 2, c] = colour
    r, c = int(row(ground)), int(col(0.0))
    image[max(r - 5, 0) : r + 5, max(c - 5, 0) : c + 5] = GREEN
    return image


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path)
    parser.add_argument("--sortie", type=int, default=1)
    parser.add_argument("--dsm", type=Path, help="the DSM (default: RUN/dsm.vrt)")
    parser.add_argument("--out", type=Path, default=Path("docs/img/flightplan_profile.png"))
    args = parser.parse_args()
    samples, flight, surface, minimum, ground, length = profile(args.run, args.sortie, args.dsm or args.run / "dsm.vrt")
    args.out.write_bytes(encode_png(draw(samples, flight, surface, minimum, ground, length)))
    least = float(np.nanmin(flight - surface))
    print(f"{args.out}: {length:,.0f} m of route, least clearance {least:.1f} m (minimum {minimum:g} m)")


if __name__ == "__main__":
    main()
