"""Density on the data footprint (the pre-pass), sampling gaps by local density, filled areas that match the rasters."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import pytest
import rasterio

from pipeline.config import load_config
from pipeline.holes import mark_sampling_gaps
from pipeline.io.vector import read_layer
from pipeline.run import run_survey
from pipeline.survey.density import auto_resolution_m, narrow_width
from pipeline.survey.footprint_density import block_histogram, choose_level, measure_footprint, merge_blocks
from pipeline.survey.scan import scan_survey

from .lasfiles import write_points


def test_block_counts_add_up_on_an_absolute_lattice():
    x, y = np.array([0.5, 0.7, 2.1, 3.9]), np.array([0.1, 0.2, -0.5, 3.9])
    ix, iy, count = block_histogram(x, y, 1.0)
    assert ix.tolist() == [0, 2, 3] and iy.tolist() == [0, -1, 3] and count.tolist() == [2, 1, 1]
    two = merge_blocks([(ix, iy, count), (ix, iy, count)], 1.0)
    assert two.count.tolist() == [4, 2, 2]
    coarse = two.coarsen(4)  # floor division: block (2, -1) goes to (0, -1)
    assert sorted(zip(coarse.ix.tolist(), coarse.iy.tolist(), coarse.count.tolist())) == [(0, -1, 2), (0, 0, 6)]


def test_level_is_the_finest_with_eight_pulses_per_block():
    rng = np.random.default_rng(0)
    x, y = rng.uniform(0, 200, 40_000), rng.uniform(0, 200, 40_000)  # 1 per m2
    blocks = choose_level(merge_blocks([block_histogram(x, y, 1.0)], 1.0))
    assert blocks.block == 4.0  # 1 and 2 per block are too few, 16 are enough
    assert blocks.occupied * 16 == pytest.approx(40_000, rel=0.01)


def test_narrow_width_and_sampling_gaps_follow_width_not_area():
    # a 3 x 3 px square, a 1 x 9 px strip, a plus of five pixels
    assert narrow_width(np.array([9, 9, 5]), np.array([12, 20, 12])).tolist() == [3.0, 1.0, 1.0]


def tiles_of(tmp_path, x, y, z, cuts):
    """The same points as one file per box of ``cuts``."""
    paths = []
    for k, (x0, x1) in enumerate(cuts):
        keep = (x >= x0) & (x < x1)
        paths.append(str(write_points(tmp_path / f"t{k}.laz", x[keep], y[keep], z[keep])))
    return paths


def test_footprint_density_ignores_empty_header_box_and_tiling(tmp_path):
    """Two dense patches 800 m apart: the box holds a tenth of the points per m2 the data does."""
    rng = np.random.default_rng(1)
    patches = [(rng.uniform(x0, x0 + 40, 16_000), rng.uniform(0, 40, 16_000)) for x0 in (0.0, 800.0)]
    x = np.concatenate([p[0] for p in patches])
    y = np.concatenate([p[1] for p in patches])
    z = np.full(len(x), 50.0)
    (tmp_path / "a").mkdir()
    one = measure_footprint(scan_survey(tiles_of(tmp_path / "a", x, y, z, [(-1, 1e4)])))
    assert one.header_density.points_per_m2 == pytest.approx(32_000 / (840 * 40), rel=0.01)
    assert one.density.points_per_m2 == pytest.approx(10.0, rel=0.05)  # 16,000 on each 1,600 m2
    assert one.density.area_source == "data footprint"
    (tmp_path / "b").mkdir()
    cut = measure_footprint(scan_survey(tiles_of(tmp_path / "b", x, y, z, [(-1, 20.3), (20.3, 817.9), (817.9, 1e4)])))
    assert cut.density == one.density
    assert (
        auto_resolution_m(one.density.pulses_per_m2) == 1.0
        and auto_resolution_m(one.header_density.pulses_per_m2) == 4.0
    )


def test_the_pre_pass_in_processes_counts_what_threads_count(tmp_path, monkeypatch):
    """Large surveys are decoded in processes (forked from the fork server): the same blocks and counts."""
    import pipeline.survey.footprint_density as footprint_density

    rng = np.random.default_rng(2)
    x, y = rng.uniform(0, 300, 30_000), rng.uniform(0, 200, 30_000)
    survey = scan_survey(tiles_of(tmp_path, x, y, np.full(len(x), 5.0), [(-1, 100), (100, 200), (200, 1e4)]))
    threads = measure_footprint(survey, workers=2).footprint
    monkeypatch.setattr(footprint_density, "POINTS_PER_PROCESS", 1_000)
    processes = measure_footprint(survey, workers=2).footprint
    assert processes is not None and threads is not None
    assert processes.area_m2 == threads.area_m2 and processes.pulses == threads.pulses == 30_000
    assert np.array_equal(processes.blocks.count, threads.blocks.count)


def sparse_survey(tmp_path):
    """240 m square at 0.44 points/m2 (a jittered 1.5 m lattice: 4 m pixels), with 12 m and 20 m square voids.

    One lattice line is missing too: a 3 m gap between points, a sampling gap.
    """
    rng = np.random.default_rng(2)
    gx, gy = np.meshgrid(np.arange(0.75, 240.0, 1.5), np.arange(0.75, 240.0, 1.5))
    x = 700_000 + gx.ravel() + rng.uniform(-0.3, 0.3, gx.size)
    y = 6_600_000 + gy.ravel() + rng.uniform(-0.3, 0.3, gx.size)
    lx, ly = x - 700_000, y - 6_600_000
    voids = [(40, 40, 12), (120, 120, 20)]
    keep = np.ones(len(x), bool)
    for vx, vy, side in voids:
        keep &= ~((lx >= vx) & (lx < vx + side) & (ly >= vy) & (ly < vy + side))
    keep &= ~((lx >= 200.5) & (lx < 202) & (ly > 20) & (ly < 220))  # one lattice line missing
    return write_points(tmp_path / "sparse.laz", x[keep], y[keep], 100 + rng.normal(0, 0.05, keep.sum())), voids


@pytest.mark.slow
def test_sparse_voids_wider_than_four_spacings_are_listed(tmp_path, dask_client):
    path, voids = sparse_survey(tmp_path)
    out = tmp_path / "out"
    run_survey([str(path)], out, load_config(), client=dask_client)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["grid"]["sizing"]["resolution_m"] == 4.0
    assert manifest["holes"]["sampling_gap_width_m"] == pytest.approx(6.0, rel=0.1)  # 4 spacings of 1.5 m
    holes = read_layer(out / "holes.gpkg", "holes")
    assert len(holes) == 2
    centres = sorted((round(g.centroid.x - 700_000), round(g.centroid.y - 6_600_000)) for g in holes.geometry)
    assert centres == [(vx + s // 2, vy + s // 2) for vx, vy, s in voids]


@dataclass(frozen=True)
class Catalog:
    """What mark_sampling_gaps reads of a HoleCatalog (it copies it with dataclasses.replace)."""

    holes: np.ndarray
    stats: dict


def catalog_of(area, edge, m2):
    """Holes by area, edge length and (row, column, cross) second moments about the centroid."""
    holes = np.zeros(len(area), [("is_small", bool), ("area_px", np.int64)])
    holes["area_px"] = area
    m2 = np.asarray(m2, np.float64)
    stats = {"area_px": np.asarray(area), "edge_len_px": np.asarray(edge)}
    stats.update({"m2_rr": m2[:, 0], "m2_cc": m2[:, 1], "m2_rc": m2[:, 2]})
    return Catalog(holes, stats)


def test_a_void_wider_than_the_gap_in_both_directions_is_never_a_gap():
    """Issue 15 item 7: thickness (2 area / edge) is half a square's side; the narrow width is the side."""
    # at 4 m pixels and an 8 m (2 px) gap width: a 12 m square (3 x 3 px), the same with a notch (a point
    # jittered into it: 8 px, edge 14), a 20 m square, a 4 m x 40 m strip
    square3, square5 = [6.0, 6.0, 0.0], [50.0, 50.0, 0.0]
    notched = [5.5, 4.875, 0.0]
    catalog = catalog_of([9, 8, 25, 10], [12, 14, 20, 22], [square3, notched, square5, [0.0, 82.5, 0.0]])
    _, gaps = mark_sampling_gaps(catalog, 2.0)
    assert gaps.tolist() == [False, False, False, True]
    _, gaps = mark_sampling_gaps(catalog, np.array([3.0, 1.0, 1.0, 0.0]))  # one width per hole
    assert gaps.tolist() == [True, False, False, False]


@pytest.mark.slow
@pytest.mark.realdata
@pytest.mark.parametrize(
    "name, header_px, footprint_px",
    [("ign_laspy_appendbug.laz", 10.0, 1.0), ("wires_quebec.laz", 2.0, 1.0), ("williams_az_urban_norm.laz", 2.0, 1.0)],
)
def test_real_files_get_the_pixel_their_data_supports(shared_data, name, header_px, footprint_px):
    survey = measure_footprint(scan_survey([str(shared_data / name)]))
    assert auto_resolution_m(survey.header_density.pulses_per_m2) == header_px
    assert auto_resolution_m(survey.density.pulses_per_m2) == footprint_px


@pytest.mark.slow
@pytest.mark.realdata
def test_filled_area_is_what_fill_mask_holds(shared_data, tmp_path, dask_client):
    """St-Barth: 31 m2 reported against 192 m2 in fill_mask before; now the same, split in holes and small voids."""
    out = tmp_path / "sb"
    run_survey(
        [str(shared_data / "ign_stbarth_nocrs.laz")],
        out,
        load_config(overrides=['survey.crs="EPSG:5490"']),
        client=dask_client,
    )
    fill = json.loads((out / "manifest.json").read_text())["holes"]["fill"]
    with rasterio.open(out / "fill_mask.vrt") as ds:
        mask = ds.read(1)
        pixel_m2 = abs(ds.transform.a * ds.transform.e)
    assert fill["filled_area_m2"] == pytest.approx(((mask > 0) & (mask < 255)).sum() * pixel_m2)
    assert fill["filled_area_m2"] == pytest.approx(fill["filled_holes_area_m2"] + fill["filled_small_voids_area_m2"])
    assert fill["filled_area_m2"] > 150


def _two_patches(tmp_path):
    """Two dense patches 800 m apart, cut into three files whose middle box spans the empty 760 m."""
    rng = np.random.default_rng(1)
    patches = [(rng.uniform(x0, x0 + 40, 16_000), rng.uniform(0, 40, 16_000)) for x0 in (0.0, 800.0)]
    x = np.concatenate([p[0] for p in patches])
    y = np.concatenate([p[1] for p in patches])
    z = 50.0 + rng.normal(0, 0.05, len(x))
    return tiles_of(tmp_path, x, y, z, [(-1, 20.3), (20.3, 817.9), (817.9, 1e4)])


@pytest.mark.slow
def test_stage_1_counts_the_pre_pass_blocks_and_plans_again_where_the_boxes_misled(tmp_path, dask_client, caplog):
    """No pre-pass: the run sizes its grid by the headers' density (4 m here), stage 1 counts the
    footprint's blocks as it decodes, and the 1 m pixel they support makes the run decode again on
    the right grid: the density the pre-pass measures, and the DSM of a run told 1 m at the start."""
    (tmp_path / "in").mkdir()
    paths = _two_patches(tmp_path / "in")
    measured = measure_footprint(scan_survey(paths)).density
    assert auto_resolution_m(scan_survey(paths).header_density.pulses_per_m2) == 4.0
    with caplog.at_level("INFO", logger="pipeline"):
        run_survey(paths, tmp_path / "auto", load_config(), client=dask_client)
    assert "decoding again" in caplog.text
    density = json.loads((tmp_path / "auto" / "manifest.json").read_text())["grid"]["sizing"]["density"]
    assert density["area_source"] == "data footprint"
    assert density["area_m2"] == measured.area_m2 and density["points"] == measured.points == 32_000
    caplog.clear()
    with caplog.at_level("INFO", logger="pipeline"):
        run_survey(paths, tmp_path / "set", load_config(overrides=["grid.resolution_m=1"]), client=dask_client)
    assert "decoding again" not in caplog.text  # the grid was right: the counts only settle the hole parameters
    for name in ("auto", "set"):
        with rasterio.open(tmp_path / name / "dsm.vrt") as src:
            if name == "auto":
                auto = src.read(1)
            else:
                assert src.res == (1.0, 1.0)
                assert np.array_equal(src.read(1), auto, equal_nan=True)


@pytest.mark.parametrize("dense", [False, True])
def test_a_run_that_planned_again_resumes_on_the_counted_density(tmp_path, dense):
    """The footprint that made a run start again is kept in its partial folder, for --resume alone."""
    from pipeline.staging import Staging
    from pipeline.survey.blocks import BlockCounts, DenseBlockCounts, FootprintDensity

    if dense:
        blocks = DenseBlockCounts(1.0, 0, 5, np.array([[9], [12]]))
        assert blocks.occupied == 2  # cached on the instance: not kept with the fields
    else:
        blocks = BlockCounts(1.0, np.array([0, 1]), np.array([5, 5]), np.array([9, 12]))
    footprint = FootprintDensity(blocks, 30, 21, True, 2.0, 0.1)
    staging = Staging.create(tmp_path / "out", run_key="k")
    (staging.work / "done" / "stale.npz").write_bytes(b"from the first grid")
    staging.start_again(footprint)
    assert not (staging.work / "done" / "stale.npz").exists()
    staging.keep_for_resume()
    resumed = Staging.create(tmp_path / "out", run_key="k", resume=True)
    kept = resumed.kept_footprint()
    assert kept is not None and kept.pulses == 21 and np.array_equal(kept.blocks.count, blocks.count)
    assert type(kept.blocks) is type(blocks) and np.array_equal(kept.blocks.ix, [0, 1])
    resumed.keep_for_resume()
    assert Staging.create(tmp_path / "out", run_key="k").kept_footprint() is None  # a fresh run counts anew


@pytest.mark.parametrize("first_only", [True, False])
def test_blocks_counted_from_raw_records_are_the_blocks_of_their_coordinates(first_only):
    """Stage 1 counts a chunk's records in one compiled pass; the pre-pass counts scaled coordinates."""
    from pipeline.survey.blocks import BlockWindow
    from pipeline.survey.footprint_density import BlockCounter

    rng = np.random.default_rng(3)
    scales, offsets = (0.01, 0.01, 0.01), (-2500.0, 84000.0, 0.0)
    x = rng.integers(-60_000, 360_000, 50_000).astype(np.int32)  # beyond the box on both sides: its edge blocks
    y = rng.integers(-60_000, 360_000, 50_000).astype(np.int32)
    returns = rng.integers(1, 4, 50_000).astype(np.uint8)
    bounds = (-2500.0, 84000.0, 500.0, 87000.0)
    for block in (1.0, 0.7, 13.0):
        expected, counted = BlockCounter(bounds, block), BlockCounter(bounds, block)
        keep = returns == 1 if first_only else np.ones(len(x), bool)
        expected.add(x[keep] * scales[0] + offsets[0], y[keep] * scales[1] + offsets[1])
        counted.add_records(x, y, scales, offsets, returns if first_only else None)
        occupied = [p.occupied() if isinstance(p, BlockWindow) else p for p in (counted.counts(), expected.counts())]
        assert all(np.array_equal(a, b) for a, b in zip(*occupied, strict=True))
        assert occupied[0][2].sum() == keep.sum()


def test_dense_windows_and_listed_blocks_add_up_alike():
    """A file's counts sent as a dense window add up with listed blocks exactly as the blocks they hold."""
    from pipeline.survey.blocks import BlockWindow, merge_blocks

    rng = np.random.default_rng(5)
    window = BlockWindow.of(10, -4, 30, 20, rng.integers(0, 3, 600))  # zeros: empty blocks
    assert window.counts.dtype == np.uint8
    far = BlockWindow.of(10_000_000, 0, 2, 2, np.array([0, 70_000, 1, 0]))  # far apart: the sorted path
    assert far.counts.dtype == np.uint32
    listed = (np.array([12, 500, 12]), np.array([0, 7, 0]), np.array([4, 1, 2]))
    for parts in ([window, listed], [window, listed, far]):
        merged = merge_blocks(parts, 1.0)
        as_listed = merge_blocks([p.occupied() if isinstance(p, BlockWindow) else p for p in parts], 1.0)
        for a, b in ((merged.ix, as_listed.ix), (merged.iy, as_listed.iy), (merged.count, as_listed.count)):
            assert np.array_equal(a, b)
        assert merged.count.sum() == window.counts.sum() + 7 + (70_001 if len(parts) == 3 else 0)


def test_local_density_is_the_median_around_each_box_whatever_the_blocks_order():
    """Merged blocks come in key order (the search skips its sort then); blocks in any other order give the same."""
    from pipeline.survey.blocks import BlockCounts
    from pipeline.survey.footprint_density import LOCAL_MARGIN_BLOCKS, local_pulses_per_m2

    rng = np.random.default_rng(3)
    ix, iy = np.meshgrid(np.arange(40), np.arange(30), indexing="ij")
    ix, iy = ix.ravel(), iy.ravel()
    keep = rng.random(len(ix)) < 0.8
    ix, iy = ix[keep], iy[keep]
    count = rng.integers(1, 50, len(ix))
    boxes = np.array([[10.0, 10.0, 14.0, 12.0], [0.0, 0.0, 2.0, 2.0], [100.0, 100.0, 104.0, 104.0]])
    block = 2.0
    in_order = local_pulses_per_m2(BlockCounts(block, ix, iy, count), boxes)
    shuffled = rng.permutation(len(ix))
    any_order = local_pulses_per_m2(BlockCounts(block, ix[shuffled], iy[shuffled], count[shuffled]), boxes)
    np.testing.assert_array_equal(in_order, any_order)
    for box, found in zip(boxes, in_order):
        lo_x, hi_x = int(box[0] // block) - LOCAL_MARGIN_BLOCKS, int(box[2] // block) + LOCAL_MARGIN_BLOCKS
        lo_y, hi_y = int(box[1] // block) - LOCAL_MARGIN_BLOCKS, int(box[3] // block) + LOCAL_MARGIN_BLOCKS
        near = (ix >= lo_x) & (ix <= hi_x) & (iy >= lo_y) & (iy <= hi_y)
        expected = np.median(count[near]) / block**2 if near.any() else np.nan
        np.testing.assert_allclose(found, expected)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_dense_and_listed_counts_are_the_same_blocks_at_every_level(seed):
    """A tiled survey's footprint is kept as a dense box; its blocks, totals, coarser levels, chosen level
    and local densities are those of the same counts listed block by block (origins on either side of 0)."""
    from pipeline.survey.blocks import BlockCounts, DenseBlockCounts
    from pipeline.survey.footprint_density import local_pulses_per_m2

    rng = np.random.default_rng(seed)
    cols, rows = int(rng.integers(1, 90)), int(rng.integers(1, 90))
    x0, y0 = int(rng.integers(-300, 300)), int(rng.integers(-300, 300))
    grid = np.where(rng.random((cols, rows)) < rng.uniform(0.3, 1.0), rng.integers(1, 12, (cols, rows)), 0)
    dense = DenseBlockCounts(0.5, x0, y0, grid.astype(np.int64))
    ix, iy = np.nonzero(grid)
    listed = BlockCounts(0.5, ix + x0, iy + y0, grid[ix, iy].astype(np.int64))
    assert np.array_equal(dense.ix, listed.ix) and np.array_equal(dense.iy, listed.iy)
    assert np.array_equal(dense.count, listed.count)
    for factor in (1, 2, 4, 8, 64):
        a, b = dense.coarsen(factor), listed.coarsen(factor)
        assert (a.block, a.occupied, a.total) == (b.block, b.occupied, b.total)
        assert all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("ix", "iy", "count"))
        # the reference: each block's count added into the coarse block holding it
        expected: dict[tuple[int, int], int] = {}
        for i, j, c in zip(listed.ix // factor, listed.iy // factor, listed.count):
            expected[(int(i), int(j))] = expected.get((int(i), int(j)), 0) + int(c)
        assert dict(zip(zip(a.ix.tolist(), a.iy.tolist()), a.count.tolist())) == expected
    for min_mean in (1.0, 8.0, 40.0, 1e9):
        a, b = choose_level(dense, min_mean=min_mean), choose_level(listed, min_mean=min_mean)
        assert (a.block, a.occupied, a.total) == (b.block, b.occupied, b.total)
    span_x, span_y = (x0 - 10) * 0.5, (y0 - 10) * 0.5
    corners = rng.uniform([span_x, span_y], [span_x + (cols + 20) * 0.5, span_y + (rows + 20) * 0.5], (40, 2))
    boxes = np.column_stack([corners, corners + rng.uniform(0, 6, (40, 2))])
    np.testing.assert_array_equal(local_pulses_per_m2(dense, boxes), local_pulses_per_m2(listed, boxes))
