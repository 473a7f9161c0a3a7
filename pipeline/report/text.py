"""Small text and HTML formatters shared by the page, the maps and the inputs reader."""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from typing import Any

from .model import _OTHER_COLOUR, CAUSE_COLOURS


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
