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

Modules: :mod:`.model` (the dataclasses and size bounds), :mod:`.page` (the HTML
sections, tables and style), :mod:`.maps` (the SVG maps), :mod:`.png` (shaded relief
and PNG encoding), :mod:`.inputs` (reading a run folder; the only one that reads
files) and :mod:`.text` (formatters shared by the others).
"""

from .inputs import prepare_maps, read_report_inputs, with_route
from .model import CAUSE_COLOURS, MAX_HOLE_VERTICES, MAX_MAP_PX, ZOOM_PX, MapHole, MapRaster, ReportInputs
from .page import render_report, write_report
from .png import encode_png, shaded_relief

__all__ = [
    "CAUSE_COLOURS",
    "MAX_HOLE_VERTICES",
    "MAX_MAP_PX",
    "ZOOM_PX",
    "MapHole",
    "MapRaster",
    "ReportInputs",
    "encode_png",
    "prepare_maps",
    "read_report_inputs",
    "render_report",
    "shaded_relief",
    "with_route",
    "write_report",
]
