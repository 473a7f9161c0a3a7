"""The report's data: map rasters, hole outlines, their colours and size bounds.

Plain frozen dataclasses (no I/O): :func:`pipeline.report.read_report_inputs` builds
them from a run folder, the page and the maps only read them; a map draws its own pictures
once (:attr:`MapRaster.images`, with :mod:`.png`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from .png import _height_range, encode_png, shaded_relief

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
    "no_return": "#009e73",
    "covered": "#56b4e9",
    "unknown": "#cc79a7",
}
_OTHER_COLOUR = "#666666"
#: Hatching of the pixels filled by holefill.
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

    @functools.cached_property
    def images(self) -> MapImages:
        """The map's shaded relief (heights coloured between the map's own range) and its filled pixels'
        mask as PNG bytes: drawn once, from the map alone (a run draws them while it plans the flights,
        :func:`pipeline.report.prepare_maps`)."""
        ny, nx = self.dsm.shape
        xmin, ymin, xmax, ymax = self.bounds
        height_range = _height_range(self.dsm)
        pixel_size = ((xmax - xmin) / nx, (ymax - ymin) / ny)
        relief = shaded_relief(self.dsm, pixel_size=pixel_size, height_range=height_range)
        filled = None
        if self.filled is not None and bool(self.filled.any()):
            filled = encode_png(np.where(self.filled, 255, 0).astype(np.uint8))
        return MapImages(relief_png=encode_png(relief), filled_png=filled, height_range=height_range)


@dataclass(frozen=True)
class MapImages:
    """The pictures of a :class:`MapRaster`: PNG bytes of its shaded relief (heights coloured between
    the map's own height range) and of its filled pixels (None: none filled)."""

    relief_png: bytes
    filled_png: bytes | None
    height_range: tuple[float, float]


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
