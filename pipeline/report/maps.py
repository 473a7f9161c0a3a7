"""The report's maps: inline SVG over a shaded-relief PNG (filled pixels hatched, holes by cause, route, AOI).

:func:`_map_svg` draws one map in named steps: the frame (:class:`_Frame`), the raster
layers, the survey area, the holes, the route, the zoom markers and the scale bar.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .model import _FILL_HATCH, _OTHER_COLOUR, CAUSE_COLOURS, Bounds, MapHole, MapRaster, ReportInputs
from .png import _RAMP, _data_uri
from .text import _cause_name, _e, _fill_text, _unit_name


@dataclass(frozen=True)
class _Frame:
    """Where a map is drawn: the SVG's user unit is one pixel of the view.

    ``box`` is the viewBox ``(x0, y0, x1, y1)`` in view pixels (larger than the view
    when it holds the whole route); ``unit`` is view pixels per screen pixel.
    """

    nx: int
    ny: int
    xmin: float
    ymax: float
    sx: float
    sy: float
    box: tuple[Any, Any, Any, Any]
    unit: float

    @property
    def width(self) -> float:
        return self.box[2] - self.box[0]

    @property
    def height(self) -> float:
        return self.box[3] - self.box[1]

    def to_px(self, xy: np.ndarray) -> np.ndarray:
        """World x, y (K, 2) to view pixels."""
        return np.column_stack([(xy[:, 0] - self.xmin) / self.sx, (self.ymax - xy[:, 1]) / self.sy])


def _map_svg(
    view: MapRaster,
    inputs: ReportInputs,
    *,
    numbered: dict[int, int],
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
    frame = _frame(view, inputs.route, display_px=display_px, show_whole_route=show_whole_route)
    route = [frame.to_px(line) for line in inputs.route if len(line)]
    out = _raster_layers(view, frame, uid=map_id)
    out += _survey_area_layer(inputs.survey_area, frame)
    out += _hole_layer(inputs.holes, view.bounds, frame)
    out += _route_layer(route, frame.unit)
    out += _zoom_markers(inputs.holes, numbered, frame)
    out.append(_scale_bar((frame.box[0], frame.box[3]), frame.width, frame.sx, unit_m, frame.unit))
    out.append("</svg>")
    return "".join(out)


def _frame(view: MapRaster, route_xy: tuple[np.ndarray, ...], *, display_px: float, show_whole_route: bool) -> _Frame:
    """The view's pixel geometry and viewBox (grown to hold the whole route with ``show_whole_route``)."""
    ny, nx = view.dsm.shape
    xmin, ymin, xmax, ymax = view.bounds
    sx, sy = (xmax - xmin) / nx, (ymax - ymin) / ny
    frame = _Frame(nx=nx, ny=ny, xmin=xmin, ymax=ymax, sx=sx, sy=sy, box=(0.0, 0.0, float(nx), float(ny)), unit=1.0)
    route = [frame.to_px(line) for line in route_xy if len(line)]
    box = frame.box
    if show_whole_route and route:
        points = np.vstack(route)
        margin = 0.02 * max(nx, ny)
        box = (
            min(box[0], points[:, 0].min() - margin),
            min(box[1], points[:, 1].min() - margin),
            max(box[2], points[:, 0].max() + margin),
            max(box[3], points[:, 1].max() + margin),
        )
    return _Frame(nx=nx, ny=ny, xmin=xmin, ymax=ymax, sx=sx, sy=sy, box=box, unit=(box[2] - box[0]) / display_px)


def _raster_layers(view: MapRaster, frame: _Frame, *, uid: str) -> list[str]:
    """The SVG's opening, its defs, the background, the shaded relief (heights coloured between the
    map's own range) and the hatching of filled pixels."""
    nx, ny, box, unit = frame.nx, frame.ny, frame.box, frame.unit
    bw, bh = frame.width, frame.height
    hatch = 8 * unit
    images = view.images
    filled_png = images.filled_png
    out = [
        f"<svg class='map' xmlns='http://www.w3.org/2000/svg' viewBox='{box[0]:.1f} {box[1]:.1f} {bw:.1f} {bh:.1f}' "
        f"preserveAspectRatio='xMidYMid meet' role='img'>",
        "<defs>",
        f"<pattern id='hatch-{uid}' patternUnits='userSpaceOnUse' width='{hatch:.3g}' height='{hatch:.3g}' "
        f"patternTransform='rotate(45)'><rect width='{hatch / 2:.3g}' height='{hatch:.3g}' fill='{_FILL_HATCH}'/>"
        "</pattern>",
    ]
    if filled_png is not None:
        out.append(
            f"<mask id='filled-{uid}' maskUnits='userSpaceOnUse' x='0' y='0' width='{nx}' height='{ny}'>"
            f"<image width='{nx}' height='{ny}' preserveAspectRatio='none' style='image-rendering:pixelated' "
            f"href='{_data_uri(filled_png)}'/></mask>"
        )
    out += [
        "</defs>",
        f"<rect x='{box[0]:.1f}' y='{box[1]:.1f}' width='{bw:.1f}' height='{bh:.1f}' fill='#fbfbfb'/>",
        f"<rect width='{nx}' height='{ny}' fill='#ececec'/>",
        # a map shown larger than its pixels (a zoom): show the DSM's pixels, not a blur
        f"<image width='{nx}' height='{ny}' preserveAspectRatio='none' "
        f"style='image-rendering:{'pixelated' if unit < 0.5 else 'auto'}' "
        f"href='{_data_uri(images.relief_png)}'/>",
    ]
    if filled_png is not None:
        out.append(
            f"<rect width='{nx}' height='{ny}' fill='url(#hatch-{uid})' opacity='0.75' mask='url(#filled-{uid})'/>"
        )
    return out


def _survey_area_layer(rings: tuple[np.ndarray, ...], frame: _Frame) -> list[str]:
    """The survey area (AOI) as dashed outlines."""
    return [
        f"<path d='{_path(frame.to_px(ring))}' fill='none' stroke='#111' stroke-width='1.2' "
        "stroke-dasharray='6 4' vector-effect='non-scaling-stroke'/>"
        for ring in rings
    ]


def _hole_layer(holes: tuple[MapHole, ...], bounds: Bounds, frame: _Frame) -> list[str]:
    """The outlined holes over the view, coloured by cause, each with its figures as a tooltip."""
    out = []
    for hole in holes:
        if not hole.rings or not _overlaps(hole.bounds, bounds):
            continue
        colour = CAUSE_COLOURS.get(hole.cause, _OTHER_COLOUR)
        d = " ".join(_path(frame.to_px(ring)) for ring in hole.rings)
        title = (
            f"hole {hole.hole_id}: {hole.cause.replace('_', ' ')} ({hole.cause_rule}), {hole.area_m2:,.0f} m², "
            f"{_fill_text(hole.fill_status, hole.fill_method)}"
        )
        out.append(
            f"<path d='{d}' fill='{colour}' fill-opacity='0.22' fill-rule='evenodd' stroke='{colour}' "
            f"stroke-width='1.6' vector-effect='non-scaling-stroke'><title>{_e(title)}</title></path>"
        )
    return out


def _route_layer(route: list[np.ndarray], unit: float) -> list[str]:
    """The re-flight route (in view pixels), haloed, and its take-off point."""
    out = []
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
    return out


def _zoom_markers(holes: tuple[MapHole, ...], numbered: dict[int, int], frame: _Frame) -> list[str]:
    """A numbered disc on each hole shown closer in a zoom."""
    out = []
    by_id = {h.hole_id: h for h in holes}
    for hole_id, number in numbered.items():
        marked = by_id.get(hole_id)
        if marked is not None and marked.label_xy is not None:
            px, py = frame.to_px(np.asarray([marked.label_xy]))[0]
            out.append(_marker(px, py, str(number), frame.unit, fill="#222", title=f"zoom {number}: hole {hole_id}"))
    return out


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


def _path(points: np.ndarray, *, close: bool = True) -> str:
    if len(points) == 0:
        return ""
    coords = " ".join(f"{x:.1f} {y:.1f}" for x, y in points)
    return f"M{coords}{'Z' if close else ''}"


def _overlaps(a: Bounds | None, b: Bounds) -> bool:
    return a is None or (a[0] <= b[2] and a[2] >= b[0] and a[1] <= b[3] and a[3] >= b[1])
