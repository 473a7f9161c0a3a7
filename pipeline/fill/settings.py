"""Value objects of the fill kernels: settings, per-component records, outcome, method codes.

Everything here is a frozen dataclass or a constant, so it pickles, hashes into
stable Dask keys and can be built from configuration at one adapter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "METHOD_CODES",
    "METHOD_NAMES",
    "NOT_FILLED",
    "UNTOUCHED",
    "ComponentFill",
    "FillOutcome",
    "FillSettings",
]

UNTOUCHED = 0
"""``method_code`` of pixels outside the region (measured or simply not asked for)."""

NOT_FILLED = 255
"""``method_code`` of region pixels that could not be filled (no support); their height is NaN."""

METHOD_CODES: dict[str, int] = {
    "nearest": 1,
    "idw": 2,
    "mls": 3,
    "tin": 4,
    "flat": 5,
    "barrier": 6,
    "river": 7,
    "spline": 8,
    "linear": 9,
    "natural": 10,
}
"""``method_code`` per method. ``barrier`` marks region pixels lying on a barrier
(a wall line): they take the highest adjacent filled or measured height, since a
DSM pixel on a wall holds the top of the wall. ``river`` marks water holes filled
with a surface stepping down along their course (:mod:`pipeline.fill.hydro`)."""

METHOD_NAMES: dict[int, str] = {v: k for k, v in METHOD_CODES.items()} | {
    UNTOUCHED: "untouched",
    NOT_FILLED: "not filled",
}

_WEIGHTS = ("wendland", "cubic", "gaussian")
_FRAMES = ("horizontal", "tilted")
#: Methods ``auto`` can choose among (``flat`` is for water only, ``barrier`` not a method).
_CANDIDATES = ("tin", "spline", "mls", "linear", "natural", "idw", "nearest")


@dataclass(frozen=True)
class FillSettings:
    """Parameters of every fill method, with defaults that suit 0.25-2 m DSMs.

    Distances are in pixels (``_px``) so one settings object serves any pixel size.

    Attributes
    ----------
    mls_k : int
        Improved MLS: each boundary pixel contributes its ``k`` nearest measured
        neighbours as support points ([MLS] 2.1 step 3). Default 8.
    mls_order : int
        Highest order of the MLS basis: 2 = quadratic ``(1, u, v, u^2, uv, v^2)``
        ([MLS] eq. 11), 1 = linear, 0 = constant. Default 2.
    mls_weight : {"wendland", "cubic", "gaussian"}
        Compactly supported weight ``w(r)``, ``r = distance / h``: Wendland C2
        ``(1-r)^4 (4r+1)``, the cubic B-spline, or a Gaussian cut (and shifted) to 0 at r = 1.
    mls_radius_factor : float
        Support radius ``h = max(mls_radius_factor * D, mls_min_radius_px)`` where
        ``D`` is the distance from the evaluated pixel to the nearest support point,
        so every pixel sees the rim on all sides of a compact hole. Default 2.5.
    mls_min_radius_px : float
        Smallest support radius; 4.5 px puts at least three rows of rim
        neighbours inside it (two rows cannot carry the curvature across the rim). Default 4.5.
    mls_min_points : int
        Fewer support points than this inside ``h`` widens ``h`` (x1.5 steps) and the
        component is marked degraded. Default 10.
    mls_band_fraction : float
        Large holes: the support is the whole band of measured pixels within
        ``mls_band_fraction * sqrt(hole pixels)`` of the rim when that is wider than the
        k-neighbour band. A thin rim around a big round hole nearly satisfies
        ``u^2 + v^2 = R^2``, which leaves the quadratic undetermined in the middle; a
        thick one fixes it. Default 0.1.
    mls_drop_tolerance : float
        Gram-Schmidt drops a basis function whose weighted orthogonal remainder is below
        this fraction of its own weighted norm. Default 1e-6.
    mls_frame : {"horizontal", "tilted"}
        Local frame ([MLS] 2.3.2 steps 1-2). "tilted": the PCA plane of the support
        points is the UV plane and the height is where the vertical line through the
        pixel centre meets the fitted surface. "horizontal" (default): the same U
        axis, but S stays vertical; a DSM is a height field, and only this keeps the
        exact reproduction of quadratic surfaces z(x, y).
    mls_dense_band_px : float
        Pixels closer than this to the support are evaluated one by one; farther ones
        (where ``h`` is large and the surface very smooth) are interpolated from a
        lattice of MLS values with 4x4 Lagrange (cubic) weights, which reproduces
        quadratics exactly. ``0`` disables the lattice. Default 8.
    mls_lattice_step_px : int
        Lattice spacing. Default 4.
    tin_order : int
        Fairing order of the ``tin`` method ([OPEN] 3.3): 1 = umbrella operator
        (harmonic, Laplace), 2 = second-order umbrella (biharmonic). Default 2.
    tin_direct_max_px : int
        Components up to this size are solved exactly at full resolution; larger ones
        keep full resolution within ``tin_band_px`` of the rim and use a bilinear
        lattice of spacing ``tin_lattice_px`` inside (a Galerkin-reduced system).
        Default 6000.
    tin_band_px, tin_lattice_px : int
        See ``tin_direct_max_px``. Defaults 4 and 6.
    idw_k : int
        Neighbours of inverse distance weighting. Default 12.
    idw_power : float
        Power of inverse distance weighting. Default 2.
    flat_percentile : float
        Water level = this percentile of the rim heights (a low one: shore pixels
        include vegetation and walls, never anything below the water). Default 10.
    flat_level : float or None
        A fixed level for ``flat`` instead of the rim percentile. Default None.
    auto_mls_min_px : int
        ``auto``: components of at least this many pixels that are round use ``mls``;
        everything else uses ``tin``. ``0`` (default) never picks ``mls``: on the
        synthetic benchmark (docs/filling.md) the biharmonic ``tin`` is more accurate
        than ``mls`` for small and for large holes alike.
    auto_mls_min_roundness : float
        Roundness = pixels / area of the circle whose diameter is the longer side of
        the bounding box (disc 1, square 1.27, strip 3x90 0.04). Default 0.5.
    auto_candidates : tuple of str
        ``auto``: the methods that compete for each component of at least
        ``auto_contest_min_px`` pixels; the one with the lowest cross-validation error on
        the component's own rim (withheld rim sectors, as ``estimate_error``) fills it and
        that error is its ``error_estimate``. Default ``("natural", "tin")``: natural-neighbour
        interpolation unless the harmonic fairing predicts the rim significantly better (both
        stay within their rim); with ``spline`` and ``mls`` too the real-survey benchmark got
        worse (they predict the rim well and overshoot inside; docs/performance.md).
        Empty: no contest (``tin``, or ``mls`` by ``auto_mls_min_px``, as before).
    auto_contest_min_px : int
        Components smaller than this are filled by ``tin`` without a contest: a rim of a
        few pixels withholds one or two, too few to rank methods, and every method is
        within the noise there. Default 4.
    auto_folds : int
        Cross-validation folds of the contest: each withholds the error estimate's
        sectors, rotated by ``holdout_every / auto_folds`` sectors (two folds: two
        perpendicular pairs of arcs, half the rim in all), so that a feature crossing the
        hole (a ridge, a break line) is withheld in one of them. Default 2.
    auto_z : float
        The first candidate (the reference, ``natural`` by default) fills a component unless another
        predicts its withheld rim better by more than ``auto_z`` standard errors of the
        paired difference of squared errors (:func:`~pipeline.fill.region.pick`); 2 is
        the usual 95 % one. On a rim of tree crowns every method misses by metres and the
        ranking is noise; the reference never overshoots the rim. Default 2.
    auto_rough_rim : float
        z units: a component whose rim heights scatter about their best plane by more than
        this (RMS) has a rough rim, several surfaces side by side (crowns, roofs, the ground
        between); ``tin``, where it is a candidate, is then its reference instead of the first
        one. Deep in such a hole the nearest rim pixels (``natural``'s neighbours) say little
        more than any others, and the harmonic fill, an average of the whole rim weighted by how
        near each part is, strays least; on a smooth rim (terrain, one roof) the nearest pixels
        carry the surface's trend in, and the first candidate stays. The pipeline passes the
        height-jump threshold (``holes.jump_threshold_m``: a step between surfaces). Default
        ``inf``: never.
    spline_tension, spline_smoothing : float
        Regularized spline with tension (``spline``, :mod:`.scattered`): tension for
        coordinates normalised by the support's extent, and smoothing (the diagonal
        added to the kernel matrix). Defaults 40 and 0.1, those of GRASS ``v.surf.rst``.
    spline_max_points : int
        The spline's support is thinned on a lattice to at most this many points (a
        dense solve, cubic in the points). Default 400.
    seam_gamma, seam_iterations, seam_width_px
        Defaults of :func:`smooth_seams` ([OPEN] 3.4 eq. 5): 0.5, 10, 3.
    estimate_error : bool
        Compute the leave-boundary-out error estimate of each component (a second
        fill; doubles the cost). Default False.
    holdout_sectors, holdout_every : int
        Leave-boundary-out: the rim is cut into ``holdout_sectors`` angular sectors
        around the component's centroid and every ``holdout_every``-th one is
        withheld. Defaults 8 and 4 (a quarter of the rim, in two opposite arcs).
    """

    mls_k: int = 8
    mls_order: int = 2
    mls_weight: str = "wendland"
    mls_radius_factor: float = 2.5
    mls_min_radius_px: float = 4.5
    mls_min_points: int = 10
    mls_band_fraction: float = 0.1
    mls_drop_tolerance: float = 1e-6
    mls_frame: str = "horizontal"
    mls_dense_band_px: float = 8.0
    mls_lattice_step_px: int = 4
    tin_order: int = 2
    tin_direct_max_px: int = 6000
    tin_band_px: int = 4
    tin_lattice_px: int = 6
    idw_k: int = 12
    idw_power: float = 2.0
    flat_percentile: float = 10.0
    flat_level: float | None = None
    auto_mls_min_px: int = 0
    auto_mls_min_roundness: float = 0.5
    auto_candidates: tuple[str, ...] = ("natural", "tin")
    auto_contest_min_px: int = 4
    auto_folds: int = 2
    auto_z: float = 2.0
    auto_rough_rim: float = math.inf
    spline_tension: float = 40.0
    spline_smoothing: float = 0.1
    spline_max_points: int = 400
    seam_gamma: float = 0.5
    seam_iterations: int = 10
    seam_width_px: float = 3.0
    estimate_error: bool = False
    holdout_sectors: int = 8
    holdout_every: int = 4

    def __post_init__(self) -> None:
        _positive_int(
            self,
            "mls_k",
            "mls_min_points",
            "mls_lattice_step_px",
            "tin_lattice_px",
            "idw_k",
            "seam_iterations",
            "holdout_sectors",
            "holdout_every",
            "auto_contest_min_px",
            "auto_folds",
            "spline_max_points",
        )
        unknown = [m for m in self.auto_candidates if m not in _CANDIDATES]
        if unknown or len(set(self.auto_candidates)) != len(self.auto_candidates):
            raise ValueError(
                f"FillSettings.auto_candidates must be distinct methods of {list(_CANDIDATES)}, got {self.auto_candidates!r}"
            )
        if not (self.spline_smoothing >= 0 and math.isfinite(self.spline_smoothing)):
            raise ValueError(
                f"FillSettings.spline_smoothing must be a finite number >= 0, got {self.spline_smoothing!r}"
            )
        _choice(self, "mls_order", (0, 1, 2))
        _choice(self, "tin_order", (1, 2))
        _choice(self, "mls_weight", _WEIGHTS)
        _choice(self, "mls_frame", _FRAMES)
        for name in (
            "mls_radius_factor",
            "mls_min_radius_px",
            "idw_power",
            "spline_tension",
            "auto_z",
            "mls_band_fraction",
            "mls_drop_tolerance",
        ):
            if not (getattr(self, name) > 0 and math.isfinite(getattr(self, name))):
                raise ValueError(f"FillSettings.{name} must be a finite number > 0, got {getattr(self, name)!r}")
        for name in ("mls_dense_band_px", "seam_width_px", "tin_band_px", "tin_direct_max_px", "auto_mls_min_px"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"FillSettings.{name} must be >= 0, got {getattr(self, name)!r}")
        if not 0 < self.seam_gamma < 1:
            raise ValueError(f"FillSettings.seam_gamma must be in (0, 1) ([OPEN] eq. 5), got {self.seam_gamma!r}")
        if not 0 <= self.flat_percentile <= 100:
            raise ValueError(f"FillSettings.flat_percentile must be in [0, 100], got {self.flat_percentile!r}")
        if not self.auto_mls_min_roundness >= 0:
            raise ValueError(f"FillSettings.auto_mls_min_roundness must be >= 0, got {self.auto_mls_min_roundness!r}")

    @property
    def weight_code(self) -> int:
        """Index of ``mls_weight`` for the compiled kernel."""
        return _WEIGHTS.index(self.mls_weight)


def _positive_int(obj: object, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        if not (isinstance(value, (int, np.integer)) and value > 0):
            raise ValueError(f"FillSettings.{name} must be an integer > 0, got {value!r}")


def _choice(obj: object, name: str, allowed: tuple) -> None:
    if getattr(obj, name) not in allowed:
        raise ValueError(f"FillSettings.{name} must be one of {list(allowed)}, got {getattr(obj, name)!r}")


@dataclass(frozen=True)
class ComponentFill:
    """How one connected component of the region was filled.

    Attributes
    ----------
    label : int
        Component label (as in ``FillOutcome.labels``).
    n_pixels : int
        Pixels in the component (barrier pixels excluded).
    method : str
        Method actually used (``auto`` resolved), or ``"none"`` when nothing could be done.
    filled : bool
        False when the component had no support at all (left NaN, code 255).
    degraded : bool
        The method had to fall back: MLS with a lower order or a widened support.
        (A large ``tin`` component on the reduced system is not degraded; ``detail``
        says so.)
    n_support : int
        Measured pixels used as support (rim pixels, plus their neighbours for
        ``mls``/``idw``).
    order : int
        Polynomial order reached by MLS (lowest over the component), fairing order of
        ``tin``; 0 for the other methods.
    error_estimate : float
        Leave-boundary-out RMSE (height units) when ``estimate_error``; NaN otherwise.
    level : float
        The level of a ``flat`` fill; NaN otherwise.
    detail : str
        Why it was degraded, in words ("" when not).
    """

    label: int
    n_pixels: int
    method: str
    filled: bool
    degraded: bool = False
    n_support: int = 0
    order: int = 0
    error_estimate: float = math.nan
    level: float = math.nan
    detail: str = ""


@dataclass(frozen=True)
class FillOutcome:
    """Result of :func:`fill_region`.

    Attributes
    ----------
    heights : ndarray of shape (M, N)
        The input heights with the region filled; NaN where it could not be filled.
        Same float dtype as the input (float64 for integer input).
    method_code : ndarray of uint8, shape (M, N)
        ``0`` untouched, :data:`METHOD_CODES` value of the method that filled a pixel,
        ``255`` region pixel that could not be filled.
    labels : ndarray of int32, shape (M, N)
        Component label of every region pixel (0 elsewhere, and on barrier pixels).
    components : tuple of ComponentFill
        One record per component, in label order.
    """

    heights: np.ndarray
    method_code: np.ndarray
    labels: np.ndarray
    components: tuple[ComponentFill, ...] = field(default_factory=tuple)

    def component(self, label: int) -> ComponentFill:
        """The record of component ``label``."""
        for rec in self.components:
            if rec.label == label:
                return rec
        raise KeyError(f"no component with label {label}")
