"""The run report: one self-contained HTML page a survey engineer reads after a run.

Rendered from the manifest (so it never disagrees with it) plus the largest holes
of the ``holes`` layer. No template engine, no external assets.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

_STYLE = """
body{font-family:system-ui,sans-serif;margin:2em;max-width:60em;color:#222}
h1{font-size:1.5em}h2{font-size:1.15em;margin-top:1.6em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}.muted{color:#777}
"""


def write_report(path: str | Path, manifest: dict[str, Any], largest_holes: list[dict[str, Any]]) -> Path:
    """Write ``report.html`` from a run's manifest and its largest holes (dicts of the ``holes`` layer)."""
    summary = manifest["summary"]
    grid = manifest["grid"]
    holes = manifest.get("holes") or {}
    parts = [
        f"<!doctype html><html><head><meta charset='utf-8'><title>holefill report</title><style>{_STYLE}</style></head><body>",
        "<h1>holefill run report</h1>",
        f"<p class='muted'>holefill {_e(manifest['holefill_version'])}, {_e(manifest['created'])}, on {_e(manifest['host'])}</p>",
        "<h2>Survey</h2>",
        _table(
            ["", ""],
            [
                ["tiles read", f"{summary['tiles']:,}"],
                ["points read / used", f"{summary['points_read']:,} / {summary['points_used']:,}"],
                ["CRS", manifest["crs"]["name"]],
                ["pixel size (CRS units)", f"{grid['resolution']:g}"],
                ["grid", f"{grid['width']:,} x {grid['height']:,} pixels, {summary['cells']} cells"],
                ["empty pixels", f"{summary['empty_pixels']:,}"],
                ["run time", f"{summary['seconds']:.1f} s ({summary['points_per_second'] / 1e6:.2f} M points/s)"],
                ["stages (s)", ", ".join(f"{k} {v:.2f}" for k, v in summary["stage_seconds"].items())],
            ],
        ),
    ]
    if manifest.get("skipped"):
        parts += [
            "<h2>Skipped tiles</h2>",
            _table(["file", "reason"], [[s["path"], s["reason"]] for s in manifest["skipped"]]),
        ]
    if holes:
        parts += [
            "<h2>Holes</h2>",
            f"<p>{holes['listed']:,} holes of at least {holes['min_area_m2']:g} m², {holes['area_m2']:,.0f} m² in all; "
            f"{holes['small_voids']:,} smaller voids and sampling gaps ({holes['small_void_area_m2']:,.0f} m²) "
            f"counted, not listed. "
            f"Survey area (AOI): {holes['aoi_area_m2']:,.0f} m².</p>",
            "<h3>By cause</h3>",
            _table(["cause", "holes"], [[cause, f"{n:,}"] for cause, n in holes["by_cause"].items()]),
            "<h3>Cell parts by type</h3>",
            "<p class='muted'>closed; open type I (across cell edges inside the AOI) or II (open to the AOI boundary), "
            "shapes A hollow, B semi-enclosed, C crossing, D island (docs/holes.md)</p>",
            _table(["type", "parts"], [[kind, f"{n:,}"] for kind, n in holes["parts_by_type"].items()]),
            "<h3>Largest holes</h3>",
            _table(
                ["hole", "area m²", "cause", "rule", "cells", "layers", "boundary jumps", "fill"],
                [
                    [
                        h["hole_id"],
                        f"{h['area_m2']:,.0f}",
                        h["cause"],
                        h["cause_rule"],
                        h["n_cells"],
                        h["max_layer"],
                        f"{h['boundary_jump_px']}/{h['boundary_px']}",
                        f"{h['fill_status']}" + (f" ({h['fill_method']})" if h.get("fill_method") else ""),
                    ]
                    for h in largest_holes
                ],
            ),  # fmt: skip
            f"<p>{holes['vertical_hole_groups']:,} vertical-hole groups, {holes['walls']:,} fitted walls, "
            f"{holes['height_jump_px']:,} height-jump pixels.</p>",
        ]
    parts += _fill_section(holes.get("fill") or {}) + _flight_section(manifest.get("flightplan") or {})
    parts += ["<h2>Products</h2>", "<p>dsm.vrt (and dsm/*.tif), holes.gpkg, manifest.json: see docs/outputs.md.</p>"]
    parts.append("</body></html>")
    path = Path(path)
    path.write_text("\n".join(parts), encoding="utf-8")
    return path


def _fill_section(fill: dict[str, Any]) -> list[str]:
    if not fill:
        return []
    return [
        "<h2>Filling</h2>",
        f"<p>{fill['filled_area_m2']:,.0f} m² filled; {fill['skipped_area_m2']:,.0f} m² left nodata "
        "(holes too large to invent: see the flight plan). fill_mask.vrt says how each pixel was filled, "
        "fill_distance.vrt how far it lies from measured data.</p>",
        _table(["status", "holes"], [[k, f"{n:,}"] for k, n in fill["holes_by_status"].items()]),
        _table(["method", "holes"], [[k, f"{n:,}"] for k, n in fill["holes_by_method"].items()]),
    ]


def _flight_section(plan: dict[str, Any]) -> list[str]:
    if not plan:
        return []
    rows = [
        ["holes planned / listed", f"{plan['holes_planned']} / {plan['holes']}"],
        ["patterns, lanes, sorties", f"{plan['patterns']}, {plan['lanes']}, {plan['sorties']}"],
        ["route (greedy)", f"{plan['flown_route_m']:,.0f} m ({plan['greedy_route_m']:,.0f} m)"],
        ["sortie durations (s)", ", ".join(f"{d:,.0f}" for d in plan["sortie_durations_s"]) or "-"],
        ["altitude reference", plan["altitude_reference"]],
    ]
    return ["<h2>Re-flight plan</h2>", _table(["", ""], rows)]


def _table(header: list[str], rows: list[list[Any]]) -> str:
    head = f"<tr>{''.join(f'<th>{_e(h)}</th>' for h in header)}</tr>" if any(header) else ""
    body = "".join("<tr>" + "".join(f"<td>{_e(c)}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table>{head}{body}</table>"


def _e(value: Any) -> str:
    return html.escape(str(value))
