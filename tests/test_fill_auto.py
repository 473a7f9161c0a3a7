"""The ``auto`` fill: each hole's method chosen by cross-validation on its own rim, and the new
candidates (``spline``: regularized spline with tension; ``linear``: linear TIN).

Surfaces where the right choice is known: a plane (every method exact), a quadratic bowl (MLS
fits a quadratic exactly), a roof ridge and a step (piecewise planar along the pixel lattice: the
linear TIN is exact, the smooth methods round them off).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.ndimage as ndi

from pipeline.fill import METHOD_CODES, FillSettings, fill_region
from pipeline.fill._problem import build_problem
from pipeline.fill.by_cause import RIM, FillParams, fill_hole, fill_kind
from pipeline.fill.natural import laplace_interpolate
from pipeline.fill.region import contest, pick
from pipeline.fill.scattered import rst_basis, rst_fit

YY, XX = np.mgrid[0:80, 0:80].astype(np.float64)
PLANE = 5 + 0.3 * XX - 0.2 * YY
BOWL = 0.01 * (XX - 40) ** 2 + 0.02 * (YY - 30) ** 2
RIDGE = np.maximum(0.0, 10 - 0.5 * np.abs(XX - 40)) + 0.1 * YY
STEP = np.where(XX > 40, 10.0, 0.0)
#: The pipeline's fairing (fill.tin_order = 1); biharmonic tin would be exact on the bowl too.
HARMONIC = FillSettings(tin_order=1, auto_candidates=("tin", "spline", "mls", "linear"))


def _hole() -> np.ndarray:
    region = np.zeros(PLANE.shape, bool)
    region[25:50, 28:55] = True
    return region


def _rmse(out, z, region) -> float:
    return float(np.sqrt(np.mean((out.heights[region] - z[region]) ** 2)))


def test_rst_basis_is_zero_at_zero_and_interpolates_without_smoothing():
    assert rst_basis(np.array([0.0]), 40.0)[0] == 0.0
    rng = np.random.default_rng(0)
    pts = rng.random((50, 2)) * 30
    z = np.sin(pts[:, 0] / 5) + pts[:, 1] / 10
    np.testing.assert_allclose(rst_fit(pts, z, pts, tension=40.0, smoothing=0.0), z, atol=1e-8)


def test_rst_reproduces_planes_even_with_smoothing():
    rng = np.random.default_rng(1)
    pts = rng.random((40, 2)) * 50
    plane = lambda p: 3.0 + 0.4 * p[:, 0] - 0.7 * p[:, 1]  # noqa: E731
    queries = rng.random((20, 2)) * 50
    np.testing.assert_allclose(
        rst_fit(pts, plane(pts), queries, tension=40.0, smoothing=0.1), plane(queries), atol=1e-9
    )


def test_rst_with_too_few_points_is_nan():
    assert np.isnan(rst_fit(np.zeros((2, 2)), np.zeros(2), np.zeros((3, 2)), tension=40.0, smoothing=0.1)).all()


@pytest.mark.parametrize("method", ["spline", "linear", "natural"])
def test_new_kernels_are_exact_on_a_plane_and_coded(method):
    region = _hole()
    out = fill_region(np.where(region, np.nan, PLANE), region, method=method)
    assert _rmse(out, PLANE, region) < 1e-5  # linear: the 1e-6 px jitter of its triangulation
    assert (out.method_code[region] == METHOD_CODES[method]).all()
    assert [c.method for c in out.components] == [method]


@pytest.mark.parametrize("method", ["linear", "natural"])
def test_linear_fills_a_hole_open_to_the_window_edge(method):
    region = np.zeros(PLANE.shape, bool)
    region[30:45, 70:] = True  # beyond the hull of its rim: nearest support height there
    out = fill_region(np.where(region, np.nan, PLANE), region, method=method)
    assert np.isfinite(out.heights[region]).all()
    inside = region & (XX < 78)
    assert np.abs(out.heights[inside] - PLANE[inside]).max() < 1e-5


def test_natural_neighbour_weights_by_voronoi_edge_over_distance():
    """Four data points on a square's corners, the query at its centre: the query's Voronoi cell
    is the square of the corners' bisectors, every edge the same, so the mean; a query nearer
    one corner leans to it, and every value stays within the data's range (no overshoot)."""
    square = np.array([[0.0, 0.0], [0.0, 10.0], [10.0, 0.0], [10.0, 10.0]])
    z = np.array([1.0, 2.0, 3.0, 10.0])
    centre = laplace_interpolate(square, z, np.array([[5.0, 5.0]]))
    # the four corners are co-circular: the two triangulations give the same Laplace weights
    assert centre[0] == pytest.approx(z.mean())
    rng = np.random.default_rng(4)
    queries = rng.uniform(0.5, 9.5, (200, 2))
    values = laplace_interpolate(square, z, queries)
    assert np.all((values >= z.min() - 1e-9) & (values <= z.max() + 1e-9))
    near = laplace_interpolate(square, z, np.array([[9.0, 9.0]]))[0]
    assert near > 7.0
    assert np.isnan(laplace_interpolate(square, z, np.array([[20.0, 20.0]]))[0])  # outside the hull


def test_natural_matches_startinpy_laplace():
    """The same interpolant as the fill benchmark's ``laplace`` alternative (startinpy, optional)."""
    startinpy = pytest.importorskip("startinpy")
    rng = np.random.default_rng(5)
    points = rng.uniform(0, 50, (300, 2))
    z = np.sin(points[:, 0] / 7) * 3 + np.cos(points[:, 1] / 5) * 2
    dt = startinpy.DT()
    dt.insert(np.column_stack([points, z]))
    queries = rng.uniform(10, 40, (40, 2))
    theirs = np.array([dt.interpolate({"method": "Laplace"}, [q])[0] for q in queries])
    np.testing.assert_allclose(laplace_interpolate(points, z, queries), theirs, atol=1e-6)


def test_a_rough_rim_makes_tin_the_reference_a_smooth_one_keeps_natural():
    """Crowns around a hole (heights scattered by metres about any plane): tin is the reference;
    sloped ground with 5 cm of noise: the first candidate, natural, stays."""
    from pipeline.fill._problem import build_problem as problem_of
    from pipeline.fill.region import rough_rims

    region = _hole()
    crowns = PLANE + 8.0 * (np.random.default_rng(0).random(PLANE.shape) > 0.5)
    settings = FillSettings(tin_order=1, auto_candidates=("natural", "tin"), auto_rough_rim=2.5)
    ground = PLANE + np.random.default_rng(1).normal(0.0, 0.05, PLANE.shape)
    for surface, rough in ((crowns, True), (ground, False)):
        heights = np.where(region, np.nan, surface)
        problem = problem_of(heights, region, pixel_size=1.0, settings=settings)
        assert rough_rims(problem, np.array([1]), 2.5).tolist() == ([1] if rough else [])
        out = fill_region(heights, region, method="auto", settings=settings)
        assert out.components[0].method == ("tin" if rough else "natural")
    assert rough_rims(problem, np.array([1]), math.inf).tolist() == []  # the default: never


def test_auto_picks_mls_on_a_quadratic_where_it_alone_is_exact():
    region = _hole()
    out = fill_region(np.where(region, np.nan, BOWL), region, method="auto", settings=HARMONIC)
    (rec,) = out.components
    assert rec.method == "mls" and rec.error_estimate < 1e-9
    assert _rmse(out, BOWL, region) < 1e-6
    assert (out.method_code[region] == METHOD_CODES["mls"]).all()
    tin = fill_region(np.where(region, np.nan, BOWL), region, method="tin", settings=HARMONIC)
    assert _rmse(tin, BOWL, region) > 1.0


@pytest.mark.parametrize("surface", [RIDGE, STEP])
def test_auto_beats_the_harmonic_tin_alone_across_a_ridge_and_a_step(surface):
    region = _hole()
    auto = fill_region(np.where(region, np.nan, surface), region, method="auto", settings=HARMONIC)
    tin = fill_region(np.where(region, np.nan, surface), region, method="tin", settings=HARMONIC)
    assert auto.components[0].method != "tin"
    assert _rmse(auto, surface, region) < 0.95 * _rmse(tin, surface, region)


def test_auto_records_the_winners_cross_validation_error_and_every_score():
    region = _hole()
    noisy = BOWL + np.random.default_rng(2).normal(0, 0.05, BOWL.shape)
    out = fill_region(np.where(region, np.nan, noisy), region, method="auto", settings=HARMONIC)  # no estimate_error
    (rec,) = out.components
    assert math.isfinite(rec.error_estimate) and 0 < rec.error_estimate < 0.5
    for name in ("tin", "spline", "mls", "linear"):
        assert name in rec.detail
    assert " withheld rim pixels (RMSE " in rec.detail  # how many pixels the scores rest on
    problem = build_problem(np.where(region, np.nan, noisy), region, pixel_size=1.0, settings=HARMONIC, support=None)
    scores = contest(problem, np.array([1]), ("tin", "spline", "mls", "linear"))[1]
    assert set(scores) == {"tin", "spline", "mls", "linear"}
    # the winner is the reference (tin) or predicts the rim better than it
    assert rec.method == "tin" or scores[rec.method] < scores["tin"]
    assert rec.error_estimate == pytest.approx(scores[rec.method])


def test_tiny_voids_get_no_contest_and_candidates_can_be_restricted():
    region = np.zeros(PLANE.shape, bool)
    region[5:6, 5:8] = True  # 3 px: tin, no contest
    region[25:50, 28:55] = True
    out = fill_region(np.where(region, np.nan, RIDGE), region, method="auto", settings=HARMONIC)
    methods = {c.n_pixels: c.method for c in out.components}
    assert methods[3] == "tin" and methods[25 * 27] != "tin"
    only = FillSettings(tin_order=1, auto_candidates=("tin", "spline"))
    assert FillSettings().auto_candidates == ("natural", "tin")  # the default: methods bounded by their rim
    out = fill_region(np.where(region, np.nan, RIDGE), region, method="auto", settings=only)
    assert {c.method for c in out.components} <= {"tin", "spline"}


def test_pick_keeps_the_reference_unless_another_is_significantly_better():
    noise = np.random.default_rng(3).normal(0, 1, 200) ** 2
    # the same errors in another order: a lower RMSE claimed, no paired evidence for it
    assert pick({"tin": (1.0, noise), "mls": (0.9, noise[::-1])}, ("tin", "mls"), 2.0) == "tin"
    clear = {"tin": (1.0, noise + 1.0), "spline": (0.5, noise), "mls": (0.7, noise + 0.2)}
    assert pick(clear, ("tin", "spline", "mls"), 2.0) == "spline"
    assert pick({"mls": (0.1, noise)}, ("tin", "mls"), 2.0) == "mls"  # tin could not fill: the first that could


def test_settings_reject_unknown_or_repeated_candidates():
    with pytest.raises(ValueError, match="auto_candidates"):
        FillSettings(auto_candidates=("tin", "flat"))
    with pytest.raises(ValueError, match="auto_candidates"):
        FillSettings(auto_candidates=("tin", "tin"))


def test_a_covered_dtm_void_is_filled_from_its_whole_rim_by_the_contest_never_flat():
    # a DTM void under a removed building on a curved slope: cause "covered"
    region = _hole()
    ground = BOWL + 0.2 * XX
    assert fill_kind("covered", _params()) == RIM
    measured = ~region
    labels = region.astype(np.int32)
    out = fill_hole(
        np.where(measured, ground, np.nan), np.where(measured, ground, np.nan), measured, labels, RIM, _params()
    )
    assert np.ptp(out.heights[region]) > 5.0  # follows the ground, not one level
    assert _rmse(out, ground, region) < 0.01
    assert out.components[0].method == "mls"  # a quadratic: MLS is exact


def test_the_configured_candidates_reach_the_kernels():
    from pipeline.config import load_config
    from pipeline.parameters import fill_params, hole_params

    config = load_config(overrides=['fill.auto_candidates=["tin", "mls"]'])
    holes = hole_params(config, pixel_size_m=1.0, spacing_m=0.5, vertical_unit_m=1.0)
    params = fill_params(config, holes, pixel_size=1.0, horizontal_unit_m=1.0, vertical_unit_m=1.0)
    assert params.settings.auto_candidates == ("tin", "mls")
    assert load_config().fill.auto_candidates == ["natural", "tin"]


def _params() -> FillParams:
    return FillParams(
        method="auto", by_cause=True, pixel_size=1.0, max_distance=math.inf, jump_threshold=2.5, settings=HARMONIC
    )


def test_component_centroids_are_scipys_centres_of_mass_bit_for_bit():
    # the holdout sectors are cut around these centroids: the same bits keep the contest's pick
    rng = np.random.default_rng(7)
    for _ in range(20):
        shape = tuple(int(v) for v in rng.integers(3, 200, 2))
        heights = np.where(rng.random(shape) < rng.uniform(0.05, 0.6), np.nan, 1.0)
        problem = build_problem(heights, np.isnan(heights), pixel_size=1.0, settings=FillSettings())
        if problem.n_labels == 0:
            continue
        expected = ndi.center_of_mass(np.ones(shape), problem.labels, np.arange(1, problem.n_labels + 1))
        assert np.array_equal(problem.centroids(), np.asarray(expected, float).reshape(-1, 2))
