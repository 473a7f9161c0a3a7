"""The run report: one self-contained HTML page a survey engineer reads after a run.

Rendered from the manifest (so it never disagrees with it), the largest holes of the
``holes`` layer and, when given, a :class:`ReportInputs`: small, already downsampled
rasters and hole outlines for the maps. The page needs no template engine, no
external asset and no network: the maps are inline SVG over PNG images embedded as
data URIs (encoded here with the standard library's ``zlib``).

:func:`write_report` is pure apart from writing the file. :func:`read_report_inputs`
builds its map inputs from a finished run's output folder (``dsm.vrt``,
``fill_mask.vrt``, ``holes.gpkg``, ``flightplan.gpkg``), bounded in size whatever the
survey's extent.
"""

from __future__ import annotations

import base64
import collections
import html
import math
import os
import struct
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

#: Longest side, in pixels, of the overview map's rasters (bounds the report's size).
MAX_MAP_PX = 1500
#: Longest side, in pixels, of each zoom on a large hole.
ZOOM_PX = 480
#: Hole outlines drawn at most (vertices, all maps together): the largest holes first.
MAX_HOLE_VERTICES = 200_000

#: Colours of the hole causes (colour-blind safe: Okabe-Ito).
CAUSE_COLOURS = {
    "occlusion": "#e69f00",
    "water": "#0072b2",
    "missed_coverage": "#d55e00",
    "unknown": "#cc79a7",
}
_OTHER_COLOUR = "#666666"
#: Elevation ramp of the DSM (fraction of the 2-98 % height range -> RGB), shaded by the hillshade.
_RAMP = (
    (0.00, (46, 112, 72)),
    (0.30, (150, 182, 96)),
    (0.55, (233, 217, 148)),
    (0.80, (186, 134, 86)),
    (1.00, (246, 244, 240)),
)
_FILL_HATCH = "#1f3f99"

Bounds = tuple[float, float, float, float]


@dataclass(frozen=True)
class MapRaster:
    """The rasters of one map, north up (row 0 is the northern edge).

    Attributes
    ----------
    dsm : ndarray of shape (M, N), float32
        Heights, NaN where there is no value (outside the survey area, holes left unfilled).
    bounds : tuple of float
        ``(xmin, ymin, xmax, ymax)`` of the array in the survey CRS.
    filled : ndarray of shape (M, N), bool, optional
        True on pixels filled by holefill (``fill_mask`` codes 1-254).
    """

    dsm: np.ndarray
    bounds: Bounds
    filled: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.dsm.ndim != 2 or min(self.dsm.shape) < 1:
            raise ValueError(f"MapRaster.dsm must be a non-empty 2-D array, got shape {self.dsm.shape}")
        if self.filled is not None and self.filled.shape != self.dsm.shape:
            raise ValueError(f"MapRaster.filled has shape {self.filled.shape}, the DSM {self.dsm.shape}")
        xmin, ymin, xmax, ymax = self.bounds
        if not (xmax > xmin and ymax > ymin):
            raise ValueError(f"MapRaster.bounds must be (xmin, ymin, xmax, ymax), got {self.bounds}")


@dataclass(frozen=True)
class MapHole:
    """One hole of the ``holes`` layer as the report needs it.

    ``rings`` are the exterior and interior rings of each of its polygons, arrays of
    shape (K, 2) of x, y in the survey CRS (drawn even-odd); empty when the hole is not
    drawn (too small at the map's scale or over the vertex budget).
    """

    hole_id: int
    cause: str
    area_m2: float
    fill_status: str
    fill_method: str | None = None
    cause_rule: str = ""
    fill_error_m: float | None = None
    bounds: Bounds | None = None
    label_xy: tuple[float, float] | None = None
    rings: tuple[np.ndarray, ...] = ()


@dataclass(frozen=True)
class ReportInputs:
    """What the report's maps and area tables are drawn from (see :func:`read_report_inputs`).

    Attributes
    ----------
    overview : MapRaster
        The whole survey grid, at most :data:`MAX_MAP_PX` on the long side.
    holes : tuple of MapHole
        Every hole of the ``holes`` layer (outlines for those drawn).
    zooms : tuple of (int, MapRaster)
        A closer map around each of the largest holes: ``(hole_id, raster)``.
    route : tuple of ndarray of shape (K, 2)
        The re-flight route's polylines (``flightplan.gpkg`` layer ``route``), if any.
    survey_area : tuple of ndarray of shape (K, 2)
        Rings of the survey area (AOI).
    part_area_by_type : dict
        Area (m²) of the ``hole_parts`` by type, keyed like the manifest's ``parts_by_type``.
    """

    overview: MapRaster
    holes: tuple[MapHole, ...] = ()
    zooms: tuple[tuple[int, MapRaster], ...] = ()
    route: tuple[np.ndarray, ...] = ()
    survey_area: tuple[np.ndarray, ...] = ()
    part_area_by_type: dict[str, float] = field(default_factory=dict)


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
    parts += [
        "<h2>Products</h2>",
        "<p>dsm.vrt (and dsm/*.tif), fill_mask.vrt, fill_distance.vrt, holes.gpkg, flightplan.gpkg and the "
        "drone files, manifest.json: see docs/outputs.md. Open dsm.vrt and holes.gpkg in QGIS or ArcGIS.</p>",
        "</body></html>",
    ]
    return "\n".join(p for p in parts if p)


# -- sections ------------------------------------------------------------------------


def _cards(manifest: dict[str, Any]) -> str:
    summary = manifest["summary"]
    holes = manifest.get("holes") or {}
    fill = holes.get("fill") or {}
    cards = [
        (f"{summary['tiles']:,}", "tiles"),
        (_count(summary["points_read"]), "points read"),
    ]
    if holes:
        cards += [
            (_area(holes.get("aoi_area_m2", 0.0)), "survey area"),
            (f"{holes['listed']:,}", f"holes ≥ {holes['min_area_m2']:g} m²"),
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
    lo, hi = _height_range(view.dsm)
    svg = _map_svg(
        view,
        inputs,
        numbered=numbered,
        height_range=(lo, hi),
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
                height_range=_height_range(zoom.dsm),
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
        f"<p>{holes['listed']:,} holes of at least {holes['min_area_m2']:g} m², {holes['area_m2']:,.0f} m² in all; "
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


def _fill_section(fill: dict[str, Any], inputs: ReportInputs | None) -> list[str]:
    if not fill:
        return []
    parts = [
        "<h2>Filling</h2>",
        f"<p>{fill['filled_area_m2']:,.0f} m² filled; {fill['skipped_area_m2']:,.0f} m² left nodata "
        "(holes too large to invent: see the flight plan). fill_mask.vrt says how each pixel was filled, "
        "fill_distance.vrt how far it lies from measured data.</p>",
    ]
    by_status: dict[str, list[float]] = collections.defaultdict(list)
    by_method: dict[str, list[float]] = collections.defaultdict(list)
    errors = []
    for h in inputs.holes if inputs else ():
        by_status[h.fill_status].append(h.area_m2)
        if h.fill_method:
            by_method[h.fill_method].append(h.area_m2)
        if h.fill_error_m is not None and math.isfinite(h.fill_error_m):
            errors.append(h.fill_error_m)

    def rows(counts: dict[str, int], areas: dict[str, list[float]]) -> list[list[Any]]:
        return [[k, f"{n:,}"] + ([f"{sum(areas.get(k, [])):,.0f}"] if inputs else []) for k, n in counts.items()]

    extra = ["area m² (listed holes)"] if inputs else []
    parts += [
        "<h3>Holes by fill status and by method</h3>",
        "<div class='cards'>",
        _table(["status", "holes"] + extra, rows(fill["holes_by_status"], by_status)),
        _table(["method", "holes"] + extra, rows(fill["holes_by_method"], by_method)),
        "</div>",
    ]
    if errors:
        e = np.asarray(errors)
        parts.append(
            "<p>Estimated fill error (leave-rim-out RMSE, "
            f"{len(e):,} holes): median {np.median(e):.2f}, 90th percentile {np.percentile(e, 90):.2f}, "
            f"largest {e.max():.2f} (height units).</p>"
        )
    return parts


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
                ["pixel size (CRS units)", f"{grid['resolution']:g}"],
                ["grid", f"{grid['width']:,} x {grid['height']:,} pixels, {summary['cells']} cells"],
                ["empty pixels", f"{summary['empty_pixels']:,}"],
                ["run time", f"{summary['seconds']:.1f} s ({summary['points_per_second'] / 1e6:.2f} M points/s)"],
            ],
        ),
        "<h3>Time by stage (s)</h3>",
        _table(["stage", "seconds", ""], timing_rows, raw_last=True),
    ]


# -- maps ------------------------------------------------------------------------------


def _map_svg(
    view: MapRaster,
    inputs: ReportInputs,
    *,
    numbered: dict[int, int],
    height_range: tuple[float, float],
    unit_m: float,
    map_id: str,
    display_px: float,
    show_whole_route: bool = False,
) -> str:
    """One map: shaded relief, filled pixels hatched, holes by cause, route, AOI, scale bar.

    The SVG's user unit is one pixel of ``view``; ``display_px`` is the width the map is
    expected to take on screen, so that lines, markers and text keep a readable size.
    With ``show_whole_route`` the view grows to hold the whole re-flight route.
    """
    ny, nx = view.dsm.shape
    xmin, ymin, xmax, ymax = view.bounds
    sx, sy = (xmax - xmin) / nx, (ymax - ymin) / ny
    uid = map_id

    def to_px(xy: np.ndarray) -> np.ndarray:
        return np.column_stack([(xy[:, 0] - xmin) / sx, (ymax - xy[:, 1]) / sy])

    route = [to_px(line) for line in inputs.route if len(line)]
    box = [0.0, 0.0, float(nx), float(ny)]  # x0, y0, x1, y1 in view pixels
    if show_whole_route and route:
        points = np.vstack(route)
        margin = 0.02 * max(nx, ny)
        box = [
            min(box[0], points[:, 0].min() - margin),
            min(box[1], points[:, 1].min() - margin),
            max(box[2], points[:, 0].max() + margin),
            max(box[3], points[:, 1].max() + margin),
        ]
    bw, bh = box[2] - box[0], box[3] - box[1]
    unit = bw / display_px  # view pixels per screen pixel
    hatch = 8 * unit
    relief = shaded_relief(view.dsm, pixel_size=(sx, sy), height_range=height_range)
    has_fill = view.filled is not None and bool(view.filled.any())
    out = [
        f"<svg class='map' xmlns='http://www.w3.org/2000/svg' viewBox='{box[0]:.1f} {box[1]:.1f} {bw:.1f} {bh:.1f}' "
        f"preserveAspectRatio='xMidYMid meet' role='img'>",
        "<defs>",
        f"<pattern id='hatch-{uid}' patternUnits='userSpaceOnUse' width='{hatch:.3g}' height='{hatch:.3g}' "
        f"patternTransform='rotate(45)'><rect width='{hatch / 2:.3g}' height='{hatch:.3g}' fill='{_FILL_HATCH}'/>"
        "</pattern>",
    ]
    if has_fill:
        mask_png = encode_png(np.where(view.filled, 255, 0).astype(np.uint8))  # type: ignore[arg-type]
        out.append(
            f"<mask id='filled-{uid}' maskUnits='userSpaceOnUse' x='0' y='0' width='{nx}' height='{ny}'>"
            f"<image width='{nx}' height='{ny}' preserveAspectRatio='none' style='image-rendering:pixelated' "
            f"href='{_data_uri(mask_png)}'/></mask>"
        )
    out += [
        "</defs>",
        f"<rect x='{box[0]:.1f}' y='{box[1]:.1f}' width='{bw:.1f}' height='{bh:.1f}' fill='#fbfbfb'/>",
        f"<rect width='{nx}' height='{ny}' fill='#ececec'/>",
        # a map shown larger than its pixels (a zoom): show the DSM's pixels, not a blur
        f"<image width='{nx}' height='{ny}' preserveAspectRatio='none' "
        f"style='image-rendering:{'pixelated' if unit < 0.5 else 'auto'}' "
        f"href='{_data_uri(encode_png(relief))}'/>",
    ]
    if has_fill:
        out.append(
            f"<rect width='{nx}' height='{ny}' fill='url(#hatch-{uid})' opacity='0.75' mask='url(#filled-{uid})'/>"
        )
    for ring in inputs.survey_area:
        out.append(
            f"<path d='{_path(to_px(ring))}' fill='none' stroke='#111' stroke-width='1.2' "
            "stroke-dasharray='6 4' vector-effect='non-scaling-stroke'/>"
        )
    for hole in inputs.holes:
        if not hole.rings or not _overlaps(hole.bounds, view.bounds):
            continue
        colour = CAUSE_COLOURS.get(hole.cause, _OTHER_COLOUR)
        d = " ".join(_path(to_px(ring)) for ring in hole.rings)
        title = (
            f"hole {hole.hole_id}: {hole.cause.replace('_', ' ')} ({hole.cause_rule}), {hole.area_m2:,.0f} m², "
            f"{_fill_text(hole.fill_status, hole.fill_method)}"
        )
        out.append(
            f"<path d='{d}' fill='{colour}' fill-opacity='0.22' fill-rule='evenodd' stroke='{colour}' "
            f"stroke-width='1.6' vector-effect='non-scaling-stroke'><title>{_e(title)}</title></path>"
        )
    for line in route:
        d = _path(line, close=False)
        out.append(
            f"<path d='{d}' fill='none' stroke='#fff' stroke-width='4.5' stroke-linejoin='round' "
            "vector-effect='non-scaling-stroke' opacity='0.85'/>"
            f"<path d='{d}' fill='none' stroke='#111' stroke-width='2' stroke-linejoin='round' "
            "vector-effect='non-scaling-stroke'><title>re-flight route</title></path>"
        )
    if route:
        hx, hy = route[0][0]
        out.append(_marker(hx, hy, "H", unit, fill="#111", title="take-off and landing"))
    by_id = {h.hole_id: h for h in inputs.holes}
    for hole_id, number in numbered.items():
        marked = by_id.get(hole_id)
        if marked is not None and marked.label_xy is not None:
            px, py = to_px(np.asarray([marked.label_xy]))[0]
            out.append(_marker(px, py, str(number), unit, fill="#222", title=f"zoom {number}: hole {hole_id}"))
    out.append(_scale_bar((box[0], box[3]), bw, sx, unit_m, unit))
    out.append("</svg>")
    return "".join(out)


def _marker(x: float, y: float, text: str, unit: float, *, fill: str, title: str) -> str:
    """A numbered disc, 11 screen pixels in radius."""
    r = 11 * unit
    return (
        f"<g><title>{_e(title)}</title><circle cx='{x:.1f}' cy='{y:.1f}' r='{r:.2f}' fill='{fill}' stroke='#fff' "
        f"stroke-width='{r / 5:.2f}'/><text x='{x:.1f}' y='{y:.1f}' dy='0.35em' text-anchor='middle' "
        f"font-size='{r * 1.2:.2f}' font-family='sans-serif' font-weight='bold' fill='#fff'>{_e(text)}</text></g>"
    )


def _scale_bar(corner: tuple[float, float], width: float, pixel: float, unit_m: float, unit: float) -> str:
    """A scale bar about a fifth of the map's width with a round length, at the bottom-left ``corner``."""
    target_m = width * pixel * unit_m / 5
    step = 10 ** math.floor(math.log10(target_m)) if target_m > 0 else 1.0
    length_m = max(m * step for m in (1, 2, 5) if m * step <= target_m) if target_m >= step else step
    bar = length_m / unit_m / pixel
    label = f"{length_m / 1000:g} km" if length_m >= 1000 else f"{length_m:g} m"
    h = 14 * unit  # text height: 14 screen pixels
    x0, y0 = corner[0] + h, corner[1] - 1.2 * h
    return (
        f"<g font-family='sans-serif' font-size='{h:.2f}'>"
        f"<rect x='{x0 - h / 2:.1f}' y='{y0 - 1.5 * h:.1f}' width='{bar + 3.6 * h:.1f}' height='{2.2 * h:.1f}' "
        f"fill='#fff' opacity='0.85' rx='{h / 4:.1f}'/>"
        f"<rect x='{x0:.1f}' y='{y0:.1f}' width='{bar / 2:.1f}' height='{h / 3:.2f}' fill='#111'/>"
        f"<rect x='{x0 + bar / 2:.1f}' y='{y0:.1f}' width='{bar / 2:.1f}' height='{h / 3:.2f}' "
        f"fill='#fff' stroke='#111' stroke-width='{h / 14:.2f}'/>"
        f"<text x='{x0:.1f}' y='{y0 - h / 4:.1f}' text-anchor='middle'>0</text>"
        f"<text x='{x0 + bar:.1f}' y='{y0 - h / 4:.1f}' text-anchor='middle'>{_e(label)}</text>"
        f"<text x='{x0 + bar + 2.2 * h:.1f}' y='{y0 + h / 3:.1f}' text-anchor='middle' font-weight='bold'>N↑</text>"
        "</g>"
    )


def _legend(inputs: ReportInputs, height_range: tuple[float, float], manifest: dict[str, Any]) -> str:
    counts = collections.Counter(h.cause for h in inputs.holes)
    items = [
        f"<span><span class='dot' style='background:{CAUSE_COLOURS.get(c, _OTHER_COLOUR)};opacity:.8'></span>"
        f"{_cause_name(c)} ({counts[c]:,})</span>"
        for c in [*CAUSE_COLOURS, *sorted(set(counts) - set(CAUSE_COLOURS))]
        if counts[c]
    ]
    items.append(
        "<span><svg width='16' height='12'><defs><pattern id='lg-hatch' patternUnits='userSpaceOnUse' width='4' "
        f"height='4' patternTransform='rotate(45)'><rect width='2' height='4' fill='{_FILL_HATCH}'/></pattern></defs>"
        "<rect width='16' height='12' fill='url(#lg-hatch)' opacity='.75'/></svg>filled by holefill</span>"
    )
    items.append(
        "<span><span class='dot' style='background:#f2f2f2;border:1px solid #bbb'></span>no data "
        "(outside the survey, holes left unfilled)</span>"
    )
    if inputs.route:
        items.append(
            "<span><svg width='22' height='8'><line x1='0' y1='4' x2='22' y2='4' stroke='#111' stroke-width='2'/>"
            "</svg>re-flight route (H: take-off)</span>"
        )
    if inputs.survey_area:
        items.append(
            "<span><svg width='22' height='8'><line x1='0' y1='4' x2='22' y2='4' stroke='#111' "
            "stroke-dasharray='4 3'/></svg>survey area</span>"
        )
    lo, hi = height_range
    stops = "".join(f"<stop offset='{f:.2f}' stop-color='rgb{c}'/>" for f, c in _RAMP)
    items.append(
        f"<span>{lo:,.1f}<svg width='90' height='10' style='margin:0 .3em'><defs><linearGradient id='lg-ramp'>{stops}"
        "</linearGradient></defs><rect width='90' height='10' fill='url(#lg-ramp)'/></svg>"
        f"{hi:,.1f} height ({_unit_name(manifest)})</span>"
    )
    return "<div class='legend'>" + "".join(items) + "</div>"


def shaded_relief(
    dsm: np.ndarray,
    *,
    pixel_size: tuple[float, float],
    height_range: tuple[float, float] | None = None,
    azimuth_deg: float = 315.0,
    altitude_deg: float = 45.0,
) -> np.ndarray:
    """An RGBA image of a DSM: heights coloured on an elevation ramp, shaded by a hillshade.

    Parameters
    ----------
    dsm : ndarray of shape (M, N)
        Heights, north up; NaN where there is no value (transparent in the image).
    pixel_size : tuple of float
        ``(dx, dy)`` pixel size in the CRS unit.
    height_range : tuple of float, optional
        Heights at the ends of the ramp (default: the 2nd and 98th percentiles).
    azimuth_deg, altitude_deg : float
        The light's direction (clockwise from north) and elevation.

    Returns
    -------
    ndarray of shape (M, N, 4), uint8

    Notes
    -----
    A coarse map flattens slopes: the heights are exaggerated by the square root of the
    pixel size (1 to 5 times) so a 100 km survey still shows its relief.
    """
    z = np.asarray(dsm, dtype=np.float64)
    valid = np.isfinite(z)
    rgba = np.zeros((*z.shape, 4), np.uint8)
    if not valid.any():
        return rgba
    if not valid.all():  # nearest valid height under the gaps, so their edges cast no shadow
        from scipy import ndimage as ndi

        index = ndi.distance_transform_edt(~valid, return_distances=False, return_indices=True)
        z = z[tuple(index)]
    lo, hi = height_range if height_range is not None else _height_range(dsm)
    dx, dy = (abs(float(p)) for p in pixel_size)
    exaggeration = min(5.0, max(1.0, math.sqrt(max(dx, dy))))
    if min(z.shape) >= 2:
        d_row, d_col = np.gradient(z * exaggeration, dy, dx)
    else:
        d_row = d_col = np.zeros_like(z)
    dz_east, dz_north = d_col, -d_row
    az, alt = math.radians(azimuth_deg), math.radians(altitude_deg)
    light = (math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt))
    shade = (-dz_east * light[0] - dz_north * light[1] + light[2]) / np.sqrt(1 + dz_east**2 + dz_north**2)
    shade = np.clip(shade, 0, 1) / max(math.sin(alt), 1e-6)  # flat ground: 1
    t = np.clip((z - lo) / (hi - lo), 0, 1) if hi > lo else np.full(z.shape, 0.5)
    fractions = [f for f, _ in _RAMP]
    for channel in range(3):
        colour = np.interp(t, fractions, [c[channel] for _, c in _RAMP])
        rgba[..., channel] = np.clip(colour * (0.35 + 0.65 * np.clip(shade, 0, 1.25)), 0, 255).astype(np.uint8)
    rgba[..., 3] = np.where(valid, 255, 0)
    return rgba


def encode_png(pixels: np.ndarray) -> bytes:
    """PNG bytes of an 8-bit image: (M, N) grey, (M, N, 2) grey + alpha, (M, N, 3) RGB or (M, N, 4) RGBA.

    Standard library only (``zlib``, ``struct``); every row uses the "up" filter, which
    suits smooth shaded relief.
    """
    a = np.asarray(pixels)
    if a.dtype != np.uint8:
        raise ValueError(f"encode_png needs uint8 pixels, got {a.dtype}")
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] not in (1, 2, 3, 4) or min(a.shape[:2]) < 1:
        raise ValueError(f"encode_png needs an (M, N) or (M, N, 1-4) image, got shape {pixels.shape}")
    height, width, channels = a.shape
    rows = np.ascontiguousarray(a).reshape(height, width * channels)
    up = rows.copy()
    up[1:] -= rows[:-1]  # uint8 arithmetic wraps modulo 256, as PNG wants
    raw = np.hstack([np.full((height, 1), 2, np.uint8), up]).tobytes()
    colour_type = {1: 0, 2: 4, 3: 2, 4: 6}[channels]
    header = struct.pack(">IIBBBBB", width, height, 8, colour_type, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(raw, 6)) + _chunk(b"IEND", b"")
    )


def _chunk(tag: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)


def _data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _path(points: np.ndarray, *, close: bool = True) -> str:
    if len(points) == 0:
        return ""
    coords = " ".join(f"{x:.1f} {y:.1f}" for x, y in points)
    return f"M{coords}{'Z' if close else ''}"


def _height_range(dsm: np.ndarray) -> tuple[float, float]:
    finite = dsm[np.isfinite(dsm)]
    if finite.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(finite, [2, 98])
    return float(lo), float(hi if hi > lo else lo + 1.0)


def _overlaps(a: Bounds | None, b: Bounds) -> bool:
    return a is None or (a[0] <= b[2] and a[2] >= b[0] and a[1] <= b[3] and a[3] >= b[1])


# -- building the inputs from a run's output folder -----------------------------------


def read_report_inputs(
    folder: str | os.PathLike,
    *,
    max_px: int = MAX_MAP_PX,
    zooms: int = 4,
    zoom_px: int = ZOOM_PX,
) -> ReportInputs | None:
    """The report's map inputs, read from a run's output (or staging) folder.

    Reads ``dsm.vrt`` and ``fill_mask.vrt`` downsampled to at most ``max_px`` pixels on
    the long side (GDAL picks the tiles' overviews), the ``holes``, ``hole_parts`` and
    ``survey_area`` layers of ``holes.gpkg`` and, when present, the ``route`` layer of
    ``flightplan.gpkg``; and a closer window (at most ``zoom_px``) around each of the
    ``zooms`` largest holes that do not span most of the survey.

    Parameters
    ----------
    folder : path-like
        A folder holding ``dsm.vrt`` (``OUT``, or the run's staging folder before commit).

    Returns
    -------
    ReportInputs or None
        None when the folder holds no ``dsm.vrt``.
    """
    folder = Path(folder)
    if not (folder / "dsm.vrt").exists():
        return None
    overview = _read_view(folder, None, max_px)
    pixel = max(
        (overview.bounds[2] - overview.bounds[0]) / overview.dsm.shape[1],
        (overview.bounds[3] - overview.bounds[1]) / overview.dsm.shape[0],
    )
    holes = _read_holes(folder / "holes.gpkg", pixel)
    survey = (overview.bounds[2] - overview.bounds[0], overview.bounds[3] - overview.bounds[1])
    zoom_views: list[tuple[int, MapRaster]] = []
    for hole in sorted(holes, key=lambda h: -h.area_m2):
        if len(zoom_views) >= zooms:
            break
        if hole.bounds is None or not hole.rings:
            continue
        w, h = hole.bounds[2] - hole.bounds[0], hole.bounds[3] - hole.bounds[1]
        if w > 0.5 * survey[0] and h > 0.5 * survey[1]:
            continue  # the overview shows it whole
        zoom_views.append((hole.hole_id, _read_view(folder, _zoom_bounds(hole.bounds, overview.bounds), zoom_px)))
    return ReportInputs(
        overview=overview,
        holes=holes,
        zooms=tuple(zoom_views),
        route=_read_lines(folder / "flightplan.gpkg", "route", pixel),
        survey_area=_read_rings(folder / "holes.gpkg", "survey_area", pixel),
        part_area_by_type=_read_part_areas(folder / "holes.gpkg"),
    )


def _zoom_bounds(hole: Bounds, limit: Bounds) -> Bounds:
    """A square window around a hole with a margin, moved (not cut) to stay inside the survey grid."""
    cx, cy = (hole[0] + hole[2]) / 2, (hole[1] + hole[3]) / 2
    half = max(hole[2] - hole[0], hole[3] - hole[1]) * 0.8 + 15.0
    half = min(half, (limit[2] - limit[0]) / 2, (limit[3] - limit[1]) / 2)
    cx = min(max(cx, limit[0] + half), limit[2] - half)
    cy = min(max(cy, limit[1] + half), limit[3] - half)
    return (cx - half, cy - half, cx + half, cy + half)


def _read_view(folder: Path, bounds: Bounds | None, max_px: int) -> MapRaster:
    """``dsm.vrt`` (and ``fill_mask.vrt``) over ``bounds`` (default: all), at most ``max_px`` on the long side."""
    import rasterio
    from rasterio.enums import Resampling

    with rasterio.open(folder / "dsm.vrt") as src:
        window = _pixel_window(src.transform, bounds, src.width, src.height)
        scale = max(window.width, window.height) / max_px
        shape = (
            (max(1, round(window.height / scale)), max(1, round(window.width / scale)))
            if scale > 1
            else (int(window.height), int(window.width))
        )
        data = src.read(1, window=window, out_shape=shape, masked=True, resampling=Resampling.average)
        dsm = np.ma.filled(data.astype(np.float32), np.nan)
        t = src.transform
        view_bounds = (
            t.c + window.col_off * t.a,
            t.f + (window.row_off + window.height) * t.e,
            t.c + (window.col_off + window.width) * t.a,
            t.f + window.row_off * t.e,
        )
    filled = None
    if (folder / "fill_mask.vrt").exists():
        with rasterio.open(folder / "fill_mask.vrt") as src:
            window = _pixel_window(src.transform, view_bounds, src.width, src.height)
            codes = src.read(1, window=window, out_shape=shape, boundless=False)
            nodata = 255 if src.nodata is None else int(src.nodata)
            filled = (codes > 0) & (codes != nodata)
    return MapRaster(dsm=dsm, bounds=tuple(float(v) for v in view_bounds), filled=filled)  # type: ignore[arg-type]


def _pixel_window(transform, bounds: Bounds | None, width: int, height: int):
    """The whole pixels of a north-up raster inside ``bounds`` (all of them without bounds)."""
    from rasterio.windows import Window

    if bounds is None:
        return Window(0, 0, width, height)
    t = transform
    c0 = max(0, math.floor((bounds[0] - t.c) / t.a + 1e-6))
    c1 = min(width, math.ceil((bounds[2] - t.c) / t.a - 1e-6))
    r0 = max(0, math.floor((bounds[3] - t.f) / t.e + 1e-6))
    r1 = min(height, math.ceil((bounds[1] - t.f) / t.e - 1e-6))
    return Window(c0, r0, max(1, c1 - c0), max(1, r1 - r0))


def _read_holes(gpkg: Path, pixel: float) -> tuple[MapHole, ...]:
    if not gpkg.exists():
        return ()
    import shapely

    from .io.vector import list_layers, read_layer

    if "holes" not in list_layers(gpkg):
        return ()
    frame = read_layer(gpkg, "holes").sort_values("area_m2", ascending=False)
    budget = MAX_HOLE_VERTICES
    holes = []
    for record, geometry in zip(frame.drop(columns="geometry").to_dict("records"), frame.geometry):
        rings: tuple[np.ndarray, ...] = ()
        bounds = label = None
        if geometry is not None and not geometry.is_empty:
            xmin, ymin, xmax, ymax = geometry.bounds
            bounds = (xmin, ymin, xmax, ymax)
            point = geometry.representative_point()
            label = (point.x, point.y)
            if budget > 0 and max(xmax - xmin, ymax - ymin) >= pixel:
                rings = tuple(_rings(shapely.simplify(geometry, pixel / 2)))
                budget -= sum(len(r) for r in rings)
        holes.append(
            MapHole(
                hole_id=int(record["hole_id"]),
                cause=str(record.get("cause") or "unknown"),
                area_m2=float(record.get("area_m2") or 0.0),
                fill_status=str(record.get("fill_status") or ""),
                fill_method=_text(record.get("fill_method")),
                cause_rule=str(record.get("cause_rule") or ""),
                fill_error_m=_float(record.get("fill_error_m")),
                bounds=bounds,
                label_xy=label,
                rings=rings,
            )
        )
    return tuple(holes)


def _read_part_areas(gpkg: Path) -> dict[str, float]:
    if not gpkg.exists():
        return {}
    import pyogrio

    from .io.vector import list_layers

    if "hole_parts" not in list_layers(gpkg):
        return {}
    frame = pyogrio.read_dataframe(
        gpkg, layer="hole_parts", columns=["category", "shape", "area_m2"], read_geometry=False
    )
    areas: dict[str, float] = collections.defaultdict(float)
    for category, shape, area in zip(frame["category"], frame["shape"], frame["area_m2"]):
        shape = _text(shape) if category != "closed" else None
        areas[f"{category}{shape}" if shape else str(category)] += float(area)
    return dict(sorted(areas.items()))


def _read_lines(gpkg: Path, layer: str, pixel: float) -> tuple[np.ndarray, ...]:
    if not gpkg.exists():
        return ()
    import shapely

    from .io.vector import list_layers, read_layer

    if layer not in list_layers(gpkg):
        return ()
    lines = []
    for geometry in read_layer(gpkg, layer).geometry:
        if geometry is None or geometry.is_empty:
            continue
        simple = shapely.simplify(geometry, pixel / 4)
        parts = getattr(simple, "geoms", [simple])
        lines += [np.asarray(part.coords)[:, :2] for part in parts if len(part.coords) >= 2]
    return tuple(lines)


def _read_rings(gpkg: Path, layer: str, pixel: float) -> tuple[np.ndarray, ...]:
    if not gpkg.exists():
        return ()
    import shapely

    from .io.vector import list_layers, read_layer

    if layer not in list_layers(gpkg):
        return ()
    return tuple(
        ring
        for geometry in read_layer(gpkg, layer).geometry
        if geometry is not None and not geometry.is_empty
        for ring in _rings(shapely.simplify(geometry, pixel / 2))
    )


def _rings(geometry) -> Iterable[np.ndarray]:
    for polygon in getattr(geometry, "geoms", [geometry]):
        if polygon.geom_type != "Polygon" or polygon.is_empty:
            continue
        yield np.asarray(polygon.exterior.coords)[:, :2]
        for interior in polygon.interiors:
            yield np.asarray(interior.coords)[:, :2]


# -- small helpers ----------------------------------------------------------------------


def _table(header: Sequence[str], rows: list[list[Any]], *, raw_first: bool = False, raw_last: bool = False) -> str:
    """An HTML table; cells are escaped except the first (``raw_first``) or last (``raw_last``) column."""
    head = f"<tr>{''.join(f'<th>{_e(h)}</th>' for h in header)}</tr>" if any(header) else ""

    def cell(i: int, n: int, value: Any) -> str:
        raw = (raw_first and i == 0) or (raw_last and i == n - 1)
        return f"<td>{value if raw else _e(value)}</td>"

    body = "".join("<tr>" + "".join(cell(i, len(row), c) for i, c in enumerate(row)) + "</tr>" for row in rows)
    return f"<table>{head}{body}</table>"


def _swatch(cause: str) -> str:
    return f"<span class='dot' style='background:{CAUSE_COLOURS.get(cause, _OTHER_COLOUR)}'></span>"


def _cause_name(cause: str) -> str:
    return _e(cause.replace("_", " "))


def _fill_text(status: str, method: str | None) -> str:
    return f"{status}" + (f" ({method})" if method else "")


def _unit_m(manifest: dict[str, Any]) -> float:
    return float(manifest["grid"].get("resolution_unit_m") or 1.0)


def _unit_name(manifest: dict[str, Any]) -> str:
    unit = _unit_m(manifest)
    return "m" if abs(unit - 1.0) < 1e-9 else ("ft" if abs(unit - 0.3048006) < 1e-4 else "CRS units")


def _area(m2: float) -> str:
    return f"{m2 / 1e6:,.2f} km²" if m2 >= 1e6 else f"{m2:,.0f} m²"


def _count(n: int) -> str:
    return f"{n / 1e9:.2f} G" if n >= 1e9 else f"{n / 1e6:.1f} M" if n >= 1e6 else f"{n:,}"


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.1f} s"
    minutes = seconds / 60
    return f"{minutes:.0f} min" if minutes < 120 else f"{minutes / 60:.1f} h"


def _number(value: Any, spec: str) -> str:
    f = _float(value)
    return "-" if f is None else format(f, spec)


def _float(value: Any) -> float | None:
    try:
        f = float(value)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _text(value: Any) -> str | None:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return None
    return str(value)


def _e(value: Any) -> str:
    return html.escape(str(value))
