"""Holes end to end: synthetic truth, cell-size invariance, holes cut into real surveys."""

from __future__ import annotations

import laspy
import numpy as np
import pytest
import rasterio
import shapely

from pipeline.config import load_config
from pipeline.evaluate.truth import score_holes
from pipeline.io.raster import geometry_mask
from pipeline.io.vector import list_layers, read_layer
from pipeline.run import run_survey
from pipeline.synth import generate_survey, preset, write_truth

pytestmark = pytest.mark.slow

LAYERS = {"holes", "hole_parts", "vertical_holes", "walls", "tiles", "cells"}


#: The synthetic truth is on the survey's 1 m grid and counts every thin occlusion sliver as
#: a hole: pin the pixel size and the area rule (no density-aware sampling gaps).
SYNTHETIC = ["grid.resolution_m=1", "holes.min_area_m2=4"]


def synthetic_run(tmp_path, client, name, *overrides, **spec):
    survey = generate_survey(tmp_path / name / "tiles", preset("demo", width_m=400.0, height_m=300.0, **spec))
    truth = write_truth(survey, tmp_path / name)
    out = tmp_path / name / "out"
    summary = run_survey(
        [str(tmp_path / name / "tiles")], out, load_config(overrides=[*SYNTHETIC, *overrides]), client=client,
        aoi=truth["survey_area"],
    )  # fmt: skip
    return survey, truth, out, summary


def test_synthetic_holes_and_causes_match_the_truth(tmp_path, dask_client):
    scores = []
    for name, spec in [
        ("strip", dict(water=False, seed=3)),
        ("both", dict(seed=4)),
        ("buildings", dict(water=False, missed_line=None, building_density=5.0, seed=5)),
    ]:
        _, truth, out, summary = synthetic_run(tmp_path, dask_client, name, **spec)
        assert LAYERS <= set(list_layers(out / "holes.gpkg"))
        score = score_holes(out / "holes.gpkg", truth["hole_cause"], min_area_px=4)
        assert score.iou >= 0.95, (name, score.as_dict())
        assert score.missed_true_holes == 0, (name, score.as_dict())
        scores.append(score)
        if name == "both":  # the river crossing the missed strip is split: each piece has its cause
            assert score.confusion["water"] == {"water": score.confusion["water"].get("water", 0)}, score.confusion
            assert score.confusion["missed_coverage"] == {"missed_coverage": 1}, score.confusion
    holes = sum(s.holes for s in scores)
    correct = sum(s.cause_correct for s in scores)
    assert holes >= 30
    assert correct / holes >= 0.95, [s.confusion for s in scores]


@pytest.mark.parametrize("area", ["footprint", "auto"])
def test_holes_do_not_depend_on_cell_size(tmp_path, dask_client, area):
    """The same holes (pixel sets, areas, causes, ids) with cells of 50 m to 1000 m.

    With the tile extents, and with the tile grid's squares (``auto``: the tiles lie
    on a 100 m grid; the missed strip at the east edge opens to the outside and stays
    exterior, and so does the 4 m2 sliver of water at the edge of the tiles' extents).
    """
    survey = generate_survey(tmp_path / "tiles", preset("demo", width_m=300.0, height_m=200.0, seed=6))
    results = {}
    sizes = (50.0, 64.0, 250.0, 1000.0)
    for cell_m in sizes:
        out = tmp_path / f"out{cell_m:g}"
        run_survey(
            [str(tmp_path / "tiles")],
            out,
            load_config(overrides=[*SYNTHETIC, f"grid.cell_size_m={cell_m}", f"survey.area={area}"]),
            client=dask_client,
        )
        holes = read_layer(out / "holes.gpkg", "holes")
        shape = survey.hole_cause.shape
        masks = sorted(
            (
                tuple(np.flatnonzero(geometry_mask(g, survey.transform, shape))),
                round(area, 3),
                cause,
                hole_id,
            )
            for g, area, cause, hole_id in zip(holes.geometry, holes["area_m2"], holes["cause"], holes["hole_id"])
        )
        results[cell_m] = masks
    assert len(results[64.0]) > 5
    # the listed holes are numbered first: 1..L in raster order of their first pixels
    assert sorted(m[3] for m in results[64.0]) == list(range(1, len(results[64.0]) + 1))
    assert "occlusion" in {m[2] for m in results[64.0]} and len({m[2] for m in results[64.0]}) >= 2
    for cell_m in sizes[1:]:
        assert [m[0] for m in results[sizes[0]]] == [m[0] for m in results[cell_m]], cell_m
        assert [m[1:] for m in results[sizes[0]]] == [m[1:] for m in results[cell_m]], cell_m
    parts64 = read_layer(tmp_path / "out64" / "holes.gpkg", "hole_parts")
    assert parts64["layer"].max() >= 1 and (parts64["category"] != "closed").any()


@pytest.mark.realdata
@pytest.mark.parametrize("name, crs", [("ign_tile_77055_627755.laz", None), ("lasr_bcts_2.laz", None)])
def test_holes_cut_into_real_surveys_are_found(shared_data, tmp_path, dask_client, name, crs):
    source = laspy.read(shared_data / name)
    minx, miny, maxx, maxy = source.header.mins[0], source.header.mins[1], source.header.maxs[0], source.header.maxs[1]
    cx, cy, w, h = (minx + maxx) / 2, (miny + maxy) / 2, maxx - minx, maxy - miny
    cuts = [
        shapely.box(cx - 0.3 * w, cy - 0.3 * h, cx - 0.3 * w + 9.3, cy - 0.3 * h + 6.7),
        shapely.Point(cx + 0.2 * w, cy + 0.1 * h).buffer(5.5),
        shapely.Polygon([(cx, cy - 0.35 * h), (cx + 12, cy - 0.35 * h), (cx + 3, cy - 0.35 * h + 10)]),
    ]
    inside = np.zeros(len(source.points), bool)
    for cut in cuts:
        inside |= shapely.contains_xy(cut, np.asarray(source.x), np.asarray(source.y))
    cut_path = tmp_path / f"cut_{name}"
    source.points = source.points[~inside]
    source.write(cut_path)
    out = tmp_path / "out"
    run_survey([str(cut_path)], out, load_config(overrides=["grid.cell_size_m=50"]), client=dask_client)
    holes = read_layer(out / "holes.gpkg", "holes")
    with rasterio.open(out / "dsm.vrt") as dsm:
        transform, shape = dsm.transform, dsm.shape
    detected = np.zeros(shape, bool)
    for geometry in holes.geometry:
        detected |= geometry_mask(geometry, transform, shape)
    rows, cols = np.indices(shape)
    x0, y0 = transform @ (cols.ravel(), rows.ravel())
    squares = shapely.box(x0, y0 - transform.a, x0 + transform.a, y0).reshape(shape)
    for cut in cuts:
        truth = shapely.within(squares, cut)  # pixels the cut emptied entirely
        found = detected & shapely.intersects(squares, cut)  # detected hole pixels touching the cut
        iou = (truth & found).sum() / (truth | found).sum()
        assert truth.sum() >= 20 and iou >= 0.9, (cut.wkt[:60], int(truth.sum()), iou)
