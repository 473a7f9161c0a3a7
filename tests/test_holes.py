"""Tests of pipeline.holes: detection, [OPEN] classification, linking, layers, causes."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import scipy.ndimage as ndi

from pipeline import holes as H
from pipeline.grid import Grid, PixelWindow
from pipeline.parameters import default_cause_rules
from pipeline.sensor.sight import BLOCKED, SEEN

JUMP = 2.0


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


def make_grid(
    height: int, width: int, cell_px: int, halo_px: int = 8, col_min: int = 0, row_top: int | None = None
) -> Grid:
    return Grid(
        resolution=1.0,
        col_min=col_min,
        row_top=height - 1 if row_top is None else row_top,
        width=width,
        height=height,
        cell_px=cell_px,
        halo_px=halo_px,
        crs_wkt="",
    )


def surface(count, z, zmin=None):
    """zmax/zmin rasters from a height raster, NaN where empty."""
    zmax = np.where(count > 0, z, np.nan).astype(np.float32)
    lo = z if zmin is None else zmin
    return zmax, np.where(count > 0, lo, np.nan).astype(np.float32)


def detect_all(grid, count, zmax, zmin, aoi=None, **kw):
    out = []
    for cell in grid.cells():
        sl = cell.halo_window.slices_within(grid.window)
        evidence = {k: v[sl] for k, v in kw.items() if isinstance(v, np.ndarray)}
        thresholds = {k: v for k, v in kw.items() if not isinstance(v, np.ndarray)}
        out.append(
            H.detect_cell_holes(
                count[sl],
                zmax[sl],
                zmin[sl],
                None if aoi is None else aoi[sl],
                cell=cell,
                grid_window=grid.window,
                params=H.DetectParams(jump_threshold=JUMP, **thresholds),
                evidence=H.CellEvidence(**evidence),
            )
        )
    return out


def hole_raster(grid, cells, catalog):
    """The global hole-id raster assembled from per-cell labels."""
    out = np.zeros(grid.window.shape, np.int64)
    for c in cells:
        out[c.cell.window.slices_within(grid.window)] = catalog.hole_id_lookup(c.cell.id)[c.labels]
    return out


def run(count, z=None, *, cell_px=64, aoi=None, min_area_px=1, zmin=None, **kw):
    if z is None:
        z = np.zeros(count.shape)
    grid = make_grid(*count.shape, cell_px)
    zmax, zmn = surface(count, z, zmin)
    cells = detect_all(grid, count, zmax, zmn, aoi, **kw)
    catalog = H.link_holes([c.without_labels() for c in cells], min_area_px=min_area_px)
    return grid, cells, catalog


def cell_at(grid, cells, row, col):
    for c in cells:
        w = c.cell.window
        if w.row_off <= row < w.row_end and w.col_off <= col < w.col_end:
            return c
    raise KeyError((row, col))


def part_at(grid, cells, row, col):
    c = cell_at(grid, cells, row, col)
    w = c.cell.window
    label = c.labels[row - w.row_off, col - w.col_off]
    assert label > 0
    return c, c.parts[label - 1]


# --------------------------------------------------------------------------------------
# raster kernels
# --------------------------------------------------------------------------------------


def test_hole_mask_respects_aoi():
    count = np.array([[0, 1], [0, 0]])
    aoi = np.array([[True, True], [False, True]])
    assert H.hole_mask(count, aoi).tolist() == [[True, False], [False, True]]
    assert H.hole_mask(count).sum() == 3


def test_height_jumps_eq1_and_neighbour_steps():
    nan = np.nan
    zmax = np.array([[0.0, 0.1, 5.0], [0.0, 0.2, 5.0], [nan, 0.0, 0.0]])
    zmin = np.array([[0.0, 0.0, 5.0], [0.0, 0.0, 1.0], [nan, 0.0, 0.0]])
    jumps = H.height_jumps(zmax, zmin, jump_threshold=2.0)
    # (1, 2) by its own span (eq. 1); columns 1 | 2 by the step between neighbours
    assert jumps.tolist() == [[False, True, True], [False, True, True], [False, False, True]]
    # NaN (empty) neighbours never make a jump
    assert not H.height_jumps(np.array([[nan, 10.0]]), np.array([[nan, 10.0]]), jump_threshold=1).any()


def test_vertical_holes_eq2():
    zmax = np.array([[10.0, 10.0, 0.4, 3.0]])
    zmin = np.array([[0.0, 0.0, 0.0, 0.0]])
    voxels = np.array([[20, 4, 1, 2]])
    vh = H.vertical_holes(zmax, zmin, voxels, voxel_height=0.5)
    assert vh.tolist() == [[False, True, False, True]]
    # [UAS] applies eq. 2 to jump pixels only
    vh = H.vertical_holes(zmax, zmin, voxels, voxel_height=0.5, jump_threshold=5.0)
    assert vh.tolist() == [[False, True, False, False]]


def test_vertical_hole_records_per_group():
    """Pixels, largest span, missing voxels and top of each 8-connected group; small groups left out."""
    from affine import Affine

    from pipeline.holes.vertical import vertical_hole_records
    from pipeline.rasterize import PixelStatistics

    zmax = np.zeros((6, 6), np.float32)
    zmin = np.zeros((6, 6), np.float32)
    voxels = np.zeros((6, 6), np.uint16)
    mask = np.zeros((6, 6), bool)
    # group A: three pixels, diagonal neighbours (8-connected)
    for (r, c), top, bottom, occupied in (((0, 0), 10.0, 0.0, 3), ((1, 1), 12.0, 2.0, 4), ((2, 2), 8.0, 1.0, 1)):
        mask[r, c], zmax[r, c], zmin[r, c], voxels[r, c] = True, top, bottom, occupied
    # group B: two pixels
    for (r, c), top, bottom, occupied in (((4, 4), 5.0, 0.0, 2), ((4, 5), 6.5, 0.5, 20)):
        mask[r, c], zmax[r, c], zmin[r, c], voxels[r, c] = True, top, bottom, occupied
    # a lone pixel, under min_px
    mask[0, 5], zmax[0, 5] = True, 30.0
    empty = np.zeros((6, 6), np.uint16)
    core = PixelStatistics(
        window=PixelWindow(0, 0, 6, 6), zmax=zmax, zmin=zmin, count=empty.astype(np.uint32),
        voxels=voxels, water=empty, source=empty, covered=empty,
    )  # fmt: skip
    records = vertical_hole_records(mask, core, Affine.identity(), voxel_height=1.0, min_px=2)
    assert [r["pixels"] for r in records] == [3, 2]
    assert [r["max_height_range"] for r in records] == [10.0, 6.0]
    assert [r["top"] for r in records] == [12.0, 6.5]
    # expected voxels floor(span / 1 m) less the occupied ones, never below 0: (10-3)+(10-4)+(7-1); (5-2)+0
    assert [r["missing_voxels"] for r in records] == [19, 3]


def test_largest_per_label_matches_ndimage():
    from pipeline.stages.fill_holes import largest_per_label

    rng = np.random.default_rng(7)
    for _ in range(50):
        labels = rng.integers(-1, 8, (20, 30))
        values = rng.random((20, 30)) * 5
        ids = rng.choice(np.arange(1, 12), size=int(rng.integers(1, 6)), replace=False)
        expected = ndi.maximum(values, labels=labels, index=ids)
        np.testing.assert_array_equal(largest_per_label(values, labels, ids), expected)
    assert largest_per_label(values, labels, np.empty(0, np.int64)).shape == (0,)


# --------------------------------------------------------------------------------------
# per cell: closed / open, type I / II, shapes A-D ([OPEN] 3.1)
# --------------------------------------------------------------------------------------

N3 = 96  # 3 x 3 cells of 32 px: the middle cell is rows/cols 32..63


def three_by_three(count, aoi=None, **kw):
    return run(count, cell_px=32, aoi=aoi, **kw)


def test_closed_hole():
    count = np.ones((N3, N3), np.uint32)
    count[40:45, 40:46] = 0
    grid, cells, cat = three_by_three(count)
    _, part = part_at(grid, cells, 42, 42)
    assert part["category"] == "closed" and part["shape"] == ""
    assert not part["touches_edge"] and part["touches_data"]
    assert len(cat.holes) == 1 and cat.holes["area_px"][0] == 30 and cat.holes["n_parts"][0] == 1


def test_open_type_I_shape_B():
    count = np.ones((N3, N3), np.uint32)
    count[26:40, 26:40] = 0  # over the middle cell's north-west corner
    grid, cells, cat = three_by_three(count)
    _, part = part_at(grid, cells, 35, 35)
    assert part["category"] == "I" and part["shape"] == "B"
    assert part["sides"] == H.SIDE_BITS["north"] | H.SIDE_BITS["west"]
    assert part["edge_runs"] == 1 and part["data_sides"] == 1
    assert cat.holes["n_parts"][0] == 4 and cat.holes["n_cells"][0] == 4


def test_open_type_I_shape_C_crossing():
    count = np.ones((N3, N3), np.uint32)
    count[44:51, 10:86] = 0  # a band crossing the middle cell west to east
    grid, cells, cat = three_by_three(count)
    _, part = part_at(grid, cells, 47, 47)
    assert part["category"] == "I" and part["shape"] == "C"
    assert part["edge_runs"] == 2 and part["data_sides"] == 2
    assert part["continues"] == H.SIDE_BITS["east"] | H.SIDE_BITS["west"]


def test_open_type_I_shape_D_island():
    count = np.ones((N3, N3), np.uint32)
    count[36:60, 28:60] = 0  # reaches into the west cell
    count[44:52, 40:50] = 1  # an island of data inside the hole
    grid, cells, _ = three_by_three(count)
    _, part = part_at(grid, cells, 38, 38)
    assert part["category"] == "I" and part["shape"] == "D" and part["islands"] == 1


def test_open_shape_A_and_layers_of_a_3x3_hole():
    count = np.ones((N3, N3), np.uint32)
    count[18:78, 18:78] = 0  # covers the middle cell and reaches 14 px into each neighbour
    grid, cells, cat = three_by_three(count)
    middle, part = part_at(grid, cells, 48, 48)
    assert part["shape"] == "A" and part["category"] == "I" and not part["touches_data"]
    assert not middle.core_has_data
    assert len(cat.holes) == 1 and cat.holes["n_parts"][0] == 9 and cat.holes["n_cells"][0] == 9
    records = cat.part_records()
    layers = {r.cell_id: r.layer for r in records}
    assert layers[middle.cell.id] == 2
    assert sorted(layers.values()) == [1] * 8 + [2]
    assert cat.holes["max_layer"][0] == 2
    mid = next(r for r in records if r.cell_id == middle.cell.id)
    assert len(mid.neighbours) == 4  # edge neighbours only with 4-connectivity
    assert all(r.hole_id == 1 for r in records)
    # 8-connectivity also links the diagonal cells through the corners
    _, _, cat8 = three_by_three(count, connectivity=8)
    mid8 = next(r for r in cat8.part_records() if r.cell_id == middle.cell.id)
    assert len(mid8.neighbours) == 8 and mid8.layer == 2


def test_type_II_aoi_boundary_inside_cell_and_grid_edge():
    count = np.ones((N3, N3), np.uint32)
    aoi = np.ones((N3, N3), bool)
    aoi[:, 56:] = False  # the AOI ends inside the middle column of cells
    count[40:50, 45:62] = 0  # reaches the AOI boundary, not the core edge
    count[70:80, 0:5] = 0  # on the grid's west edge
    grid, cells, cat = three_by_three(count, aoi=aoi)
    _, part = part_at(grid, cells, 45, 46)
    assert part["category"] == "II" and part["touches_aoi_boundary"] and not part["touches_edge"]
    _, edge_part = part_at(grid, cells, 75, 2)
    assert edge_part["category"] == "II"
    # empty pixels outside the AOI are no hole
    assert cat.stats["area_px"].sum() == 10 * 11 + 10 * 5
    assert cat.holes["touches_aoi_boundary"].all()


def test_small_voids_counted_not_listed_and_settled_in_cells():
    rng = np.random.default_rng(3)
    count = np.ones((N3, N3), np.uint32)
    count[rng.random((N3, N3)) < 0.02] = 0
    count[10:20, 10:20] = 0
    _, _, cat = three_by_three(count, min_area_px=5)
    assert cat.listed["area_px"].min() >= 5 and len(cat.listed) >= 1
    assert cat.small_void_count == cat.holes["is_small"].sum() > 0
    # cells may settle small closed voids themselves: same counts, same listed holes
    grid = make_grid(N3, N3, 32)
    zmax, zmin = surface(count, np.zeros((N3, N3)))
    cells_settled = detect_all(grid, count, zmax, zmin, min_area_px=5)
    cat_settled = H.link_holes(cells_settled, min_area_px=5)
    assert cat_settled.settled_small_voids > 0
    assert cat_settled.small_void_count == cat.small_void_count
    assert cat_settled.small_void_px == cat.small_void_px
    np.testing.assert_array_equal(cat_settled.listed["area_px"], cat.listed["area_px"])
    assert any((c.labels == -1).any() for c in cells_settled)
    lookup = cat_settled.hole_id_lookup(cells_settled[0].cell.id)
    assert lookup[-1] == -1 and lookup[0] == 0


def test_diagonal_contact_across_a_cell_corner():
    count = np.ones((64, 64), np.uint32)
    count[28:32, 28:32] = 0  # north-west cell, ends at its south-east corner
    count[32:36, 32:36] = 0  # south-east cell, starts at its north-west corner
    _, _, cat4 = run(count, cell_px=32)
    _, _, cat8 = run(count, cell_px=32, connectivity=8)
    assert len(cat4.holes) == 2 and len(cat8.holes) == 1


def test_validation_errors():
    grid = make_grid(64, 64, 32, halo_px=2)
    cell = grid.cells()[0]
    shape = cell.halo_window.shape
    z = np.zeros(shape, np.float32)
    count = np.ones(shape, np.uint32)
    with pytest.raises(ValueError, match="halo"):
        H.detect_cell_holes(count, z, z, cell=cell, grid_window=grid.window, params=H.DetectParams(1.0))
    with pytest.raises(ValueError, match="shape"):
        params = H.DetectParams(1.0, local_radius_px=2)
        H.detect_cell_holes(count[1:], z, z, cell=cell, grid_window=grid.window, params=params)
    with pytest.raises(ValueError, match="connectivity"):
        params = H.DetectParams(1.0, local_radius_px=2, connectivity=6)
        H.detect_cell_holes(count, z, z, cell=cell, grid_window=grid.window, params=params)


def test_results_pickle():
    count = np.ones((N3, N3), np.uint32)
    count[18:78, 18:78] = 0
    grid, cells, cat = three_by_three(count)
    again = pickle.loads(pickle.dumps(cells[4].without_labels()))
    assert again.cell == cells[4].cell and again.labels is None
    np.testing.assert_array_equal(again.parts, cells[4].parts)
    cat2 = pickle.loads(pickle.dumps(cat))
    np.testing.assert_array_equal(cat2.holes, cat.holes)


# --------------------------------------------------------------------------------------
# cell-size invariance
# --------------------------------------------------------------------------------------


def invariance_scene(seed=7, n=200):
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[:n, :n]
    z = 100 + 0.05 * c + rng.normal(0, 0.03, (n, n))
    count = np.ones((n, n), np.uint32)
    z[40:70, 30:60] += 12.0  # building with a shadow band east of it
    count[40:70, 60:66] = 0
    lake = ((r - 140) / 25.0) ** 2 + ((c - 60) / 35.0) ** 2 < 1
    count[lake] = 0
    count[100:112, :] = 0  # strip across the whole raster (touches the grid edge)
    blobs = ndi.gaussian_filter(rng.standard_normal((n, n)), 3) > 0.12
    count[blobs] = 0
    count[rng.random((n, n)) < 0.01] = 0
    # holes touching only diagonally across cell corners at 64 and 128
    for k in (64, 128):
        count[k - 2 : k, k - 2 : k] = 0
        count[k : k + 2, k : k + 2] = 0
    aoi = (r - 100) ** 2 + (c - 100) ** 2 < 97**2  # AOI boundary inside cells
    aoi[:, 190:] = True
    return count, z, aoi


@pytest.mark.parametrize("connectivity", [4, 8])
def test_same_holes_whatever_the_cell_size(connectivity):
    count, z, aoi = invariance_scene()
    water = np.zeros(count.shape, np.uint16)
    water[150:170, 60:80] = 3
    line = (np.arange(count.shape[1])[None, :] // 50 + np.zeros((count.shape[0], 1), int)).astype(np.int64)
    results = {}
    for cell_px, col_min, row_top in ((64, 0, None), (1000, 0, None), (48, 37, 1000)):
        grid = make_grid(*count.shape, cell_px, col_min=col_min, row_top=row_top)
        zmax, zmin = surface(count, z)
        cells = detect_all(
            grid, count, zmax, zmin, aoi, connectivity=connectivity, water_points=water, flight_line=line
        )
        cat = H.link_holes([c.without_labels() for c in cells], min_area_px=4)
        causes = H.classify_causes(cat.stats, default_cause_rules(pixel_size=1.0, jump_threshold=JUMP))
        results[cell_px] = (hole_raster(grid, cells, cat), cat, causes, len(cells))
    base_raster, base, base_causes, _ = results[1000]
    assert results[64][3] > 9 and results[48][3] > 9 and results[1000][3] == 1
    for key in (64, 48):
        raster, cat, causes, _ = results[key]
        np.testing.assert_array_equal(raster, base_raster)  # the same pixel sets, the same ids
        for name in ("hole_id", "area_px", "touches_aoi_boundary", "is_small"):
            np.testing.assert_array_equal(cat.holes[name], base.holes[name])
        for name, (dtype, _, _) in H.STATS_COLUMNS.items():
            if dtype is np.float64:
                np.testing.assert_allclose(cat.stats[name], base.stats[name], rtol=1e-9, atol=1e-6, err_msg=name)
            else:
                np.testing.assert_array_equal(cat.stats[name], base.stats[name], err_msg=name)
        np.testing.assert_array_equal(cat.stats.height_hist, base.stats.height_hist)
        np.testing.assert_array_equal(cat.stats.line_hist, base.stats.line_hist)
        np.testing.assert_array_equal(causes, base_causes)
    # the partition is the connected components of the whole raster
    structure = ndi.generate_binary_structure(2, 1 if connectivity == 4 else 2)
    ref, n_ref = ndi.label((count == 0) & aoi, structure)
    assert n_ref == len(base.holes)
    pairs = np.unique(np.stack([ref[ref > 0], base_raster[ref > 0]]), axis=1)
    assert pairs.shape[1] == n_ref  # one-to-one
    # and the ring statistics are those of the whole raster
    data = count > 0
    for hole_id in (1, int(np.argmax(base.holes["area_px"])) + 1):
        mask = base_raster == hole_id
        grow = ndi.binary_dilation(mask, ndi.generate_binary_structure(2, 1))
        ring = grow & data
        assert base.stats["ring_px"][hole_id - 1] == ring.sum()


def strip_scene(n=160):
    """A missed strip (columns 70-89, outside every swath) between two swaths, with voids at its edges.

    West of it, a house at the swath's edge whose shadow (blocked from every line) opens onto the
    strip; east of it, a dark patch seen unobstructed that touches the strip; further west, a
    shadow that touches nothing; further east, a wide shadow with a sliver outside every swath
    on its side (rows 120-139: where the swath's edge runs through it, at its unknown surface).
    """
    rng = np.random.default_rng(3)
    z = 10 + rng.normal(0, 0.02, (n, n))
    count = np.ones((n, n), np.uint32)
    coverage = np.ones((n, n), np.int8)
    sight = np.zeros((n, n), np.uint8)
    coverage[:, 70:90] = 2
    count[:, 70:90] = 0
    z[20:40, 50:62] += 9.0  # the house at the strip's edge, its shadow east of it
    count[20:40, 62:70] = 0
    sight[20:40, 62:70] = BLOCKED
    count[60:72, 90:100] = 0  # the dark patch
    sight[60:72, 90:100] = SEEN
    z[100:110, 20:28] += 9.0  # a house inside the swath, its shadow touching nothing
    count[100:110, 28:33] = 0
    sight[100:110, 28:33] = BLOCKED
    z[120:140, 120:136] += 12.0  # a tall house east of the strip, its wide shadow west of it
    count[120:140, 100:120] = 0
    sight[120:140, 100:120] = BLOCKED
    coverage[120:140, 100:102] = 2
    sight[120:140, 100:102] = 0
    return count, z, coverage, sight


@pytest.mark.parametrize("connectivity", [4, 8])
def test_shadows_opening_onto_a_missed_strip_join_it_whatever_the_cell_size(connectivity):
    count, z, coverage, sight = strip_scene()
    rules = default_cause_rules(pixel_size=1.0, jump_threshold=JUMP)

    def classify(stats):
        return H.classify_causes(stats, rules, sight_known=True)

    results = {}
    for cell_px, col_min, row_top in ((1000, 0, None), (64, 0, None), (40, 13, 500)):
        grid = make_grid(*count.shape, cell_px, col_min=col_min, row_top=row_top)
        zmax, zmin = surface(count, z)
        cells = detect_all(grid, count, zmax, zmin, connectivity=connectivity, coverage=coverage, sight=sight)
        catalog = H.link_holes(
            [c.without_labels() for c in cells], min_area_px=4, joins=lambda stats: H.strip_joins(classify(stats))
        )
        results[cell_px] = (hole_raster(grid, cells, catalog), catalog, classify(catalog.stats))
    raster, catalog, causes = results[1000]
    for key in (64, 40):
        other_raster, other, other_causes = results[key]
        np.testing.assert_array_equal(other_raster, raster)
        np.testing.assert_array_equal(other.holes["area_px"], catalog.holes["area_px"])
        np.testing.assert_array_equal(other.stats["ring_px"], catalog.stats["ring_px"])
        np.testing.assert_array_equal(other_causes, causes)

    def cause_at(row, col):
        hole = raster[row, col]
        return hole, str(causes["cause"][hole - 1]), str(causes["rule"][hole - 1])

    strip, cause, rule = cause_at(5, 80)
    assert (cause, rule) == ("missed_coverage", "coverage_gap")
    assert cause_at(30, 65)[0] == strip  # the shadow opening onto the strip is part of it
    assert cause_at(65, 95)[0] != strip and cause_at(65, 95)[1] == "no_return"  # seen: apart
    assert cause_at(105, 30)[1:] == ("occlusion", "line_of_sight")  # touches nothing: itself
    wide, cause, rule = cause_at(130, 110)
    assert (cause, rule) == ("occlusion", "line_of_sight")  # 40 px outside every swath on 360 px of shadow
    assert cause_at(130, 100)[0] == wide  # ... which took the sliver in
    # the strip's ring is counted once per pixel, as on the whole raster
    mask = raster == wide
    ring = ndi.binary_dilation(mask, ndi.generate_binary_structure(2, 1)) & (count > 0)
    assert catalog.stats["ring_px"][wide - 1] == ring.sum()


def test_water_beside_a_shadow_is_no_evidence_of_water_where_the_lines_of_sight_are_known():
    """A tree's shadow on a lake's shore has the lake's edge in its ring: blocked, so an occlusion."""
    count, z, coverage, sight = strip_scene()
    water = np.zeros(count.shape, np.uint16)
    water[98:112, 33:36] = 2  # class-9 returns along the isolated shadow's east side
    grid = make_grid(*count.shape, 64)
    zmax, zmin = surface(count, z)
    cells = detect_all(grid, count, zmax, zmin, coverage=coverage, sight=sight, water_points=water)
    catalog = H.link_holes([c.without_labels() for c in cells], min_area_px=4)
    hole = hole_raster(grid, cells, catalog)[105, 30] - 1
    rules = default_cause_rules(pixel_size=1.0, jump_threshold=JUMP)
    assert catalog.stats["ring_water_px"][hole] / catalog.stats["ring_px"][hole] < H.causes.WATER_RING_SHARE
    known = H.classify_causes(catalog.stats, rules, sight_known=True)[hole]
    assert (known["cause"], known["rule"]) == ("occlusion", "line_of_sight")
    rim_only = H.classify_causes(catalog.stats, rules)[hole]
    assert (rim_only["cause"], rim_only["rule"]) == ("water", "water_points")


def test_seen_voids_join_a_missed_strip_only_where_the_heights_are_assumed():
    causes = np.array(
        [
            ("missed_coverage", "coverage_gap"),
            ("occlusion", "line_of_sight"),
            ("no_return", "seen"),
            ("water", "water_edge"),
        ],
        H.CAUSE_DTYPE,
    )
    takes_in, joins = H.strip_joins(causes)
    assert takes_in.tolist() == [1, 0, 0, 2] and joins.tolist() == [0, 1, 0, 2]  # strips take in shadows, water water
    assert H.strip_joins(causes, heights_assumed=True)[1].tolist() == [0, 1, 1, 2]


# --------------------------------------------------------------------------------------
# causes
# --------------------------------------------------------------------------------------


def classify(count, z, zmin=None, **kw):
    rules = {k: kw.pop(k) for k in list(kw) if k in ("max_shadow_ratio",)}
    _, _, cat = run(count, z, zmin=zmin, cell_px=64, min_area_px=10, **kw)
    causes = H.classify_causes(cat.stats, default_cause_rules(pixel_size=1.0, jump_threshold=JUMP, **rules))
    big = np.argmax(cat.holes["area_px"])
    return causes[big], cat


def test_cause_building_shadow_is_occlusion():
    rng = np.random.default_rng(1)
    z = 100 + rng.normal(0, 0.03, (96, 96))
    count = np.ones((96, 96), np.uint32)
    z[20:60, 20:45] += 12.0  # a 12 m building
    count[20:60, 45:51] = 0  # its scan shadow: 6 px wide band along the east wall
    cause, _ = classify(count, z)
    assert cause["cause"] == "occlusion", cause


def test_cause_courtyard_walls_is_occlusion():
    rng = np.random.default_rng(2)
    z = 100 + rng.normal(0, 0.03, (96, 96))
    zmin = z.copy()
    count = np.ones((96, 96), np.uint32)
    z[20:70, 20:70] += 15.0  # a block with a narrow courtyard nobody saw into
    count[35:55, 38:50] = 0
    ring = ndi.binary_dilation(count == 0) & (count > 0)
    zmin = np.where(ring, zmin, z)  # roof-edge pixels also hold points on the walls
    cause, _ = classify(count, z, zmin=zmin)
    assert cause["cause"] == "occlusion" and cause["rule"] == "jumps", cause


def lake_scene(n=128, rx=40, ry=28, trees=0.0, seed=4):
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[:n, :n]
    d = np.sqrt(((r - n / 2) / ry) ** 2 + ((c - n / 2) / rx) ** 2)
    wobble = 1 + 0.08 * np.sin(5 * np.arctan2(r - n / 2, c - n / 2))
    lake = d < wobble
    dist = ndi.distance_transform_edt(~lake)
    z = 20.0 + 0.15 * dist + rng.normal(0, 0.03, (n, n))  # banks rise away from the water
    zmin = z.copy()
    count = np.where(lake, 0, 5).astype(np.uint32)
    if trees:
        shore = (dist > 0) & (dist < 2.5) & (rng.random((n, n)) < trees)
        z = np.where(shore, z + 15.0, z)  # canopy; zmin stays on the ground
    return count, z, zmin


def test_cause_flat_low_lake_is_water():
    count, z, zmin = lake_scene()
    cause, _ = classify(count, z, zmin=zmin)
    assert cause["cause"] == "water" and cause["rule"] == "flat_low_rim", cause


def test_cause_lake_with_trees_on_the_shore_is_still_water():
    count, z, zmin = lake_scene(trees=0.3)
    cause, _ = classify(count, z, zmin=zmin)
    assert cause["cause"] == "water", cause


def river_scene(n=200, fall_per_px=0.01, north_bank_m=0.0, seed=6):
    """A meandering river flowing east, its surface falling ``fall_per_px`` per pixel; banks rise away."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[:n, :n]
    centre = n / 2 + 15 * np.sin(2 * np.pi * c / 120)
    offset = r - centre
    river = np.abs(offset) < 6
    water_level = 20.0 - fall_per_px * c
    bank = np.maximum(np.abs(offset) - 6, 0)
    z = water_level + 0.3 + 0.15 * bank + np.where(offset < 0, north_bank_m, 0.0) + rng.normal(0, 0.03, (n, n))
    count = np.where(river, 0, 5).astype(np.uint32)
    return count, z


@pytest.mark.parametrize("fall_per_px", [0.0, 0.002, 0.01])
def test_cause_sloped_river_is_water_by_its_rim(fall_per_px):
    # the rim falls along the course and matches across the banks: a river reach (0 to 1 %)
    count, z = river_scene(fall_per_px=fall_per_px)
    cause, _ = classify(count, z, zmin=z)
    assert cause["cause"] == "water", cause
    if fall_per_px >= 0.01:
        assert cause["rule"] == "river_rim", cause


def test_cause_river_rim_needs_level_banks_a_gentle_fall_and_a_long_hole():
    # one bank 1 m above the other: water is level across
    count, z = river_scene(north_bank_m=1.0)
    assert classify(count, z, zmin=z)[0]["cause"] != "water"
    # a reach falling 5 %: a road or a field, not a river
    count, z = river_scene(fall_per_px=0.05)
    assert classify(count, z, zmin=z)[0]["cause"] != "water"
    # a round void on a 1.8 % slope: its rim falls 0.9 m across, and a pond cannot slope
    rng = np.random.default_rng(7)
    n = 120
    r, c = np.mgrid[:n, :n]
    z = 30.0 + 0.018 * c + rng.normal(0, 0.03, (n, n))
    count = np.where(np.hypot(r - n / 2, c - n / 2) < 25, 0, 5).astype(np.uint32)
    assert classify(count, z, zmin=z)[0]["cause"] != "water"
    # the same void on a 0.5 % slope falls 0.25 m across: a level pond
    z = 30.0 + 0.005 * c + rng.normal(0, 0.03, (n, n))
    assert classify(count, z, zmin=z)[0]["cause"] == "water"


def test_cause_water_points_and_water_mask():
    count, z, zmin = lake_scene(n=96, rx=20, ry=14)
    z = z + 0.02 * np.arange(96)[None, :] * 40  # a tilted rim: geometry alone says no water
    water = ((ndi.binary_dilation(count == 0, iterations=2)) & (count > 0)).astype(np.uint16)
    cause, _ = classify(count, z, zmin=zmin, water_points=water)
    assert cause["cause"] == "water" and cause["rule"] == "water_ring"  # water all round: before any gap
    some = water.copy()
    some[:, 48:] = 0  # water returns on the western half of the ring only
    some[:, :40] = 0
    cause, _ = classify(count, z, zmin=zmin, water_points=some)
    assert cause["cause"] == "water" and cause["rule"] == "water_points"
    cause, _ = classify(count, z, zmin=zmin, water_mask=count == 0)
    assert cause["cause"] == "water" and cause["rule"] == "water_mask"


def test_cause_strip_is_missed_coverage_even_on_a_slope():
    rng = np.random.default_rng(5)
    n = 200
    z = 50 + 0.15 * np.arange(n)[None, :] + rng.normal(0, 0.05, (n, n))  # 15 % slope along the strip
    count = np.ones((n, n), np.uint32)
    count[90:102, :] = 0
    cause, _ = classify(count, z)
    assert cause["cause"] == "missed_coverage" and cause["rule"] == "strip", cause
    # flight-line evidence: both sides from different lines keeps it; one line rejects it
    lines = np.where(np.arange(n)[:, None] < 96, 1, 2) + np.zeros((1, n), int)
    assert classify(count, z, flight_line=lines)[0]["cause"] == "missed_coverage"
    assert classify(count, z, flight_line=np.ones((n, n), int))[0]["cause"] != "missed_coverage"


def test_cause_hole_on_a_hillside_is_not_occlusion():
    n = 96
    z = 10 + 0.6 * np.arange(n)[None, :] + 0.0 * np.arange(n)[:, None]  # a steep, plain slope
    count = np.ones((n, n), np.uint32)
    count[40:52, 40:52] = 0
    cause, _ = classify(count, z)
    assert cause["cause"] != "occlusion", cause


def test_cause_without_ring_is_unknown():
    count = np.zeros((64, 64), np.uint32)
    _, _, cat = run(count, cell_px=32)
    causes = H.classify_causes(cat.stats, default_cause_rules(pixel_size=1.0, jump_threshold=JUMP))
    assert causes["cause"].tolist() == ["unknown"] and causes["rule"].tolist() == ["no_ring"]


def test_merge_stats_is_exact():
    count, z, aoi = invariance_scene(seed=11, n=120)
    grid = make_grid(120, 120, 1000)
    zmax, zmin = surface(count, z)
    cells = detect_all(grid, count, zmax, zmin, aoi)
    stats = cells[0].stats
    # merging all parts into one row equals summing by hand
    merged = H.merge_hole_stats([stats, stats], [np.zeros(len(stats), int), np.zeros(len(stats), int)], 1)
    assert merged["area_px"][0] == 2 * stats["area_px"].sum()
    assert merged["row_min"][0] == stats["row_min"].min()
    mask = cells[0].labels > 0
    rows, cols = np.nonzero(mask)
    one = H.merge_hole_stats([stats], [np.zeros(len(stats), int)], 1)
    np.testing.assert_allclose(one["mean_row"][0], rows.mean())
    np.testing.assert_allclose(one["m2_rc"][0], ((rows - rows.mean()) * (cols - cols.mean())).sum())
    np.testing.assert_allclose(one["m2_rr"][0], ((rows - rows.mean()) ** 2).sum())


def test_shape_metrics_of_a_rectangle():
    count = np.ones((64, 64), np.uint32)
    count[10:16, 5:45] = 0
    _, _, cat = run(count, cell_px=32)
    m = H.shape_metrics(cat.stats)[0]
    assert m["length_px"] == pytest.approx(40) and m["width_px"] == pytest.approx(6)
    assert m["fill"] == pytest.approx(1.0) and m["thickness_px"] == pytest.approx(2 * 240 / 92)


def test_grid_window_type():
    assert isinstance(make_grid(10, 10, 16).window, PixelWindow)


def test_cell_whose_parts_are_all_settled():
    count = np.ones((N3, N3), np.uint32)
    count[40, 40] = count[50, 45] = 0
    grid = make_grid(N3, N3, 32)
    zmax, zmin = surface(count, np.zeros((N3, N3)))
    cells = detect_all(grid, count, zmax, zmin, min_area_px=3)
    middle = cells[4]
    assert middle.n_parts == 0 and middle.small_void_count == 2 and (middle.labels == -1).sum() == 2
    cat = H.link_holes(cells, min_area_px=3)
    assert len(cat.holes) == 0 and cat.small_void_count == 2 and cat.small_void_px == 2
