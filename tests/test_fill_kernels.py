"""Fill kernels on small synthetic arrays: exactness, independence, masks, codes."""

from __future__ import annotations

import pickle
import subprocess
import sys

import numpy as np
import pytest
import scipy.ndimage as ndi

from pipeline.fill import (
    METHOD_CODES,
    NOT_FILLED,
    FillSettings,
    fill_distance,
    fill_region,
    leave_boundary_out_error,
    lower_side_support,
    rim_level,
    smooth_seams,
)

YY, XX = np.mgrid[0:40, 0:50].astype(np.float64)
PLANE = 3 + 0.2 * XX - 0.1 * YY
QUADRATIC = 1 + 0.01 * XX**2 - 0.02 * XX * YY + 0.005 * YY**2 + 0.3 * XX
HARMONIC = 0.01 * (XX**2 - YY**2)
SMOOTH = 3 * np.sin(XX / 7) * np.cos(YY / 9)


def _holes() -> np.ndarray:
    region = np.zeros(PLANE.shape, bool)
    region[10:25, 12:30] = True
    region[30:33, 5:9] = True
    region[5, 40] = True
    return region


def _fill(surface, region, method, **kw):
    h = surface.copy()
    h[region] = np.nan
    return fill_region(h, region, method=method, pixel_size=kw.pop("pixel_size", 0.5), **kw)


def _maxerr(out, surface, region):
    return float(np.max(np.abs(out.heights - surface)[region]))


@pytest.mark.parametrize("surface", [PLANE, QUADRATIC], ids=["plane", "quadratic"])
@pytest.mark.parametrize("weight", ["wendland", "cubic", "gaussian"])
def test_mls_reproduces_planes_and_quadratics(surface, weight):
    region = _holes()
    out = _fill(surface, region, "mls", settings=FillSettings(mls_weight=weight))
    assert _maxerr(out, surface, region) < 1e-6
    assert all(c.method == "mls" and c.order == 2 and not c.degraded for c in out.components if c.n_pixels > 1)


def test_mls_lattice_keeps_quadratics_exact():
    yy, xx = np.mgrid[0:90, 0:90].astype(np.float64)
    surface = 2 + 0.002 * xx**2 + 0.001 * xx * yy - 0.003 * yy**2
    region = (yy - 45) ** 2 + (xx - 45) ** 2 <= 35**2
    out = _fill(surface, region, "mls", pixel_size=1.0)
    assert _maxerr(out, surface, region) < 1e-6


def test_mls_tilted_frame_reproduces_planes():
    region = _holes()
    out = _fill(PLANE, region, "mls", settings=FillSettings(mls_frame="tilted"))
    assert _maxerr(out, PLANE, region) < 1e-6


@pytest.mark.parametrize("surface", [PLANE, HARMONIC], ids=["plane", "x2-y2"])
def test_harmonic_fill_reproduces_harmonic_functions(surface):
    region = _holes()
    out = _fill(surface, region, "tin", settings=FillSettings(tin_order=1))
    assert _maxerr(out, surface, region) < 1e-8


def test_biharmonic_reproduces_quadratics_and_beats_harmonic_on_smooth_surface():
    region = _holes()
    assert _maxerr(_fill(QUADRATIC, region, "tin"), QUADRATIC, region) < 1e-8
    first = _maxerr(_fill(QUADRATIC, region, "tin", settings=FillSettings(tin_order=1)), QUADRATIC, region)
    assert first > 0.1  # harmonic cannot carry curvature
    err2 = _maxerr(_fill(SMOOTH, region, "tin"), SMOOTH, region)
    err1 = _maxerr(_fill(SMOOTH, region, "tin", settings=FillSettings(tin_order=1)), SMOOTH, region)
    assert err2 < 0.1 and err2 < err1


def test_large_component_reduced_system_reproduces_planes():
    yy, xx = np.mgrid[0:120, 0:120].astype(np.float64)
    surface = 5 + 0.3 * xx - 0.2 * yy
    region = (yy - 60) ** 2 + (xx - 60) ** 2 <= 50**2
    for order in (1, 2):
        out = _fill(surface, region, "tin", settings=FillSettings(tin_order=order, tin_direct_max_px=1000))
        assert "reduced" in out.components[0].detail
        assert _maxerr(out, surface, region) < 1e-6


def test_idw_and_nearest_are_sane():
    region = _holes()
    for method in ("idw", "nearest"):
        out = _fill(PLANE, region, method)
        filled = out.heights[region]
        rim = PLANE[~region]
        assert np.all(np.isfinite(filled))
        assert filled.min() >= rim.min() - 1e-9 and filled.max() <= rim.max() + 1e-9
        assert np.all(out.method_code[region] == METHOD_CODES[method])
    single = np.zeros_like(region)
    single[20, 20] = True
    const = np.full(PLANE.shape, 7.0)
    assert _fill(const, single, "nearest").heights[20, 20] == 7.0
    assert _fill(const, single, "idw").heights[20, 20] == pytest.approx(7.0)


def test_flat_fill_is_exact_at_rim_percentile_or_given_level():
    region = _holes()
    out = _fill(PLANE, region, "flat")
    level = rim_level(np.where(region, np.nan, PLANE), region, percentile=10.0)
    for rec in out.components:
        assert rec.level == pytest.approx(level[rec.label])
        assert np.all(out.heights[out.labels == rec.label] == rec.level)
    fixed = _fill(PLANE, region, "flat", settings=FillSettings(flat_level=1.5))
    assert np.all(fixed.heights[region] == 1.5)


def test_measured_pixels_are_never_changed_and_dtype_kept():
    region = _holes()
    h = PLANE.astype(np.float32)
    h[region] = np.nan
    for method in ("tin", "mls", "idw", "nearest", "flat", "auto"):
        out = fill_region(h, region, method=method)
        assert out.heights.dtype == np.float32
        np.testing.assert_array_equal(out.heights[~region], h[~region])
        assert np.all(out.method_code[~region] == 0)
    assert np.isnan(h[region]).all()  # input untouched


def test_components_are_filled_independently():
    region = _holes()
    h = PLANE.copy()
    h[region] = np.nan
    both = fill_region(h, region, method="tin")
    one = region.copy()
    one[30:33, 5:9] = False
    alone = fill_region(h, one, method="tin")
    np.testing.assert_allclose(both.heights[one], alone.heights[one], atol=1e-10)
    # two holes sharing a rim pixel (biharmonic energies must not couple them)
    z = SMOOTH.copy()
    two = np.zeros(z.shape, bool)
    two[10:20, 10:20] = True
    two[10:20, 21:30] = True
    hz = z.copy()
    hz[two] = np.nan
    joint = fill_region(hz, two, method="tin")
    left = two.copy()
    left[:, 21:] = False
    sep = fill_region(hz, left, method="tin")  # the other hole unknown but not filled
    np.testing.assert_allclose(joint.heights[left], sep.heights[left], atol=1e-10)


def test_caller_labels_split_components():
    region = np.zeros((20, 20), bool)
    region[5:15, 5:15] = True
    labels = np.zeros((20, 20), np.int32)
    labels[5:15, 5:10] = 1
    labels[5:15, 10:15] = 2
    z = np.where(np.arange(20)[None, :] < 10, 1.0, 5.0) * np.ones((20, 1))
    out = fill_region(np.where(region, np.nan, z), region, method="tin", labels=labels)
    assert [c.label for c in out.components] == [1, 2]
    assert out.heights[10, 6] < 2.0 and out.heights[10, 13] > 4.0
    with pytest.raises(ValueError, match="labels"):
        fill_region(z, region, labels=np.zeros((20, 20), np.int32))


def test_unknown_method_and_bad_shapes_raise():
    with pytest.raises(ValueError, match="unknown fill method"):
        fill_region(PLANE, _holes(), method="kriging")
    with pytest.raises(ValueError, match="shape"):
        fill_region(PLANE, np.zeros((3, 3), bool))
    with pytest.raises(ValueError, match="seam_gamma"):
        FillSettings(seam_gamma=1.5)


def test_region_without_support_stays_nan_with_code_255():
    h = np.full((10, 10), np.nan)
    region = np.zeros((10, 10), bool)
    region[3:6, 3:6] = True
    for method in ("tin", "mls", "idw", "nearest", "flat", "auto"):
        out = fill_region(h, region, method=method)
        assert np.isnan(out.heights[region]).all()
        assert np.all(out.method_code[region] == NOT_FILLED)
        assert not out.components[0].filled


@pytest.mark.parametrize("method", ["tin", "mls", "idw", "nearest", "flat", "auto"])
def test_no_nan_leaks_into_filled_pixels_when_support_exists(method):
    rng = np.random.default_rng(3)
    h = SMOOTH.copy()
    h[rng.random(h.shape) < 0.05] = np.nan  # scattered unknown pixels outside the region
    region = _holes()
    out = fill_region(h, region, method=method)
    assert np.isfinite(out.heights[region]).all()
    assert np.all(out.method_code[region] != NOT_FILLED)


def _building_scene():
    """Ground plane at 10 m, a building at 20 m (cols 30+), an occlusion hole between."""
    z = np.full((30, 50), 10.0) + 0.01 * np.arange(50)[None, :]
    z[:, 30:] = 20.0
    region = np.zeros(z.shape, bool)
    region[8:22, 22:30] = True
    h = z.copy()
    h[region] = np.nan
    wall = np.zeros(z.shape, bool)
    wall[:, 30] = True
    return z, h, region, wall


@pytest.mark.parametrize("method", ["tin", "mls", "idw"])
def test_step_kept_next_to_building(method):
    z, h, region, wall = _building_scene()
    naive = fill_region(h, region, method="tin")
    assert naive.heights[15, 29] > 12.0  # ramps up to the roof
    support = lower_side_support(h, region, jump_threshold=2.0)
    assert not support[15, 30] and support[15, 21]
    out = fill_region(h, region, method=method, support=support, barriers=wall)
    assert np.abs(out.heights[region] - z[region]).max() < 0.5


def test_support_and_barrier_masks_are_honoured():
    z = np.zeros((20, 20))
    z[:, 10:] = 100.0
    region = np.zeros(z.shape, bool)
    region[5:15, 5:15] = True
    h = np.where(region, np.nan, z)
    support = np.ones(z.shape, bool)
    support[:, 10:] = False
    out = fill_region(h, region, method="idw", support=support)
    assert np.all(out.heights[region] == 0.0)
    barriers = np.zeros(z.shape, bool)
    barriers[:, 10] = True
    out = fill_region(h, region, method="tin", barriers=barriers)
    left, right = out.heights[5:15, 5:10], out.heights[5:15, 11:15]
    assert np.allclose(left, 0.0) and np.allclose(right, 100.0)
    assert np.all(out.method_code[5:15, 10] == METHOD_CODES["barrier"])
    assert np.allclose(out.heights[5:15, 10], 100.0)  # a wall pixel holds the wall top


def test_degradation_recorded_when_neighbours_are_few():
    h = np.full((12, 12), np.nan)
    h[5, 2] = 1.0
    h[5, 8] = 3.0
    region = np.zeros(h.shape, bool)
    region[4:7, 3:8] = True
    out = fill_region(h, region, method="mls")
    rec = out.components[0]
    assert rec.degraded and rec.order < 2 and rec.detail
    assert np.isfinite(out.heights[region]).all()


def test_auto_chooses_per_component_and_codes_match():
    yy, xx = np.mgrid[0:120, 0:120].astype(np.float64)
    z = 0.001 * xx**2 + 0.1 * yy
    region = np.zeros(z.shape, bool)
    region[10:12, 10:12] = True
    region[40:100, 40:100] = True  # compact, large
    region[5:8, 30:118] = True  # a long strip
    # without a contest (no candidates) auto is the shape rule: tin, mls for large round holes on request
    no_contest = FillSettings(auto_candidates=())
    assert {c.method for c in fill_region(np.where(region, np.nan, z), region, settings=no_contest).components} == {
        "tin"
    }
    settings = FillSettings(auto_mls_min_px=100, auto_candidates=())
    out = fill_region(np.where(region, np.nan, z), region, method="auto", settings=settings)
    used = {c.label: c.method for c in out.components}
    assert sorted(used.values()) == ["mls", "tin", "tin"]
    for c in out.components:
        assert np.all(out.method_code[out.labels == c.label] == METHOD_CODES[c.method])


def test_smooth_seams_reduces_step_and_keeps_measured_pixels():
    z = np.zeros((20, 20))
    z[:, 10:] = 1.0  # two cells filled separately meet at column 10
    filled = np.zeros(z.shape, bool)
    filled[5:15, 5:15] = True
    seam = np.zeros(z.shape, bool)
    seam[:, 9:11] = True
    out = smooth_seams(z, filled, seam, gamma=0.5, iterations=20, width_px=2)
    assert abs(out[10, 10] - out[10, 9]) < abs(z[10, 10] - z[10, 9])
    np.testing.assert_array_equal(out[~filled], z[~filled])
    far = filled & (np.abs(np.arange(20)[None, :] - 9.5) > 3) * np.ones((20, 1), bool)
    np.testing.assert_array_equal(out[far], z[far])


def test_fill_distance_in_survey_units():
    measured = np.ones((5, 9), bool)
    measured[2, 2:7] = False
    d = fill_distance(measured, pixel_size=2.0)
    assert d[2, 4] == pytest.approx(2.0) and d[0, 0] == 0.0


def test_leave_boundary_out_error():
    region = _holes()
    h = np.where(region, np.nan, PLANE)
    err = leave_boundary_out_error(h, region, method="tin")
    assert err[1] < 1e-8  # planes are exact
    err_s = leave_boundary_out_error(np.where(region, np.nan, SMOOTH), region, method="nearest")
    assert err_s[1] > 0
    out = fill_region(h, region, method="tin", settings=FillSettings(estimate_error=True))
    assert out.component(1).error_estimate == pytest.approx(err[1])


def test_settings_and_outcome_pickle():
    s = FillSettings(tin_order=1)
    assert pickle.loads(pickle.dumps(s)) == s
    out = fill_region(np.where(_holes(), np.nan, PLANE), _holes(), method="tin")
    back = pickle.loads(pickle.dumps(out))
    assert [(c.label, c.method, c.n_support) for c in back.components] == [
        (c.label, c.method, c.n_support) for c in out.components
    ]
    np.testing.assert_array_equal(back.heights, out.heights)


def test_fill_package_imports_no_io_or_dask():
    code = (
        "import sys, pipeline.fill; bad = [m for m in ('laspy', 'rasterio', 'pyogrio', 'geopandas', "
        "'dask', 'distributed') if m in sys.modules]; print(','.join(bad))"
    )
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == ""


def test_clamp_to_rim_keeps_fills_within_each_components_rim():
    from pipeline.fill import clamp_to_rim

    heights = np.array(
        [
            [1.0, 1.0, 1.0, 1.0, 7.0, 7.0, 7.0],
            [1.0, np.nan, np.nan, 5.0, 7.0, np.nan, 9.0],
            [1.0, 1.0, 1.0, 1.0, 7.0, 8.0, 7.0],
        ]
    )
    region = np.isnan(heights)
    filled = np.where(region, np.array([[0, 9.0, -3.0, 0, 0, 20.0, 0]] * 3), heights)
    out = clamp_to_rim(filled, heights, region)
    assert out[1, 1] == 5.0 and out[1, 2] == 1.0  # left hole: rim 1..5
    assert out[1, 5] == 9.0  # right hole: rim 7..9
    np.testing.assert_array_equal(out[~region], heights[~region])  # measured pixels untouched
    low_side = np.zeros_like(region)
    low_side[0, 1:3] = low_side[2, 1:3] = low_side[1, 0] = True  # only the 1 m rim supports the left hole
    out = clamp_to_rim(filled, heights, region, support=low_side)
    assert out[1, 1] == 1.0 and out[1, 2] == 1.0


@pytest.mark.parametrize("seed", range(4))
def test_the_low_side_of_a_step_but_the_whole_rim_of_a_slope(seed):
    """An occlusion is filled from the low side of the step beside it; on a hillside the rim spans
    more than a step without one, and the whole rim is the support (``pdal_alirt_afghan``: a cut
    void on a 48 degree slope was filled 10 m low from its lower rim). A shadow band along a wall,
    whose rim a tilted plane fits exactly, and a one-pixel void at a wall's foot keep the low side."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[:40, :40].astype(float)
    angle = rng.uniform(0, 2 * np.pi)
    slope = 1.1 * (np.cos(angle) * cols + np.sin(angle) * rows) + rng.normal(0, 0.8, (40, 40))  # 48 deg, rough
    hole = np.zeros((40, 40), bool)
    hole[15:25, 14:26] = True
    support = lower_side_support(np.where(hole, np.nan, slope), hole, jump_threshold=2.5)
    rim = ndi.binary_dilation(hole, structure=np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], bool)) & ~hole
    assert support[rim].all()

    street = rng.normal(0, 0.05, (40, 40))
    band = street.copy()
    band[:, :14] += 12.0  # a roof west of a wall at column 14
    shadow = np.zeros((40, 40), bool)
    shadow[5:35, 14:20] = True  # its 6 px scan shadow along the wall
    support = lower_side_support(np.where(shadow, np.nan, band), shadow, jump_threshold=2.5)
    assert not support[5:35, 13].any() and support[5:35, 20].all()

    foot = np.zeros((40, 40), bool)
    foot[20, 14] = True
    support = lower_side_support(np.where(foot, np.nan, band), foot, jump_threshold=2.5)
    assert not support[20, 13] and support[20, 15] and support[19, 14] and support[21, 14]


def test_linear_quantiles_are_numpy_s_value_for_value(rng):
    """The rim levels and the walls' steps take numpy's quantiles without its per-call set-up: the same doubles,
    ties, ends and NaN-skipping percentiles included."""
    from pipeline.quantiles import linear_quantiles

    for _ in range(2000):
        values = rng.normal(0, 10, int(rng.integers(1, 40)))
        if rng.random() < 0.3:
            values = np.round(values)  # ties
        quantiles = (0.0, 0.1, 0.5, 0.9, 1.0, float(rng.random()))
        assert linear_quantiles(values, quantiles) == list(np.quantile(values, quantiles))
        percentile = float(rng.integers(0, 101))
        assert linear_quantiles(values, (percentile / 100,)) == [np.percentile(values, percentile)]
        with_gaps = np.where(rng.random(len(values)) < 0.2, np.nan, values)  # a wall's lows: NaN where no lowest point
        if np.isfinite(with_gaps).any():
            finite = with_gaps[np.isfinite(with_gaps)]
            assert linear_quantiles(finite, (0.2,)) == [np.nanpercentile(with_gaps, 20)]
