"""GeoPackage layers (pyogrio through geopandas): writing them, reading them back.

Layers are written into a GeoPackage inside the run's staging folder; the whole
file is moved into place when the run succeeds (see ``pipeline.staging``). Polygon
files given by the user (``--aoi``, ``--water``) are read here too.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import shapely
from pyproj import CRS, Transformer

from ..errors import CRSError, InputDataError, OutputError

if TYPE_CHECKING:
    import geopandas as gpd
    import pandas as pd

# pyogrio (which imports geopandas and pandas, 0.3 s) is imported where a layer is read or
# written: the workers that import this module through the survey plan never do either


def write_layer(
    path: str | os.PathLike,
    layer: str,
    records: list[dict[str, Any]],
    geometries: list[shapely.Geometry],
    *,
    crs_wkt: str,
    geometry_type: str | None = None,
    fields: dict[str, str] | None = None,
) -> Path:
    """Write (or replace) one layer of a GeoPackage.

    Parameters
    ----------
    records : list of dict
        One attribute dictionary per feature (the same keys in each).
    geometries : list of shapely geometries
        One per record, in the layer's CRS.
    geometry_type : str, optional
        Forced OGR geometry type (e.g. "Polygon") so that empty layers are typed.
    fields : dict, optional
        The layer's fields (name -> numpy dtype: ``"int64"``, ``"float64"``, ``"bool"``,
        ``"object"`` for text), written even when there is no record: a GIS user meets
        the same columns in an empty layer.
    """
    return write_layer_in_parts(
        path, layer, [(records, geometries)], crs_wkt=crs_wkt, geometry_type=geometry_type, fields=fields
    )


def write_layer_in_parts(
    path: str | os.PathLike,
    layer: str,
    parts: Iterable[tuple[list[dict[str, Any]], Sequence[shapely.Geometry]]],
    *,
    crs_wkt: str,
    geometry_type: str | None = None,
    fields: dict[str, str] | None = None,
) -> Path:
    """:func:`write_layer` from ``(records, geometries)`` parts, each appended after the first.

    The same layer, feature for feature, as one call with the parts joined; only one part's
    data frame exists at a time (the 209,208 vertical holes of a 1 B point survey: a frame and
    its geometries of some 300 MB at once). Parts without a record add nothing.
    """
    import geopandas as gpd
    import pandas as pd

    path = Path(path)
    written = False
    for records, geometries in parts:
        if not records:
            continue
        frame = gpd.GeoDataFrame(records, geometry=list(geometries), crs=crs_wkt or None)
        _write_frame(frame, path, layer, geometry_type, append=written)
        written = True
    if not written:
        if fields:
            columns = {name: pd.Series([], dtype=dtype) for name, dtype in fields.items()}
            frame = gpd.GeoDataFrame(columns, geometry=gpd.GeoSeries([]), crs=crs_wkt or None)
        else:
            frame = gpd.GeoDataFrame([], geometry=[], crs=crs_wkt or None)
        _write_frame(frame, path, layer, geometry_type, append=False)
    return path


def _write_frame(frame: gpd.GeoDataFrame, path: Path, layer: str, geometry_type: str | None, *, append: bool) -> None:
    import pyogrio

    try:
        pyogrio.write_dataframe(
            frame,
            path,
            layer=layer,
            driver="GPKG",
            geometry_type=geometry_type,
            promote_to_multi=bool(geometry_type and geometry_type.startswith("Multi")),
            append=append,
        )
    except Exception as e:
        raise OutputError(f"{path}: cannot write layer '{layer}': {e}") from None


def read_layer(path: str | os.PathLike, layer: str) -> gpd.GeoDataFrame:
    """Read one layer back (tests, evaluation)."""
    import pyogrio

    return pyogrio.read_dataframe(path, layer=layer)


def read_attributes(path: str | os.PathLike, layer: str, columns: list[str]) -> pd.DataFrame | None:
    """Some fields of a layer, without geometries; None when the layer lacks one of them (an empty layer has no field)."""
    import pyogrio

    if any(column not in pyogrio.read_info(path, layer=layer)["fields"] for column in columns):
        return None
    return pyogrio.read_dataframe(path, layer=layer, columns=columns, read_geometry=False)


def list_layers(path: str | os.PathLike) -> list[str]:
    """Layer names of a GeoPackage."""
    import pyogrio

    return [name for name, _ in pyogrio.list_layers(path)]


def read_survey_area(
    path: str | os.PathLike, crs: CRS, *, what: str = "AOI", within: shapely.Geometry | None = None
) -> shapely.Geometry:
    """The union of the polygons of a vector file, in the survey CRS.

    Refused (:class:`InputDataError`, naming the file) where it holds no polygon, only empty
    ones, or, with ``within`` (the survey area), none that overlaps it: polygons beside the
    data are most likely in another CRS than their file says, or of another place.
    """
    import pyogrio

    try:
        frame = pyogrio.read_dataframe(path)
    except Exception as e:
        raise InputDataError(path, f"{what} file cannot be read: {e}") from None
    polygons = [g for g in frame.geometry if g is not None and g.geom_type in ("Polygon", "MultiPolygon")]
    if not polygons:
        raise InputDataError(path, f"{what} file holds no polygon")
    polygons = [g for g in polygons if not g.is_empty]
    if not polygons:
        raise InputDataError(path, f"{what} file holds only empty polygons (no coordinates)")
    if frame.crs is None:
        raise CRSError(path, f"{what} file has no CRS")
    area = shapely.union_all(polygons)
    if not CRS.from_user_input(frame.crs).equals(crs, ignore_axis_order=True):
        transformer = Transformer.from_crs(frame.crs, crs, always_xy=True)
        area = shapely.transform(area, lambda xy: _transform_xy(transformer, xy))
    area = shapely.make_valid(area)
    if within is not None and not within.is_empty and not area.intersects(within):
        bounds = ", ".join(f"{v:.6g}" for v in area.bounds)
        survey = ", ".join(f"{v:.6g}" for v in within.bounds)
        raise InputDataError(
            path,
            f"{what} polygons do not overlap the survey area (theirs: {bounds}; the survey's: {survey}; "
            f"in {crs.to_string()}): is the file's CRS right?",
        )
    return area


def _transform_xy(transformer: Transformer, xy: np.ndarray) -> np.ndarray:
    x, y = transformer.transform(xy[:, 0], xy[:, 1])
    return np.column_stack([x, y])
