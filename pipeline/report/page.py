"""The report's HTML page: its sections, tables and style sheet (pure apart from :func:`write_report`)."""

from __future__ import annotations

import collections
import html
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from .maps import _legend, _map_svg
from .model import ReportInputs
from .text import _area, _cause_name, _count, _duration, _e, _fill_text, _number, _swatch, _table, _unit_m, _unit_name

_STYLE = """
body{font-family:system-ui,sans-serif;margin:2em auto;max-width:64em;padding:0 1em;color:#222;line-height:1.4}
h1{font-size:1.5em;margin-bottom:.2em}h2{font-size:1.15em;margin-top:1.8em;border-bottom:1px solid #ccc}
h3{font-size:1em;margin:1em 0 .3em}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}.muted{color:#666}
.cards{display:flex;flex-wrap:wrap;gap:.6em;margin:1em 0}
.card{border:1px solid #ddd;border-radius:6px;padding:.5em .8em;min-width:9em;background:#fafafa}
.card b{display:block;font-size:1.35em}.card span{color:#555;font-size:.85em}
.warn{background:#fff6e0;border-left:4px solid #e69f00;padding:.4em 1em;margin:1em 0}
.warn li{margin:.2em 0}.ok{background:#eef7ee;border-left:4px solid #3a3;padding:.4em 1em}
figure{margin:1em 0}figcaption{font-size:.9em;color:#444;margin-top:.3em}
svg.map{width:100%;height:auto;border:1px solid #bbb;background:#fff;display:block}
.zooms{display:grid;grid-template-columns:repeat(auto-fill,minmax(22em,1fr));gap:1em}
.legend{display:flex;flex-wrap:wrap;gap:.3em 1.2em;font-size:.9em;margin:.4em 0;align-items:center}
.legend svg{vertical-align:middle;margin-right:.3em}
.bar{background:#7a9cc6;height:.8em;display:inline-block;vertical-align:middle}
.dot{display:inline-block;width:.8em;height:.8em;border-radius:2px;vertical-align:middle;margin-right:.3em}
"""


def write_report(
    path: str | os.PathLike,
    manifest: dict[str, Any],
    largest_holes: list[dict[str, Any]],
    *,
    inputs: ReportInputs | None = None,
) -> Path:
    """Write ``report.html`` from a run's manifest, its largest holes and, optionally, map inputs.

    Parameters
    ----------
    path : path-like
        The HTML file to write.
    manifest : dict
        The run's manifest (``manifest.json``).
    largest_holes : list of dict
        Records of the ``holes`` layer, largest first (the manifest's ``holes.largest``).
    inputs : ReportInputs, optional
        Maps and outlines (:func:`read_report_inputs`); without them the page has tables only.

    Returns
    -------
    Path
        ``path``.
    """
    path = Path(path)
    path.write_text(render_report(manifest, largest_holes, inputs=inputs), encoding="utf-8")
    return path


def render_report(
    manifest: dict[str, Any], largest_holes: list[dict[str, Any]], *, inputs: ReportInputs | None = None
) -> str:
    """The report's HTML (see :func:`write_report`); pure."""
    holes = manifest.get("holes") or {}
    fill = holes.get("fill") or {}
    unit = _unit_name(manifest)
    parts = [
        "<!doctype html><html lang='en'><head><meta charset='utf-8'>",
        "<meta name='viewport' content='width=device-width,initial-scale=1'>",
        f"<title>holefill report: {_e(manifest.get('outputs', {}).get('dsm_vrt', 'run'))}</title>",
        f"<style>{_STYLE}</style></head><body>",
        "<h1>holefill run report</h1>",
        f"<p class='muted'>holefill {_e(manifest['holefill_version'])}, {_e(manifest['created'])}, "
        f"on {_e(manifest['host'])}; CRS {_e(manifest['crs']['name'])}</p>",
        _cards(manifest),
        _warnings(manifest, inputs),
    ]
    if inputs is not None:
        parts += _overview_section(manifest, largest_holes, inputs, unit)
    if holes:
        parts += _holes_section(holes, largest_holes, inputs)
    parts += _fill_section(fill, inputs) + _flight_section(manifest.get("flightplan") or {})
    parts += _survey_section(manifest)
    if manifest.get("skipped"):
        parts += [
            "<h2>Skipped tiles</h2>",
            _table(["file", "reason"], [[s["path"], s["reason"]] for s in manifest["skipped"]]),
        ]
    parts += ["<h2>Products</h2>", _products(manifest), "</body></html>"]
    return "\n".join(p for p in parts if p)


def _products(manifest: dict[str, Any]) -> str:
    """What this run wrote (the manifest's files, folders as ``name/*``): no product it did not write."""
    names: list[str] = []
    for record in (manifest.get("outputs") or {}).get("files", []):
        first, _, rest = str(record["path"]).partition("/")
        name = f"{first}/*{Path(rest).suffix}" if rest else first
        if name not in names:
            names.append(name)
    listed = ", ".join(html.escape(n) for n in names + ["manifest.json"])
    hint = (
        "Open dsm.vrt and holes.gpkg in QGIS or ArcGIS." if "holes.gpkg" in names else "Open dsm.vrt in QGIS or ArcGIS."
    )
    return f"<p>{listed}: see docs/outputs.md. {hint}</p>"


# -- sections ------------------------------------------------------------------------


def _cards(manifest: dict[str, Any]) -> str:
    summary = manifest["summary"]
    holes = manifest.get("holes") or {}
    fill = holes.get("fill") or {}
    cards = [
        (f"{summary['tiles']:,}", "tiles"),
        (_count(summary["points_read"]), "points read"),
        (_count(summary.get("points_used", summary["points_read"])), "points used"),
    ]
    if holes:
        cards += [
            (_area(holes.get("aoi_area_m2", 0.0)), "survey area"),
            (f"{holes['listed']:,}", f"holes ≥ {holes['min_area_m2']:.3g} m²"),
            (_area(holes["area_m2"]), "in holes"),
        ]
    if fill:
        cards += [(_area(fill["filled_area_m2"]), "filled"), (_area(fill["skipped_area_m2"]), "left without data")]
    cards.append((_duration(summary["seconds"]), "run time"))
    return (
        "<div class='cards'>"
        + "".join(f"<div class='card'><b>{_e(v)}</b><span>{_e(k)}</span></div>" for v, k in cards)
        + "</div>"
    )


def _warnings(manifest: dict[str, Any], inputs: ReportInputs | None) -> str:
    """What a survey engineer should look at before using the result."""
    items = []
    summary = manifest["summary"]
    holes = manifest.get("holes") or {}
    fill = holes.get("fill") or {}
    if manifest.get("complete") is False:
        items.append("the manifest says this result is <b>not complete</b>")
    if manifest.get("skipped"):
        items.append(f"{len(manifest['skipped']):,} input tiles were skipped (listed under Skipped tiles)")
    if summary.get("points_outside"):
        items.append(
            f"{summary['points_outside']:,} points lie outside their tile's header bounds and were not used "
            "(see the log and manifest.json, inputs)"
        )
    if summary.get("points_used", 1) == 0:
        items.append("no point was used: check the filter settings (filter.keep_classes, filter.drop_classes)")
    if holes:
        aoi = holes.get("aoi_area_m2") or 0.0
        if aoi > 0 and holes["area_m2"] / aoi > 0.05:
            items.append(f"holes cover {holes['area_m2'] / aoi:.1%} of the survey area")
        unknown = holes["by_cause"].get("unknown", 0)
        if unknown:
            items.append(f"{unknown:,} hole(s) of unknown cause: no rule explained them (docs/holes.md, Causes)")
        if fill.get("skipped_area_m2"):
            skipped = {k: n for k, n in fill["holes_by_status"].items() if k.startswith("skipped")}
            items.append(
                f"{sum(skipped.values()):,} hole(s), {_area(fill['skipped_area_m2'])}, left without data in the DSM ("
                + ", ".join(f"{n} {k.removeprefix('skipped: ')}" for k, n in skipped.items())
                + ")"
            )
    plan = manifest.get("flightplan") or {}
    unplanned = {
        hole: reason
        for hole, reason in (plan.get("holes_not_planned") or {}).items()
        if "is not re-flown" not in reason
    }
    if "not_planned" in plan:
        items.append(f"no re-flight plan: {_e(plan['not_planned'])}")
    if unplanned:
        sample = "; ".join(f"hole {h}: {r}" for h, r in list(unplanned.items())[:5])
        items.append(f"{len(unplanned):,} hole(s) to re-fly could not be planned ({_e(sample)})")
    if summary.get("resumed_tasks"):
        items.append(f"a resumed run: {summary['resumed_tasks']:,} tasks were taken from the interrupted run")
    if not items:
        return "<div class='ok'>Nothing to look at first: no skipped tile, no hole left without data.</div>"
    return "<div class='warn'><b>Look at first</b><ul>" + "".join(f"<li>{i}</li>" for i in items) + "</ul></div>"


def _overview_section(
    manifest: dict[str, Any], largest_holes: list[dict[str, Any]], inputs: ReportInputs, unit: str
) -> list[str]:
    view = inputs.overview
    drawn = [h for h in inputs.holes if h.rings]
    numbered = {hole_id: i + 1 for i, (hole_id, _) in enumerate(inputs.zooms)}
    lo, hi = view.images.height_range
    svg = _map_svg(
        view,
        inputs,
        numbered=numbered,
        unit_m=_unit_m(manifest),
        map_id="ov",
        display_px=960,
        show_whole_route=True,
    )
    xmin, ymin, xmax, ymax = view.bounds
    ny, nx = view.dsm.shape
    note = f"{len(drawn):,} of {len(inputs.holes):,} holes outlined" + (
        " (the smallest are too small at this scale)" if len(drawn) < len(inputs.holes) else ""
    )
    parts = [
        "<h2>Overview</h2>",
        "<figure>",
        svg,
        _legend(inputs, (lo, hi), manifest),
        f"<figcaption>{_e(manifest['crs']['name'])}: x {xmin:,.0f} to {xmax:,.0f}, y {ymin:,.0f} to {ymax:,.0f} {unit}; "
        f"map pixel {(xmax - xmin) / nx:,.3g} {unit}; {note}. Hover a hole for its figures. Numbers mark the "
        "zooms below.</figcaption>",
        "</figure>",
    ]
    if inputs.zooms:
        by_id = {h.hole_id: h for h in inputs.holes}
        parts += ["<h3>The largest holes, closer</h3>", "<div class='zooms'>"]
        for i, (hole_id, zoom) in enumerate(inputs.zooms):
            hole = by_id.get(hole_id)
            zsvg = _map_svg(
                zoom,
                inputs,
                numbered={},
                unit_m=_unit_m(manifest),
                map_id=f"z{i}",
                display_px=470,
            )
            caption = f"<b>{i + 1}</b>: hole {hole_id}"
            if hole is not None:
                caption += f", {_cause_name(hole.cause)} ({_e(hole.cause_rule)}), {hole.area_m2:,.0f} m², " + _e(
                    _fill_text(hole.fill_status, hole.fill_method)
                )
            parts += ["<figure>", zsvg, f"<figcaption>{caption}</figcaption>", "</figure>"]
        parts.append("</div>")
    return parts


def _holes_section(
    holes: dict[str, Any], largest_holes: list[dict[str, Any]], inputs: ReportInputs | None
) -> list[str]:
    aoi = holes.get("aoi_area_m2") or 0.0
    area_by_cause: dict[str, float] = collections.defaultdict(float)
    for h in inputs.holes if inputs else ():
        area_by_cause[h.cause] += h.area_m2
    cause_rows = []
    for cause, n in holes["by_cause"].items():
        row = [_swatch(cause) + _cause_name(cause), f"{n:,}"]
        if inputs is not None:
            a = area_by_cause.get(cause, 0.0)
            row += [f"{a:,.0f}", f"{a / aoi:.2%}" if aoi else "-"]
        cause_rows.append(row)
    cause_head = ["cause", "holes"] + (["area m²", "of survey area"] if inputs is not None else [])
    type_rows = [
        [kind, f"{n:,}"] + ([f"{inputs.part_area_by_type.get(kind, 0.0):,.0f}"] if inputs is not None else [])
        for kind, n in holes["parts_by_type"].items()
    ]
    return [
        "<h2>Holes</h2>",
        f"<p>{holes['listed']:,} holes of at least {holes['min_area_m2']:.3g} m², {holes['area_m2']:,.0f} m² in all; "
        f"{holes['small_voids']:,} smaller voids ({holes['small_void_area_m2']:,.0f} m²) counted, not listed. "
        f"Survey area (AOI): {aoi:,.0f} m².</p>",
        "<h3>By cause</h3>",
        _table(cause_head, cause_rows, raw_first=True),
        "<h3>Cell parts by type</h3>",
        "<p class='muted'>closed; open type I (across cell edges inside the AOI) or II (open to the AOI boundary), "
        "shapes A hollow, B semi-enclosed, C crossing, D island (docs/holes.md)</p>",
        _table(["type", "parts"] + (["area m²"] if inputs is not None else []), type_rows),
        "<h3>Largest holes</h3>",
        _table(
            ["hole", "area m²", "cause", "rule", "cells", "layers", "boundary jumps", "fill", "fill error m"],
            [
                [
                    h["hole_id"],
                    f"{h['area_m2']:,.0f}",
                    h["cause"],
                    h["cause_rule"],
                    h["n_cells"],
                    h["max_layer"],
                    f"{h['boundary_jump_px']}/{h['boundary_px']}",
                    _fill_text(h["fill_status"], h.get("fill_method")),
                    _number(h.get("fill_error_m"), ".2f"),
                ]
                for h in largest_holes
            ],
        ),
        f"<p>{holes['vertical_hole_groups']:,} vertical-hole groups, {holes['walls']:,} fitted walls, "
        f"{holes['height_jump_px']:,} height-jump pixels.</p>",
    ]


def _fill_split(fill: dict[str, Any]) -> str:
    """' (A m² in listed holes, B m² in small voids)', where the manifest splits the filled area."""
    if "filled_holes_area_m2" not in fill:
        return ""
    return (
        f" ({fill['filled_holes_area_m2']:,.0f} m² in listed holes, "
        f"{fill['filled_small_voids_area_m2']:,.0f} m² in small voids and sampling gaps)"
    )


def _fill_section(fill: dict[str, Any], inputs: ReportInputs | None) -> list[str]:
    if not fill:
        return []
    parts = [
        "<h2>Filling</h2>",
        f"<p>{fill['filled_area_m2']:,.0f} m² filled{_fill_split(fill)}; {fill['skipped_area_m2']:,.0f} m² left nodata "
        "(holes too large to invent: see the flight plan). fill_mask.vrt says how each pixel was filled, "
        "fill_distance.vrt how far it lies from measured data.</p>",
    ]
    by_status: dict[str, list[float]] = collections.defaultdict(list)
    by_method: dict[str, list[float]] = collections.defaultdict(list)
    errors = []
    errors_by_cause: dict[str, list[float]] = collections.defaultdict(list)
    for h in inputs.holes if inputs else ():
        by_status[h.fill_status].append(h.area_m2)
        if h.fill_method:
            by_method[h.fill_method].append(h.area_m2)
        if h.fill_error_m is not None and math.isfinite(h.fill_error_m):
            errors.append(h.fill_error_m)
            errors_by_cause[h.cause].append(h.fill_error_m)

    def rows(counts: dict[str, int], areas: dict[str, list[float]]) -> list[list[Any]]:
        listed = [[f"{len(areas.get(k, [])):,}", f"{sum(areas.get(k, [])):,.0f}"] for k in counts] if inputs else []
        return [[k, *(listed[i] if inputs else []), f"{n:,}"] for i, (k, n) in enumerate(counts.items())]

    # the stage counts every void it filled, the small voids under the listing's area too; the
    # listed holes are those of holes.gpkg
    columns = ["listed holes", "area m² (listed holes)"] if inputs else []
    every = "all voids (small ones included)"
    parts += [
        "<h3>Holes by fill status and by method</h3>",
        "<div class='cards'>",
        _table(["status", *columns, every], rows(fill["holes_by_status"], by_status)),
        _table(["method", *columns, every], rows(fill["holes_by_method"], by_method)),
        "</div>",
    ]
    if errors:
        e = np.asarray(errors)
        parts.append(
            "<p>Estimated fill error (water: spread of its edge level; others: leave-rim-out RMSE, "
            f"{len(e):,} holes): median {np.median(e):.2f}, 90th percentile {np.percentile(e, 90):.2f}, "
            f"largest {e.max():.2f} (height units).</p>"
        )
        # water: the spread of the heights its edge level came from; the rest: the rim cross-validation
        parts += [
            "<h3>Estimated fill error by cause</h3>",
            _table(
                ["cause", "holes", "median", "90th percentile", "largest", "from"],
                [
                    [
                        cause,
                        f"{len(v):,}",
                        f"{np.median(v):.2f}",
                        f"{np.percentile(v, 90):.2f}",
                        f"{max(v):.2f}",
                        "spread of its edge level" if cause == "water" else "withheld-rim cross-validation",
                    ]
                    for cause, v in sorted(errors_by_cause.items())
                ],
            ),
        ]
    return parts


def _flight_section(plan: dict[str, Any]) -> list[str]:
    if not plan:
        return []
    if "not_planned" in plan:
        return ["<h2>Re-flight plan</h2>", f"<p>None: {_e(plan['not_planned'])}.</p>"]
    rows = [
        ["holes planned / listed", f"{plan['holes_planned']} / {plan['holes']}"],
        ["patterns, lanes, sorties", f"{plan['patterns']}, {plan['lanes']}, {plan['sorties']}"],
        ["route (greedy)", f"{plan['flown_route_m']:,.0f} m ({plan['greedy_route_m']:,.0f} m)"],
        ["sortie durations (s)", ", ".join(f"{d:,.0f}" for d in plan["sortie_durations_s"]) or "-"],
        ["least clearance per sortie (m)", _clearances(plan.get("sortie_min_clearance_m"))],
        ["take-off", _take_off(plan)],
        ["altitude reference", plan["altitude_reference"]],
    ]
    shares: dict[str, float] = plan.get("hole_visible_share") or {}
    if shares:
        values = sorted(shares.values())
        least = min(shares, key=lambda hole: shares[hole])
        rows.append(
            [
                "hole ground seen from its lanes",
                f"least {values[0]:.0%} (hole {least}), median {values[len(values) // 2]:.0%}"
                f", over {len(values)} planned holes",
            ]
        )
    return ["<h2>Re-flight plan</h2>", _table(["", ""], rows)]


def _clearances(values: list[float | None] | None) -> str:
    """Each sortie's least clearance above the highest surface near its legs (flightplan.min_clearance_m)."""
    return ", ".join("-" if v is None else f"{v:,.1f}" for v in values) if values else "-"


def _take_off(plan: dict[str, Any]) -> str:
    """Where the drone takes off, the ground height there and where it comes from; the warning if any (plain text: the table escapes it)."""
    home = plan.get("home")
    if not home:
        return "-"
    text = f"({home[0]:,.1f}, {home[1]:,.1f})"
    if plan.get("home_ground_m") is not None:
        text += f", ground {plan['home_ground_m']:,.2f}"
    if plan.get("home_height_from"):
        text += f" (from {plan['home_height_from']})"
    if plan.get("home_warning"):
        text += f"; warning: {plan['home_warning']}"
    return text


def _survey_section(manifest: dict[str, Any]) -> list[str]:
    summary = manifest["summary"]
    grid = manifest["grid"]
    stages = summary.get("stage_seconds") or {}
    longest = max(stages.values(), default=0.0) or 1.0
    timing_rows = [
        [name, f"{s:,.1f}", f"<span class='bar' style='width:{12 * s / longest:.2f}em'></span>"]
        for name, s in stages.items()
    ]
    return [
        "<h2>Survey and timings</h2>",
        _table(
            ["", ""],
            [
                ["tiles read", f"{summary['tiles']:,}"],
                ["points read / used", f"{summary['points_read']:,} / {summary['points_used']:,}"],
                ["CRS", manifest["crs"]["name"]],
                ["heights", _heights_text(manifest.get("heights", {}))],
                ["pixel size (CRS units)", f"{grid['resolution']:g}"],
                ["grid", f"{grid['width']:,} x {grid['height']:,} pixels, {summary['cells']} cells"],
                ["empty pixels", f"{summary['empty_pixels']:,}"],
                ["run time", f"{summary['seconds']:.1f} s ({summary['points_per_second'] / 1e6:.2f} M points/s)"],
            ],
        ),
        "<h3>Time by stage (s)</h3>",
        _table(["stage", "seconds", ""], timing_rows, raw_last=True),
    ]


def _heights_text(heights: dict[str, Any]) -> str:
    """The manifest's ``heights`` in words (:mod:`pipeline.survey.ground_level`)."""
    if heights.get("heights") == "above_ground":
        return (
            f"above the ground: {heights['ground_points_at_zero']:,} of {heights['ground_points']:,} ground "
            "points lie at z = 0, so the DSM is a height-above-ground model"
        )
    return "elevations"
