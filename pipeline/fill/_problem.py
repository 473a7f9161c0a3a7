"""The validated fill problem shared by every method, and the support-point helpers.

A *component* is a 4-connected set of region pixels (or a caller-given label). Its
*rim* is the set of support pixels 4-adjacent to it: the measured boundary from which
every method fills ([MLS] 2.1 step 2, the hole boundary; [OPEN] 3.3, the fixed
boundary of the fairing).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.ndimage as ndi
from scipy.spatial import cKDTree

from .settings import FillSettings

CROSS = ndi.generate_binary_structure(2, 1)
SHIFTS = ((1, 0), (-1, 0), (0, 1), (0, -1))


@dataclass(frozen=True)
class Problem:
    """Arrays of one :func:`fill_region` call, validated and in float64.

    Attributes
    ----------
    heights : ndarray of float64
        Input heights, NaN on region pixels.
    labels : ndarray of int32
        Component label of region pixels to fill (0 elsewhere and on barriers).
    support : ndarray of bool
        Pixels usable as support: finite, outside the region, not on a barrier and
        allowed by the caller's ``support`` mask.
    n_labels : int
        Highest label.
    pixel_size : float
        Pixel size in survey units.
    settings : FillSettings
    """

    heights: np.ndarray
    labels: np.ndarray
    support: np.ndarray
    n_labels: int
    pixel_size: float
    settings: FillSettings

    @cached_property
    def labelled(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rows, columns and labels of the labelled pixels, in row-major order (as ``np.nonzero``).

        Found once per problem: a fill window is mostly unlabelled, and the rims, sizes and
        centroids of its components were each a pass over the whole window (1,415 passes for a
        211 M-point survey's holes). The arrays must not be changed, nor ``labels`` after this.
        """
        rows, cols = np.nonzero(self.labels)
        return rows, cols, self.labels[rows, cols]

    def sizes(self) -> np.ndarray:
        """Pixels per label (index = label; index 0 counts the unlabelled pixels)."""
        label = self.labelled[2]
        sizes = np.bincount(label, minlength=self.n_labels + 1)
        sizes[0] = self.labels.size - len(label)
        return sizes

    def centroids(self) -> np.ndarray:
        """Row and column of every label's centroid, shape ``(n_labels, 2)``.

        The values of ``ndi.center_of_mass(ones, labels, 1..n)``, summed over the labelled
        pixels alone in the same order, so bit for bit the same; a window's unlabelled
        pixels cost one pass instead of three weighted sums (a quarter of a 42 M-point
        survey's fill stage).
        """
        rows, cols, label = self.labelled
        count = np.bincount(label, minlength=self.n_labels + 1)[1:]
        row_sum = np.bincount(label, weights=rows.astype(np.float64), minlength=self.n_labels + 1)[1:]
        col_sum = np.bincount(label, weights=cols.astype(np.float64), minlength=self.n_labels + 1)[1:]
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.column_stack([row_sum / count, col_sum / count])

    def slices(self) -> list:
        """Bounding box of every label (``ndi.find_objects``)."""
        return ndi.find_objects(self.labels, max_label=self.n_labels)


def as_bool(name: str, mask: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray | None:
    """Check that an optional mask is a 2-D array of ``shape``; return it as bool."""
    if mask is None:
        return None
    mask = np.asarray(mask)
    if mask.shape != shape:
        raise ValueError(f"`{name}` has shape {mask.shape}, expected the shape of `heights` {shape}")
    return mask.astype(bool, copy=False)


def build_problem(heights, region, *, pixel_size, settings, support=None, barriers=None, labels=None) -> Problem:
    """Validate the public arguments and build a :class:`Problem` (see :func:`fill_region`)."""
    heights = np.asarray(heights)
    if heights.ndim != 2:
        raise ValueError(f"`heights` must be a 2-dimensional array, got {heights.ndim} dimensions")
    if np.ma.isMaskedArray(heights):
        raise TypeError("masked arrays are not supported: set unknown heights to NaN")
    if not (np.isfinite(pixel_size) and pixel_size > 0):
        raise ValueError(f"`pixel_size` must be a finite number > 0, got {pixel_size!r}")
    if not isinstance(settings, FillSettings):
        raise TypeError(f"`settings` must be a FillSettings, got {type(settings).__name__}")
    shape = heights.shape
    region = as_bool("region", region, shape)
    support = as_bool("support", support, shape)
    barriers = as_bool("barriers", barriers, shape)
    z = heights.astype(np.float64, copy=True)
    z[region] = np.nan
    todo = region if barriers is None else region & ~barriers
    if labels is None:
        lab, n = ndi.label(todo, structure=CROSS)
        lab = lab.astype(np.int32, copy=False)
    else:
        labels = np.asarray(labels)
        if labels.shape != shape or not np.issubdtype(labels.dtype, np.integer):
            raise ValueError(f"`labels` must be an integer array of shape {shape}")
        if np.any(labels[todo] <= 0):
            raise ValueError("`labels` must be > 0 on every region pixel (0 = not a component)")
        lab = np.where(todo, labels, 0).astype(np.int32)
        n = int(lab.max(initial=0))
    usable = np.isfinite(z) & ~region
    if support is not None:
        usable &= support
    if barriers is not None:
        usable &= ~barriers
    return Problem(
        heights=z, labels=lab, support=usable, n_labels=int(n), pixel_size=float(pixel_size), settings=settings
    )


def rim_pairs(problem: Problem, wanted: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(label, flat index of rim pixel) pairs, unique, for every component.

    ``wanted`` (bool per label) restricts the labels considered.
    """
    lab = problem.labels
    h, w = lab.shape
    flat_sup = problem.support.ravel()
    out_l, out_i = [], []
    rows, cols, ll = problem.labelled
    if wanted is not None:
        chosen = wanted[ll]
        rows, cols, ll = rows[chosen], cols[chosen], ll[chosen]
    for dr, dc in SHIFTS:
        r, c = rows + dr, cols + dc
        ok = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        fi = r[ok] * w + c[ok]
        s = flat_sup[fi]
        out_l.append(ll[ok][s])
        out_i.append(fi[s])
    if not out_l:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    key = np.unique(np.concatenate(out_l).astype(np.int64) * (h * w) + np.concatenate(out_i))
    return key // (h * w), key % (h * w)


def fit_plane(rows: np.ndarray, cols: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Least-squares plane ``z = a + b col + c row`` through pixels: ``(a, b, c)``."""
    design = np.column_stack([np.ones(len(z)), cols, rows]).astype(np.float64)
    plane, *_ = np.linalg.lstsq(design, z, rcond=None)
    return plane


def rims_by_label(problem: Problem, labels: np.ndarray) -> dict[int, np.ndarray]:
    """Flat indices of the rim pixels of each component in ``labels``."""
    wanted = np.zeros(problem.n_labels + 1, bool)
    wanted[labels] = True
    rim_l, rim_i = rim_pairs(problem, wanted)
    bounds = np.searchsorted(rim_l, np.arange(problem.n_labels + 2))
    return {int(k): rim_i[bounds[k] : bounds[k + 1]] for k in labels}


def padded_box(sl: tuple[slice, slice], pad: int, shape: tuple[int, int]) -> tuple[slice, slice]:
    """The bounding box ``sl`` grown by ``pad`` pixels, clipped to ``shape``."""
    return (
        slice(max(sl[0].start - pad, 0), min(sl[0].stop + pad, shape[0])),
        slice(max(sl[1].start - pad, 0), min(sl[1].stop + pad, shape[1])),
    )


def support_points(problem: Problem, label: int, rim_flat: np.ndarray, k: int, min_reach: int = 0) -> np.ndarray:
    """Flat indices of the support points of one component: its rim plus the ``k``
    nearest measured neighbours of every rim pixel ([MLS] 2.1 step 3).

    Neighbours are searched in a band grown from the rim through support pixels only
    (a geodesic dilation), so they never reach across a barrier or a non-support pixel.
    With ``min_reach`` wider than the k-neighbour band, the band of that width (thinned
    to a lattice beyond the k-neighbour band) is the support (large holes need a thick rim to fix a quadratic, see ``mls.py``).
    """
    if len(rim_flat) == 0 or k <= 0:
        return rim_flat
    h, w = problem.labels.shape
    rr, cc = np.divmod(rim_flat, w)
    base = int(np.ceil(np.sqrt(k))) + 1
    reach = max(base, min_reach)
    box = (
        slice(max(rr.min() - reach, 0), min(rr.max() + reach + 1, h)),
        slice(max(cc.min() - reach, 0), min(cc.max() + reach + 1, w)),
    )
    sup = problem.support[box]
    seed = np.zeros_like(sup)
    seed[rr - box[0].start, cc - box[1].start] = True
    band = ndi.binary_dilation(seed, structure=np.ones((3, 3), bool), iterations=reach, mask=sup)
    br, bc = np.nonzero(band)
    if reach > base:
        # the outer band on a sparser lattice (stride ~ reach / 5): it fixes the broad
        # trend; the k-neighbour band near the rim stays dense
        stride = max(1, reach // 5)
        near = ndi.binary_dilation(seed, structure=np.ones((3, 3), bool), iterations=base, mask=sup)
        keep = near[br, bc] | (((br + box[0].start) % stride == 0) & ((bc + box[1].start) % stride == 0))
        return np.union1d((br[keep] + box[0].start) * w + (bc[keep] + box[1].start), rim_flat)
    if len(br) <= len(rr):
        return rim_flat
    tree = cKDTree(np.column_stack([br, bc]))
    kk = min(k + 1, len(br))
    _, nn = tree.query(np.column_stack([rr - box[0].start, cc - box[1].start]), k=kk)
    pick = np.unique(nn.ravel())
    flat = (br[pick] + box[0].start) * w + (bc[pick] + box[1].start)
    return np.union1d(flat, rim_flat)
